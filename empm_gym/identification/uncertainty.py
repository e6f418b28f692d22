"""How far to trust a fit or a comparison of fits, from the data alone (one place for the noise estimates).

- :func:`measurement_noise`: the depth noise of a recording, as the robust spread of observed points
  about their local surface (a plane through their nearest neighbours). It is the floor below which no
  model can bring a point-to-surface residual.
- :func:`paired_gain_test`: does model B predict held-out frames better than model A by more than the
  frame-to-frame noise explains? A moving-block bootstrap over frames of the paired per-frame
  differences (frames of a recording are correlated, so whole blocks are resampled), with a penalty
  per added parameter. The doctor's "explains more than noise" test is this function.

Assumptions, stated: the per-frame errors of a recording form a stationary, weakly dependent sequence
over the held-out frames (blocks of ``block`` frames capture the dependence), and the frames held out
were never used to fit either model.
"""

from __future__ import annotations

from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ["measurement_noise", "paired_gain_test", "gain_is_significant", "block_bootstrap_indices", "assess_fit", "newton_bootstrap",
           "body_thickness", "grid_resolution", "coarser_grid_scene", "DENSITY_SCALED", "MIN_CELLS_ACROSS"]


def measurement_noise(points: Sequence[np.ndarray], *, k: int = 60, max_points: int = 3000, seed: int = 0) -> float:
    """Robust standard deviation [m] of observed points about their local surface, over all frames given.

    For each (subsampled) point, a plane is fitted to its ``k`` nearest neighbours; the distance of the
    point to that plane is its residual. The median absolute residual / 0.6745 estimates the noise's
    standard deviation. The plane fit absorbs part of the noise when it is comparable with the point spacing
(neighbours are chosen in 3-D): 0.92-1.0x the true sigma for noise up to 0.8x the spacing, 0.82x at 1.5x.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    res = []
    for p in points:
        p = np.asarray(p, np.float64)
        if len(p) <= k:
            continue
        q = p if len(p) <= max_points else p[rng.choice(len(p), max_points, replace=False)]
        _, idx = cKDTree(p).query(q, k=k + 1)
        nb = p[idx[:, 1:]]
        c = nb.mean(1, keepdims=True)
        cov = np.einsum("ski,skj->sij", nb - c, nb - c)
        _, v = np.linalg.eigh(cov)
        n = v[:, :, 0]
        res.append(np.abs(np.einsum("si,si->s", q - c[:, 0], n)))
    if not res:
        raise ValueError("measurement_noise: no frame has enough observed points to estimate the noise")
    return float(np.median(np.concatenate(res)) / 0.6745)


def block_bootstrap_indices(n: int, block: int, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """``[n_boot, n]`` frame indices of a moving-block bootstrap (blocks of ``block`` consecutive frames)."""
    block = int(max(1, min(block, n)))
    starts = rng.integers(0, n - block + 1, size=(n_boot, -(-n // block)))
    idx = (starts[:, :, None] + np.arange(block)[None, None, :]).reshape(n_boot, -1)[:, :n]
    return idx


def paired_gain_test(base: Sequence[float], candidate: Sequence[float], *, added_params: int = 1,
                     penalty_per_param: float = 0.05, block: Optional[int] = None, n_boot: int = 2000,
                     level: float = 0.95, seed: int = 0) -> Dict[str, float]:
    """Held-out gain of ``candidate`` over ``base`` (per-frame errors of the same frames, lower is better).

    Returns ``gain`` (relative: 1 - mean(candidate) / mean(base)), ``gain_abs`` (mean difference, error
    units), ``lower`` / ``upper`` (bootstrap ``level`` interval of the relative gain), ``threshold``
    (``penalty_per_param * added_params``, the relative gain an added parameter must pay for) and
    ``significant``: the whole interval lies above the threshold (a one-sided test of "the gain exceeds the
    penalty" at (1 + level) / 2). A gain whose point estimate clears the penalty but whose interval reaches below
    it is not enough: on the doctor's recordings such marginal gains were what an extra parameter bought on
    recordings without the effect (benchmarks/RESULTS.md).
    """
    a = np.asarray(base, np.float64)
    b = np.asarray(candidate, np.float64)
    if a.shape != b.shape or a.ndim != 1 or len(a) < 2:
        raise ValueError(f"paired_gain_test: need two equal-length per-frame error series of >= 2 frames, got "
                         f"{a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return {"gain": float("nan"), "gain_abs": float("nan"), "lower": float("nan"), "upper": float("nan"),
                "threshold": penalty_per_param * added_params, "significant": False}
    n = len(a)
    block = int(block or max(2, round(n ** (1.0 / 3.0) * 1.5)))
    idx = block_bootstrap_indices(n, block, n_boot, np.random.default_rng(seed))
    ma, mb = a[idx].mean(1), b[idx].mean(1)
    rel = 1.0 - mb / np.maximum(ma, 1e-300)
    lo, hi = np.quantile(rel, [(1.0 - level) / 2.0, 1.0 - (1.0 - level) / 2.0])
    gain = float(1.0 - b.mean() / max(a.mean(), 1e-300))
    thr = float(penalty_per_param * added_params)
    return {"gain": gain, "gain_abs": float(a.mean() - b.mean()), "lower": float(lo), "upper": float(hi),
            "threshold": thr, "significant": gain_is_significant({"gain": gain, "lower": lo, "threshold": thr})}


def gain_is_significant(test: Dict[str, float]) -> bool:
    """The verdict of :func:`paired_gain_test` from its ``gain``, ``lower`` and ``threshold``: the whole interval
    lies above the threshold (a value missing or null, as ``doctor.json`` writes a non-finite one, is NaN)."""
    g, lo, thr = (float("nan") if test.get(k) is None else float(test[k]) for k in ("gain", "lower", "threshold"))
    return bool(np.isfinite(g) and lo > thr and g > thr)


# ---------------------------------------------------------------------------------------------------------
# Uncertainty and identifiability of a fitted material
# ---------------------------------------------------------------------------------------------------------

#: Parameters that enter the equations of motion only divided by the density: scaling E, density,
#: yield_stress and viscosity together leaves every trajectory unchanged (the momentum equation divided by
#: the density; Coulomb friction and the grippers act on velocities). From motion alone, without a force
#: measurement, only their ratios to the density are determined.
DENSITY_SCALED = ("E", "yield_stress", "viscosity")
_UNITS = {"E": "Pa", "yield_stress": "Pa", "viscosity": "Pa s"}
_RATIO_UNITS = {"E": "m^2/s^2", "yield_stress": "m^2/s^2", "viscosity": "m^2/s"}

#: Below this many grid cells across its thinnest part (as :func:`body_thickness` measures it) a body's
#: stiffness is not resolved: a 2.4 cm rope at dx = 2 cm (1.2 cells) fitted E 6.9x too stiff, at dx = 1 cm
#: (2.4 cells) within 5 % (issue 14); a 4 cm rope at dx = 2 cm (2 cells) within 15 % (tests/identification).
MIN_CELLS_ACROSS = 1.5
#: An interval wider than this share of the search box (in the optimiser's coordinates: a factor 3.2 of E
#: when the box is 10x either way) leaves the parameter undetermined: the data do not pin it down. (At 0.5,
#: a factor 10, the one-camera elastic dough's E was reported determined at +58 % with a factor-3.5
#: interval.)
WIDE_INTERVAL = 0.25
#: Below this many cells the fit is flagged as marginal (a warning, the parameter stays determined).
MARGINAL_CELLS_ACROSS = 3.0


def body_thickness(particles: np.ndarray, volumes: Optional[np.ndarray] = None, *, quantile: float = 0.2) -> float:
    """Thickness [m] of a body's thin parts: the ``quantile`` (default the 20th percentile) over the body of
    its local thickness, the diameter of the largest ball inside the body that holds the point.

    Every particle fills a cube of its own volume (side from ``volumes``, but never less than the nearest-neighbour
    distance, so that neighbours' cubes touch), voxelised at a third of that side; for every distance level k of its
    Euclidean distance transform, the balls of radius k around the voxels at least k deep cover the points of local
    thickness >= 2k voxels. For a rope this is its diameter everywhere, for a lump its smallest extent.
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    x = np.asarray(particles, np.float64).reshape(-1, 3)
    if len(x) < 2:
        raise ValueError("body_thickness: need at least 2 particles")
    d, _ = cKDTree(x).query(x, k=2)
    h = float(np.median(d[:, 1]))  # the lattice's spacing: cubes of this side leave no gap between neighbours
    if volumes is not None:
        # a body whose volumes were scaled to a measured volume can be smaller per particle than its lattice: cubes
        # of that side leave gaps, and the porous raster reads thin everywhere (a 2.4 cm rope on a 2.5 mm lattice
        # read 1.8 cm with volumes 2.44 mm on a side; a sampled cylinder as thick, 0.65 cm with volumes 2.18 mm on
        # a side)
        h = max(h, float(np.cbrt(np.median(np.asarray(volumes, np.float64)))))
    # every particle fills the cube of its own volume, rasterised at a third of its side (coarser for large
    # bodies: at most about a million voxels)
    v = max(h / 3.0, float(np.cbrt(np.prod(np.ptp(x, 0) + h) / 1.0e6)))
    h = max(h, 3.0 * v)
    lo = x.min(0) - 3 * v
    idx = np.rint((x - lo) / v).astype(int)
    occ = np.zeros(idx.max(0) + 4, bool)
    for o in np.array(np.meshgrid(*([[-1, 0, 1]] * 3), indexing="ij")).reshape(3, -1).T:
        occ[idx[:, 0] + o[0], idx[:, 1] + o[1], idx[:, 2] + o[2]] = True
    # round off the staircase of the cubes (half a particle spacing), which no inscribed ball reaches
    occ = ndimage.gaussian_filter(occ.astype(np.float32), 1.5) > 0.5
    dist = ndimage.distance_transform_edt(occ)
    local = np.zeros_like(dist)
    for k in np.unique(np.floor(dist[occ] * 2.0) / 2.0):
        # the union of balls of radius k around the voxels at least k deep (a dilation, by distance)
        cover = (ndimage.distance_transform_edt(dist < k) <= k + 1e-9) & occ
        local[cover] = np.maximum(local[cover], 2.0 * k)
    return float(np.quantile(local[occ], quantile) * v)


def grid_resolution(scene):
    """``(resolution, problem, note)`` of a scene's grid for its frame-0 body (:func:`body_thickness`).

    ``resolution``: ``thickness_m``, ``dx_m``, ``cells_across``. ``problem`` (a sentence, or None) when fewer
    than :data:`MIN_CELLS_ACROSS` cells cross the body's thin parts: a fitted stiffness is then not a
    measurement. ``note`` (or None) below :data:`MARGINAL_CELLS_ACROSS` cells: expect a bias of tens of per cent
    (a rope recorded from a simulation 4.8 cells across, fitted 2.0 cells across: E +28 %; 3.2 cells across:
    +8 %; benchmarks/RESULTS.md, session 22).
    """
    thick = body_thickness(scene.particles, scene.volumes)
    dx = float(scene.grid_config().dx)
    cells = thick / dx
    res = {"thickness_m": thick, "dx_m": dx, "cells_across": cells}
    where = f"{cells:.1f} cells of dx = {dx:g} m across the body's thin parts ({thick * 100:.1f} cm)"
    advice = f"--dx {thick / MARGINAL_CELLS_ACROSS:.2g} or finer resolves it"
    if cells < MIN_CELLS_ACROSS:
        return res, (f"the grid is too coarse for the body: {where}, fewer than {MIN_CELLS_ACROSS:g} (a 2.4 cm rope "
                     f"at 1.2 cells fitted E 6.9x too stiff); {advice}"), None
    if cells < MARGINAL_CELLS_ACROSS:
        return res, None, (f"grid: {where}; the stiffness may be biased by tens of per cent (measured on a rope "
                           f"recorded from a simulation 4.8 cells across: fitted 2.0 cells across, E +28 %; 3.2 "
                           f"cells across, +8 %); {advice}")
    return res, None, None


def resolving_dx(scene, refill: Callable[[float], object], *, cells: float = MARGINAL_CELLS_ACROSS,
                 halvings: int = 2) -> Tuple[object, list]:
    """``(scene, levels)``: ``scene`` on a grid cell on which its frame-0 body is at least ``cells`` cells
    across (:data:`MARGINAL_CELLS_ACROSS` unless given): its own cell, halved at most ``halvings`` times, the
    body filled again on each finer cell by ``refill(dx)`` (a scene, or None where it cannot be: the coarser one
    is kept). ``levels``: the :func:`grid_resolution` of every grid looked at, coarsest first.

    The body's thickness is measured again on each finer fill before the cell is halved once more: a body
    filled on a coarse lattice may read thinner than it is (a 2.3 cm rope filled at 1 cm read 1.2 cm, and the
    cell was halved twice, to 80,000 particles, where 5 mm resolves it 4.6 cells across; benchmarks/RESULTS.md,
    session 35; most of that was :func:`body_thickness` rasterising particles whose volumes are smaller than their
    lattice, mended in session 38: it reads 2.3 cm now). A grid too coarse for the body changes how it moves by
    more than many effects do, and a fit reads that as physics: the doctor at dx = 1 cm on ropes 1.9 cells across, recorded by a simulation at 5 mm
    (the same material, no effect), named table friction, a stiffness field and plasticity on 3 of 6 (confidence
    0.77 to 1.00); at 5 mm (4.5 cells across), 0 of 6 (session 34); the doctor asks for 4 cells
    (``doctor.DOCTOR_CELLS_ACROSS``). (:func:`_finer_grid_scene` is the other use of :data:`MARGINAL_CELLS_ACROSS`:
    a variant of an identification's scene, its particles unchanged, for the grid's share of an interval; here the
    body is filled again on the cell chosen.)"""
    levels = [grid_resolution(scene)[0]]
    for _ in range(halvings):
        if levels[-1]["cells_across"] >= cells:
            break
        finer = refill(levels[-1]["dx_m"] / 2.0)
        if finer is None:
            break
        scene = finer
        levels.append(grid_resolution(scene)[0])
    return scene, levels


def _quadratic_features(dz: np.ndarray) -> np.ndarray:
    """[K, 1 + n + n (n + 1) / 2] features of a quadratic in dz [K, n]: 1, dz_i, dz_i dz_j (i <= j)."""
    K, n = dz.shape
    cols = [np.ones(K)] + [dz[:, i] for i in range(n)]
    cols += [dz[:, i] * dz[:, j] * (0.5 if i == j else 1.0) for i in range(n) for j in range(i, n)]
    return np.stack(cols, 1)


def _gradient_hessian(coef: np.ndarray, n: int):
    """(g [..., n], H [..., n, n]) from quadratic coefficients [..., P] of :func:`_quadratic_features`."""
    g = coef[..., 1:1 + n]
    H = np.zeros(coef.shape[:-1] + (n, n))
    k = 1 + n
    for i in range(n):
        for j in range(i, n):
            H[..., i, j] = H[..., j, i] = coef[..., k]
            k += 1
    return g, H


def _design(n: int, step: float) -> np.ndarray:
    """Offsets [K, n] (units of z) around the optimum: the centre, +-step and +-2 step along every axis, and
    +step along every pair of axes (so every second derivative is measured)."""
    rows = [np.zeros(n)]
    for i in range(n):
        for s in (-2, -1, 1, 2):
            e = np.zeros(n)
            e[i] = s * step
            rows.append(e)
    for i in range(n):
        for j in range(i + 1, n):
            e = np.zeros(n)
            e[i] = e[j] = step
            rows.append(e)
    return np.array(rows)


def newton_bootstrap(per_frame: np.ndarray, dz: np.ndarray, *, n_boot: int = 2000, block: Optional[int] = None,
                     seed: int = 0) -> Dict[str, np.ndarray]:
    """Where the loss's minimum lies, and how much that depends on which frames were recorded.

    ``per_frame`` [K, T]: the per-frame loss at K points ``dz`` [K, n] around a fitted optimum (offsets in
    the optimiser's coordinates). A quadratic in dz is fitted to every frame's losses by least squares;
    the mean over frames gives the loss's gradient g and curvature H at the optimum, and the Newton step
    -H^-1 g the minimum of the local model. A moving-block bootstrap over frames (as in
    :func:`paired_gain_test`) repeats this on resampled frames. Where a resample's curvature is not positive
    along a direction, the minimum is unbounded along it: the parameters that direction moves (by more
    than 0.3 of its unit vector) get +-inf.

    Returns ``step`` [n] (the Newton step of all frames), ``H`` [n, n], ``g`` [n], ``draws`` [n_boot, n]
    (Newton steps of the resamples), ``g_draws`` [n_boot, n] and ``H_draws`` [n_boot, n, n] (the resamples'
    gradients and curvatures), ``residual`` (rms misfit of the quadratic relative to the spread of the mean loss
    over the design).
    """
    L = np.asarray(per_frame, np.float64)
    dz = np.asarray(dz, np.float64)
    K, T = L.shape
    n = dz.shape[1]
    Phi = _quadratic_features(dz)
    if K < Phi.shape[1]:
        raise ValueError(f"newton_bootstrap: {K} design points cannot determine a quadratic in {n} parameters")
    coef, *_ = np.linalg.lstsq(Phi, L, rcond=None)  # [P, T]
    mean_L = L.mean(1)
    fit = Phi @ coef.mean(1)
    spread = float(np.ptp(mean_L)) or 1e-300
    residual = float(np.sqrt(np.mean((fit - mean_L) ** 2)) / spread)
    rng = np.random.default_rng(seed)
    block = int(block or max(2, round(T ** (1.0 / 3.0) * 1.5)))
    idx = block_bootstrap_indices(T, block, n_boot, rng)
    c_all = coef.mean(1)[None]
    c_b = coef.T[idx].mean(1)  # [n_boot, P]
    g, H = _gradient_hessian(np.concatenate([c_all, c_b]), n)
    steps = np.empty((len(g), n))
    for b in range(len(g)):
        w, V = np.linalg.eigh(H[b])
        proj = V.T @ g[b]
        s = np.zeros(n)
        unbounded = np.zeros(n)
        for k in range(n):
            if w[k] > 1e-12 * max(1.0, np.abs(w).max()):
                s -= proj[k] / w[k] * V[:, k]
            else:  # no minimum along V[:, k]: downhill without end
                direction = -np.sign(proj[k]) or 1.0
                unbounded += direction * V[:, k] * (np.abs(V[:, k]) > 0.3)
        s[unbounded != 0] = np.sign(unbounded[unbounded != 0]) * np.inf
        steps[b] = s
    return {"step": steps[0], "g": g[0], "H": H[0], "draws": steps[1:], "g_draws": g[1:], "H_draws": H[1:],
            "residual": residual}


def assess_fit(result, scene, observations, *, level: float = 0.95, step: float = 0.1, n_boot: int = 2000,
               resample_bodies: int = 2, seed: int = 0, objective=None, other_bodies: Sequence = (),
               body_note: Optional[str] = None, refine_grid: bool = True) -> Dict:
    """Uncertainty intervals and identifiability of a :class:`~.offline.FitResult`, from the data alone.

    Method (stated): the fitted scene is simulated once more with the fitted parameters moved by
    +-``step`` and +-2 ``step`` along each optimiser coordinate (log of E, density, yield stress, ...; the
    logit of nu) and along each pair, as worlds of one batched simulation over the fitted frames. The
    per-frame losses give, through :func:`newton_bootstrap`, the distribution of the loss's minimum over
    resamples of the recorded frames. The same is repeated with the frame-0 body sampled by
    ``resample_bodies`` other particle lattices (each particle moved by up to half a spacing), and the
    ``level`` interval of every parameter is the quantile range of all these minima together: noise in the
    recording plus the discretisation of the body. ``other_bodies`` (``[(label, Scene or None)]``, from
    :func:`~.data.view_jackknife_bodies`: the frame-0 body rebuilt with one camera left out at a time) add the
    share of the body's reconstructed *shape*: the same probes run on each, and their minima are pooled with
    the rest, so the interval spans how far the fit moves when one view less shapes the body (conservative:
    a body from fewer views is worse than the one fitted; for a single-view completion, the body completed about
    its half-turn axis moved by a pixel either way). Without them the shape is taken as given,
    and a warning says so quoting ``body_note`` (how the body was built) when given; with only the axis's
    variants, the warning says that the prior itself is taken as given. With
    ``refine_grid``, a grid too coarse to resolve the body well (fewer than :data:`MARGINAL_CELLS_ACROSS` cells
    across its thin parts, but at least :data:`MIN_CELLS_ACROSS`) adds the grid's share the same way: the
    probes run once more on a grid of that many cells across (at most 1 / 0.6 times finer, and only while the
    particles still fill it at 8 or more per cell), so the interval spans how far the minimum moves when the
    grid resolves the body (the one-camera rope at 2.2 cells fitted E 5.7 % low, outside an interval that
    held only noise and lattices). A grid that resolves the body (at least that many cells) adds its share on a
    grid :data:`COARSER_GRID` times coarser, while the body keeps :data:`MIN_CELLS_ACROSS` cells there
    (:func:`coarser_grid_scene`): three cells across is not convergence (``empm synth``'s rope at 3.4 cells
    fitted E 7 % low, outside an interval of noise, lattices and views alone). The fitted body's loss is also
    split in halves (:data:`SPLITS`): the depth's and the tracks' terms (where it has both), the first and the
    second half of the fitting frames; each half alone gives its own interval (``identifiability.splits``), and
    where a pair's do not overlap, a warning says why they may disagree (a tracker's or a segmenter's error, a
    wrong body, the Chamfer's own bias; a model that does not hold alike over the recording) and the interval
    spans both (its width then decides whether the value is determined). The quadratic about the fit sees one
    basin only: up to :data:`MAX_FAR` members of the fit's own search (CMA-ES's) far from the fit and nearly as good
    (:func:`_far_members`) are simulated again on the fitted body and compared with the fit frame by frame
    (:func:`paired_gain_test`); one the frames cannot tell from the fit joins the interval, and says so (seed 25's
    dough squeezed and lifted with a tracker's and a segmenter's errors moved from E = 15.2 to 56.1 kPa when 1.3 %
    of its track entries were left out, session 86, and was then reported "determined" within 9 %). A fit without
    such a search (Adam's descent from one start) is scanned across its box instead: :data:`SCAN_POINTS` values of
    each parameter, the others at the fit (:func:`_scan_points`), simulated beside the probes; those within
    :data:`FAR_LOSS` of the fit's loss are compared with it as the far members are. It assumes
    the model is right up to noise that is stationary and weakly dependent over frames (blocks of frames
    are resampled); the grid's resolution is checked separately.

    A parameter is ``determined: false`` (with the reasons in ``identifiability.warnings``) when it lies at
    its search bound, when its interval reaches past the search box or spans more than
    :data:`WIDE_INTERVAL` of it (the loss is flat, or nearly, within noise along it), when it is correlated with another fitted parameter by more than 0.95 (only a combination is
    determined), when it is E / yield_stress / viscosity fitted together with the density (only their
    ratio to the density enters the motion), or when the grid has fewer than :data:`MIN_CELLS_ACROSS` cells
    across the body's thinnest part.

    Returns ``{"uncertainty": {param: {"interval", "level", "determined", "bounded_only"}}, "identifiability":
    {...}}``, both for the material file's ``fit`` section; ``bounded_only`` is "upper" or "lower" where the
    interval runs out of the search box on one side only (:func:`one_sided_bound`), else None.
    """
    from .data import AXIS_VARIANT, SAME_BODY, TRIMMED_BODY
    from .offline import Objective, default_bounds
    from .problem import ParamSpace, _ForwardSim, run_together

    names = list(result.params)
    n = len(names)
    bounds = {k: tuple(v) for k, v in (result.extra.get("bounds") or default_bounds(result.init)).items()}
    space = ParamSpace(names, bounds)
    F = int(result.frames_used)
    if objective is None:
        obs_model = result.extra.get("observation") or ("surface" if observations.surface else "particles")
        objective = Objective(scene, observations, F, observation=obs_model, **result.extra.get("objective", {}))
    z0 = space.to_z(result.params)
    dz = _design(n, step)
    far = _far_members(result, space, z0)  # simulated beside the fitted body's probes: another basin?
    # a fit without a search population of its own (Adam's descent from one start) is looked at across its box
    scan = [] if result.extra.get("population") else _scan_points(space, z0)
    cand = [space.from_z(z0 + d) for d in dz]
    base = result.material
    mu0 = result.friction if result.friction is not None else scene.table_friction
    mats = [space.material(c, base, mu0) for c in cand]
    # the fit, then the far members, then the scan's values
    far_worlds = (mats[:1] + [space.material(m, base, mu0) for m, _ in far]
                  + [space.material(space.from_z(z), base, mu0) for z in scan])
    rng = np.random.default_rng(seed)
    draws_all, curv_all, diverged, nbs, labels = [], [], [], [], []
    variants = [("fitted body", scene)] + [(f"lattice {b}", None) for b in range(1, 1 + int(resample_bodies))]
    variants += [(label, sc) for label, sc in other_bodies if sc is not None]
    skipped = [label for label, sc in other_bodies if sc is None]
    finer = _finer_grid_scene(scene) if refine_grid else None
    if finer is not None:
        variants.append((f"grid dx = {finer.dx:.3g} m", finer))
    coarser = coarser_grid_scene(scene) if refine_grid else None
    coarse_dropped, coarse_curv, coarse_in = False, None, []  # the last: combinations that hold that grid's share
    if coarser is not None:
        variants.append((f"coarser grid dx = {coarser.dx:.3g} m", coarser))
    objs, sims = [], []
    for b, (label, sc) in enumerate(variants):
        obj = objective
        if b > 0:
            if sc is None:  # the same body sampled by another particle lattice: the discretisation's share
                sc = _resampled_body(scene, rng)
            obj = Objective(sc, observations, F, observation=objective.observation, l_dist=objective.l_dist,
                            l_trk=objective.l_trk, chamfer=objective.direction,
                            **{k: v for k, v in result.extra.get("objective", {}).items() if k in ("max_points", "seed")})
        objs.append(obj)
        sims.append(_ForwardSim(sc, [m for m, _ in mats], [mu for _, mu in mats]))
        variants[b] = (label, sc)
    if len(far_worlds) > 1:  # the fit and the far values on the fitted body, apart (a stiffer value's time step is
        # not the probes')
        sims.append(_ForwardSim(scene, [m for m, _ in far_worlds], [mu for _, mu in far_worlds]))
    # every body's and grid's probes advanced together (side by side on a GPU; one after the other on a CPU)
    runs = run_together([sim.steps(F, queued=True) for sim in sims])
    far_tests = []  # (values in optimiser coordinates, the fit's gain over them, where they came from)
    if len(far_worlds) > 1:
        Xf, _, _ = runs.pop()
        Lf = np.stack([objective.per_frame(Xf[:, w]) for w in range(Xf.shape[1])])[:, objective.seen[1:F]]
        # each far value against the fit on the same frames: is the fit better? (one that diverged, or whose loss
        # is not finite, is no rival; a scan's value whose loss is not within FAR_LOSS of the fit's is not tested)
        zs = [(space.to_z(m), "search") for m, _ in far] + [(z, "scan") for z in scan]
        far_tests = [(z, paired_gain_test(Lm, Lf[0], added_params=0, seed=seed), src)
                     for (z, src), Lm in zip(zs, Lf[1:]) if np.all(np.isfinite(Lm))
                     and (src == "search" or np.mean(Lm) <= (1.0 + FAR_LOSS) * np.mean(Lf[0]))]
    for b, ((label, sc), obj, (X, div, _)) in enumerate(zip(variants, objs, runs)):
        diverged += div
        terms = [obj.per_frame_terms(X[:, w]) for w in range(len(cand))]  # (depth, tracks or None) per world
        L = np.stack([d if t is None else d + t for d, t in terms])  # Objective.per_frame's
        L = L[:, obj.seen[1:F]]  # a frame without observed points is not scored
        nb = newton_bootstrap(L, dz, n_boot=n_boot, seed=seed + b)
        nbs.append(nb)
        labels.append(label)
        if b == 0:
            splits = _splits(obj, terms, obj.seen[1:F], dz, n_boot=n_boot, seed=seed)
        if sc is coarser is not None and (not np.all(np.isfinite(nb["step"])) or
                                          np.mean(~np.all(np.isfinite(nb["draws"]), 1)) > (1.0 - level) / 2.0):
            # the grid's share is how far the minimum moves; where the coarser grid's loss has none (or its own
            # interval is open), no shift is measured: its runaway draws say only that that grid is too coarse
            coarse_dropped = True
            # a ridge's Newton steps run off on any grid: along the combination it shares, this grid may still
            # place the minimum (pair_combination decides)
            coarse_curv = (nb["g_draws"], nb["H_draws"])
            continue
        draws_all.append(nb["draws"])
        curv_all.append((nb["g_draws"], nb["H_draws"]))
    nb = nbs[0]
    pooled = np.concatenate(draws_all)
    G, Hs = (np.concatenate(x) for x in zip(*curv_all))  # every kept body's resamples' gradients and curvatures
    shape_note = None
    n_shape = len(other_bodies) - len(skipped)  # bodies rebuilt from other views or completions
    axis_only = n_shape > 0 and all(label.startswith(AXIS_VARIANT) for label, sc in other_bodies if sc is not None)
    if n_shape == 0 and body_note:
        shape_note = (f"the frame-0 body's shape is taken as given ({body_note}): the interval does not include "
                      f"an error in its shape")
    elif axis_only:
        shape_note = (f"the frame-0 body's hidden side is the stated prior's ({body_note or 'single-view completion'})"
                      f": the interval includes where the views place its axis, not an error of the prior itself")
    q = [(1.0 - level) / 2.0, 1.0 - (1.0 - level) / 2.0]
    warnings, reasons = [], {k: [] for k in names}
    # another basin, or halves of the loss that put k apart (SPLITS): why it is not determined, where it is not
    disagree = {k: [] for k in names}
    unc = {}
    draws = z0[None] + pooled
    # one z-step as a fraction of the box: "at the bound" means within 2 % of the box's z-width of an end
    for i, k in enumerate(names):
        lo_z, hi_z = _quantiles(draws[:, i], q)
        # every resample's minimum ran off one way: the interval is open on that side and ends at the fit
        if np.isneginf(hi_z):
            hi_z = z0[i]
        if np.isposinf(lo_z):
            lo_z = z0[i]
        for zm, test, src in far_tests:
            if not test["significant"] and not lo_z <= zm[i] <= hi_z:
                # a value the search evaluated (or the scan) fits these frames within their noise as well as the
                # fit: the loss has another basin (or a flat stretch) there that the quadratic about the fit does
                # not see
                disagree[k].append(_basin_words(space, k, zm, test, q, src))
                lo_z, hi_z = min(lo_z, zm[i]), max(hi_z, zm[i])
        for split, halves in splits.items():
            apart = _halves_apart(space, k, i, z0, split, halves, q)
            if apart:
                # two halves of the loss put the minimum in places the frames' noise does not join: the depth and
                # the tracks (a tracker's, a segmenter's, the body's error, the Chamfer's own bias), or the early
                # and the late frames (a model that does not hold alike); the bootstrap over frames sees none of
                # it. The interval spans both, and its width decides, as for any other.
                disagree[k].append(apart["warning"])
                lo_z, hi_z = min(lo_z, *apart["lo_z"]), max(hi_z, *apart["hi_z"])
        interval = [_from_z(space, k, lo_z), _from_z(space, k, hi_z)]
        reasons[k] += box_reasons(space, k, z0[i], z0[i] + nb["step"][i], lo_z, hi_z, level=level)
        unc[k] = {"interval": interval, "level": level, "determined": True,
                  "bounded_only": one_sided_bound(space, k, lo_z, hi_z)}
    # correlations between fitted parameters (finite draws only)
    corr, combos, curv_corr = {}, {}, {}
    fin = np.all(np.isfinite(pooled), 1)
    C = np.corrcoef(pooled[fin].T) if n > 1 and fin.sum() > 10 else None
    for i in range(n):
        for j in range(i + 1, n):
            pair = f"{names[i]},{names[j]}"
            if C is not None:
                corr[pair] = float(C[i, j]) if np.isfinite(C[i, j]) else 0.0
            r = corr.get(pair, 0.0)
            # the loss's own curvature couples them as strongly (or is a saddle: no minimum of the two together):
            # where most resamples' minima run off, the few finite ones give no steady correlation (the dough
            # squeezed and lifted with a slip: r = 1.00 in one run, 0.75 in the next, the same fit)
            hii, hjj, hij = nb["H"][i, i], nb["H"][j, j], nb["H"][i, j]
            rc = float(-hij / np.sqrt(hii * hjj)) if hii > 0.0 and hjj > 0.0 else 0.0
            curv_corr[pair] = rc
            # the curvature decides where the draws cannot: a saddle, or most resamples' minima running off
            if abs(r) <= CORRELATED and not (abs(rc) > CORRELATED and (abs(rc) > 1.0 or fin.mean() < 0.5)):
                continue
            said = (f"r = {r:+.2f}" if abs(r) > CORRELATED else
                    (f"r = {r:+.2f} over the {fin.mean():.0%} of resamples that place a minimum" if pair in corr
                     else "too few resamples place a minimum to correlate them")
                    + f", {rc:+.2f} from the loss's curvature at the fit"
                    + (" (a saddle: no minimum of the two together)" if abs(rc) > 1.0 else ""))
            r_used = r if abs(r) > CORRELATED else float(np.clip(rc, -1.0, 1.0))
            # E (or a yield stress, a viscosity) with the density: their ratio, below, is the combination
            by_density = "density" in (names[i], names[j]) and {names[i], names[j]} & set(DENSITY_SCALED)
            pc = None if by_density else pair_combination(
                space, names[i], names[j], z0[[i, j]], nb["H"][np.ix_([i, j], [i, j])], G[:, [i, j]],
                Hs[:, [i, j]][:, :, [i, j]], r_used, level=level,
                rivals=[zm[[i, j]] for zm, test, _ in far_tests if not test["significant"]],
                halves={sp: {h: (m["g_draws"][:, [i, j]], m["H_draws"][:, [i, j]][:, :, [i, j]])
                             for h, m in hv.items()} for sp, hv in splits.items()},
                dropped=None if coarse_curv is None else (coarse_curv[0][:, [i, j]],
                                                          coarse_curv[1][:, [i, j]][:, :, [i, j]]))
            what = "at most a combination of the two is determined"
            if pc is not None:
                name = _power_name(*pc["of"], pc["exponent"])
                combos[name] = pc
                if pc.pop("dropped_pooled", False):
                    coarse_in.append(name)
                if pc["determined"]:
                    what = f"only the combination {name} = {pc['value']:.4g} is determined (see the combinations)"
            for a, b in ((i, j), (j, i)):
                reasons[names[a]].append(f"correlated with {names[b]} ({said}): {what}")
    rho_fitted = "density" in names
    for k in DENSITY_SCALED:
        if k not in names:
            continue
        rho = result.params["density"] if rho_fitted else float(base.density)
        val = result.params[k] / rho
        entry = {"value": val, "unit": _RATIO_UNITS[k], "density_assumed": None if rho_fitted else rho}
        if not rho_fitted:
            entry["interval"] = [v / rho for v in unc[k]["interval"]]
            entry["note"] = (f"density was not fitted (assumed {rho:g} kg/m^3): from motion alone only {k}/density "
                             f"is determined; {k} scales with the assumed density")
        else:
            reasons[k].append(f"fitted together with the density: the motion depends only on {k}/density")
            reasons["density"].append(f"fitted together with {k}: the motion depends only on {k}/density")
            entry["note"] = f"only {k}/density is determined from motion without a force measurement"
        combos[f"{k}/density"] = entry
    resolution, problem, note = grid_resolution(scene)
    if problem:
        for k in names:
            reasons[k].append(problem)
    elif note:
        warnings.append(note)
    if diverged:
        warnings.append(f"{len(diverged)} of {len(cand) * len(variants)} probe simulations diverged: the interval "
                        f"is approximate")
    for label in skipped:
        if label.endswith(SAME_BODY):  # the trim would remove almost nothing: no share is left out
            continue
        if label.startswith(TRIMMED_BODY):
            warnings.append(f"the frame-0 body could not be rebuilt as the {label}: the interval leaves out that "
                            f"body's share of the body's shape")
            continue
        warnings.append(f"the frame-0 body could not be rebuilt {label}: the interval leaves out that view's share "
                        f"of the body's shape")
    if shape_note:
        warnings.append(shape_note)
    if coarse_dropped:
        warnings.append(f"on the coarser grid (dx = {coarser.dx:.3g} m) the loss has no minimum near the fit: the "
                        f"interval leaves out the grid's share"
                        + (f" (along {', '.join(coarse_in)} it has one: that combination's interval holds it)"
                           if coarse_in else ""))
    if nb["residual"] > 0.2:
        warnings.append(f"the loss is far from quadratic within +-{2 * step:g} of the optimum (misfit "
                        f"{nb['residual']:.0%}): the intervals are approximate")
    z_min = z0 + np.where(np.isfinite(nb["step"]), nb["step"], 0.0)
    for i, k in enumerate(names):
        lo, hi = unc[k]["interval"]
        if np.all(np.isfinite(nb["step"])) and not (lo <= result.params[k] <= hi) and not reasons[k]:
            warnings.append(f"{k}: the fit stopped at {result.params[k]:.4g}, outside its interval; the loss's "
                            f"local model puts the minimum at {_from_z(space, k, z_min[i]):.4g} (more iterations "
                            f"may help)")
        if reasons[k]:
            unc[k]["determined"] = False
            if hi < space.bounds[k][0] or lo > space.bounds[k][1]:
                # the resamples' minima of a local model that does not fit this loss (or has none: a ridge, a
                # kink) lie wholly outside the box searched: quoted as an interval, they would be a number no data
                # support (the doctor's plastic dough, session 87: E = 38.7 kPa in a box from 19 kPa, with an
                # "interval" of 0 to 0.015 Pa)
                unc[k].update(interval=[_from_z(space, k, -np.inf), _from_z(space, k, np.inf)], bounded_only=None)
                reasons[k].append(f"the loss's local model puts its minimum outside the box searched ({lo:.4g} to "
                                  f"{hi:.4g} over the resamples): no interval is given")
            reasons[k] = disagree[k] + reasons[k]  # a wide interval's first cause, where halves disagree
            warnings += [f"{k}: {r}" for r in reasons[k]]
        else:
            warnings += disagree[k]
    return {"uncertainty": unc,
            "identifiability": {
                "method": (f"moving-block bootstrap over the fitted frames ({n_boot} resamples) of the minimum of a "
                           f"quadratic fitted per frame to the loss at +-{step:g} and +-{2 * step:g} around the "
                           f"optimum (optimiser coordinates: log scale, logit for nu), pooled over the body "
                           f"sampled by {1 + int(resample_bodies)} particle lattices"
                           + (f" and rebuilt from other views or completions ({n_shape} bodies)" if n_shape else "")
                           + (f", and on a finer grid (dx = {finer.dx:.3g} m)" if finer is not None else "")
                           + (f", and on a coarser grid (dx = {coarser.dx:.3g} m)" if coarser is not None
                              and not coarse_dropped else "")
                           + "".join(f"; checked against {' and '.join(SPLITS[sp][0])} alone" for sp in splits)
                           + (f"; {len(far)} members of the fit's search far from it tested against it"
                              if far else "")
                           + (f"; each value scanned across its search box ({len(scan)} values, the others at "
                              f"the fit), those within {FAR_LOSS:.0%} of the fit's loss tested against it"
                              if scan else "")
                           + "; assumes the model is right up to stationary, weakly dependent noise"
                           + ("" if n_shape else " and the frame-0 body's shape")),
                # per body: where the loss's local model puts the minimum (None: it has none, the loss runs on)
                "body_minima": ({lab: (_from_z(space, names[0], z0[0] + m["step"][0]) if np.isfinite(m["step"][0])
                                       else None)
                                 for lab, m in zip(labels, nbs)} if n == 1 else None),
                # where each half of the loss (SPLITS) alone puts each value: {split: {param: {half: interval}}}
                "splits": {sp: {k: {h: [_from_z(space, k, z0[i] + v) for v in _quantiles(m["draws"][:, i], q)]
                                    for h, m in halves.items()} for i, k in enumerate(names)}
                           for sp, halves in splits.items()},
                "warnings": warnings, "combinations": combos, "correlation": corr,
                # the same from the fitted body's curvature at the fit (Laplace: -H_ij / sqrt(H_ii H_jj); beyond +-1
                # a saddle)
                "curvature_correlation": curv_corr, "resolution": resolution,
                "curvature": nb["H"].tolist(), "quadratic_misfit": nb["residual"]}}


#: Above this correlation of two fitted parameters' minima over the resamples, neither is determined alone.
CORRELATED = 0.95


def _power_name(a: str, b: str, p: float) -> str:
    """``b * a^p`` written for a reader: "yield_stress/E", "viscosity/E^0.5", "grip_friction*E^2"."""
    if p == -1.0:
        return f"{b}/{a}"
    if p == 1.0:
        return f"{b}*{a}"
    return f"{b}/{a}^{-p:g}" if p < 0 else f"{b}*{a}^{p:g}"


def _power_unit(ua: str, ub: str, p: float) -> str:
    """SI unit of ``b * a^p`` from the parameters' units ("-" for none)."""
    if ua == ub:
        return "-" if 1.0 + p == 0.0 else (ua if 1.0 + p == 1.0 else f"{ua}^{1.0 + p:g}")
    if ua == "-":
        return ub
    pa = ua if p == 1.0 else f"{ua}^{p:g}"
    return pa if ub == "-" else f"{ub} {pa}"


def pair_combination(space, a: str, b: str, z_fit: Sequence[float], H: np.ndarray, g_draws: np.ndarray,
                     H_draws: np.ndarray, r: float, *, level: float = 0.95, rivals: Sequence = (),
                     halves: Optional[Dict[str, Dict[str, tuple]]] = None,
                     dropped: Optional[tuple] = None) -> Optional[dict]:
    """The combination of two correlated log-scale parameters ``a`` and ``b`` that the frames fix.

    Two correlated values lie on a ridge of the loss: along it the loss is flat (or falls: a yield stress and E
    where the frames show where yield begins but not the stiffness, whose resamples' Newton steps run off to
    infinity), across it the loss is curved. The direction across it is the stiffer eigenvector of ``H`` (the
    all-frames curvature of the pair, [2, 2], in the optimiser's coordinates of ``space``, a
    :class:`~.problem.ParamSpace`): on log scales, the power law ``b * a^p`` in SI units that stays constant
    along the ridge, with ``a`` and ``b`` swapped where that keeps ``|p|`` at most 1 (the parameter that weighs
    most in it leads: the demo's slip gave "grip_friction*E^5" before, now "E*grip_friction^0.25"). ``p`` is snapped to a quarter where the curvature across is at least 1 / 1.25^2 of the
    stiffest (the interval at most a quarter wider), else rounded to two decimals. Each resample (gradients
    ``g_draws`` [m, 2] and curvatures ``H_draws`` [m, 2, 2], :func:`newton_bootstrap`'s, pooled over bodies)
    puts the loss's minimum along that direction from the fit ``z_fit`` somewhere: the ``level`` interval of the
    combination there (a resample with no curvature along it runs off: an open end). ``rivals`` ([z_a, z_b] each):
    values the frames cannot tell from the fit (:func:`_far_members` that :func:`paired_gain_test` could not set
    apart); the interval reaches each one's combination too (the demo's slip had E*grip_friction^0.25 "determined"
    at 10.0 to 16.0 kPa against a true 16.7, while its search's E = 23.2 kPa and grip friction 0.66, as good a
    fit, put it at 20.9). ``halves`` (``{split: {half: (g_draws, H_draws)}}``, the pair's resamples of each half of
    the loss, :data:`SPLITS`) each put the combination somewhere the same way; where a split's two halves put it in
    intervals that do not overlap (the ends that face each other closed and within the values the box spans), the
    interval spans both and the note says why they may disagree, as for a value alone (:func:`_halves_apart`).
    ``dropped`` (``(g_draws, H_draws)``): the resamples of a body left out of the values' intervals because the
    loss has no minimum near the fit there (the coarser grid: a ridge's Newton steps run off on it as well); where
    along the combination it has one in all but (1 - ``level``) / 2 of them, it joins the combination's interval
    (``"dropped_pooled"`` True in the result: the combination holds that body's share; the plastic rope pressed at
    full resolution had yield_stress/E "determined" at 0.0375 to 0.0909 without the grid's share, truth 0.0354).

    Along the ridge the loss must not fall: where its curvature along the ridge (the softer direction of ``H``) is
    negative in all but (1 - ``level``) / 2 of the resamples, the fit sits on a saddle short of the ridge's minimum,
    and a bent ridge fixes another value there: not determined (``falls_along_ridge``: that share; the rope squeezed
    and lifted with a slip at full resolution, a saddle with curvatures -0.30 and 1 of the stiffest, had
    grip_friction/E^0.5 "determined" at 0.0068 to 0.0088 against a true 0.0034).

    Returns ``{"value" (at the fit), "interval", "level", "unit", "of", "exponent", "correlation", "determined",
    "note", "splits", "falls_along_ridge"}`` (``of``: [a, b] after the swap, the combination
    ``of[1] * of[0]^exponent``; ``splits``: ``{split: {half: interval}}``); ``determined`` where the
    interval is closed and spans at most :data:`WIDE_INTERVAL` of the leading parameter's search box (log scale):
    the standard it would be held to alone if the other were known. None where either parameter is not on a log
    scale (nu, the stiffness slopes: no power law), the loss is not curved across any direction, or the other's
    power rounds to 0 (then the leader is not correlated with it)."""
    from empm_gym.sim.effects import parameter

    if parameter(a).transform != "log" or parameter(b).transform != "log" or len(g_draws) < 3:
        return None
    H, g_draws, H_draws = (np.asarray(x, float) for x in (H, g_draws, H_draws))
    w, V = np.linalg.eigh(H)
    if not w[1] > 0.0:
        return None
    halves = {sp: {h: tuple(np.asarray(x, float) for x in gh) for h, gh in hv.items()}
              for sp, hv in (halves or {}).items()}
    if dropped is not None:
        dropped = tuple(np.asarray(x, float) for x in dropped)
    if abs(V[0, 1]) > abs(V[1, 1]):  # the combination is mostly a's: a leads (power 1), b's power at most 1
        a, b, z_fit = b, a, np.asarray(z_fit, float)[::-1]
        rivals = [np.asarray(zr, float)[::-1] for zr in rivals]
        H, g_draws, H_draws = H[::-1, ::-1], g_draws[:, ::-1], H_draws[:, ::-1, ::-1]
        halves = {sp: {h: (g[:, ::-1], Hh[:, ::-1, ::-1]) for h, (g, Hh) in hv.items()} for sp, hv in halves.items()}
        if dropped is not None:
            dropped = (dropped[0][:, ::-1], dropped[1][:, ::-1, ::-1])
        w, V = np.linalg.eigh(H)
    p_exact = float(V[0, 1] / V[1, 1])
    across = lambda p: float(np.array([p, 1.0]) @ H @ np.array([p, 1.0])) / (1.0 + p * p)
    p = round(4.0 * p_exact) / 4.0
    if p == 0.0 or across(p) < w[1] / 1.25 ** 2:
        p = round(p_exact, 2)
    if p == 0.0:
        return None
    u = np.array([p, 1.0]) / np.hypot(p, 1.0)
    sa, sb = parameter(a).scale, parameter(b).scale
    # log of b * a^p in SI units at the fit; a step t along u moves it by t * |(p, 1)|
    c_fit = z_fit[1] + np.log(sb) + p * (z_fit[0] + np.log(sa))
    slope = float(np.hypot(p, 1.0))

    def minima(g, Hh):  # each resample's minimum along u, as the combination's log (+-inf: none, it runs off)
        gu, hu = g @ u, np.einsum("i,mij,j->m", u, Hh, u)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(hu > 0.0, -gu / np.where(hu > 0.0, hu, 1.0), np.where(gu > 0.0, -np.inf, np.inf))
        return c_fit + slope * t

    q = [(1.0 - level) / 2.0, 1.0 - (1.0 - level) / 2.0]
    c = minima(g_draws, H_draws)
    pooled_dropped = False
    if dropped is not None:
        cd = minima(*dropped)
        if np.mean(~np.isfinite(cd)) <= (1.0 - level) / 2.0:  # along the combination that body places the minimum
            c, pooled_dropped = np.concatenate([c, cd]), True
    lo, hi = (float(x) for x in _quantiles(c, q))
    at_rivals = [zr[1] + np.log(sb) + p * (zr[0] + np.log(sa)) for zr in rivals]
    lo, hi = min([lo] + at_rivals), max([hi] + at_rivals)
    ia, ib = list(space.names).index(a), list(space.names).index(b)
    box = space.z_hi[ib] - space.z_lo[ib]  # held to b's own standard, as if a were known
    name = _power_name(a, b, p)
    # the values the combination takes over the box's corners: a half's end outside them places nothing
    corners = [zb + np.log(sb) + p * (za + np.log(sa)) for za in (space.z_lo[ia], space.z_hi[ia])
               for zb in (space.z_lo[ib], space.z_hi[ib])]
    split_iv, apart = {}, []
    for sp, hv in halves.items():
        (ha, lo_a, hi_a), (hb, lo_b, hi_b) = ((h, *(float(x) for x in _quantiles(minima(*gh), q)))
                                              for h, gh in hv.items())
        split_iv[sp] = {ha: [lo_a, hi_a], hb: [lo_b, hi_b]}
        if _apart_within(lo_a, hi_a, lo_b, hi_b, min(corners), max(corners)):
            apart.append(f"{ha} alone puts {name} at {np.exp(lo_a):.4g} to {np.exp(hi_a):.4g} and {hb} alone at "
                         f"{np.exp(lo_b):.4g} to {np.exp(hi_b):.4g} ({100 * level:.0f} % intervals): they disagree "
                         f"beyond the frames' noise, so {SPLITS[sp][1]}; its interval spans both")
            lo, hi = min(lo, lo_a, lo_b), max(hi, hi_a, hi_b)
    # along the ridge (the softer direction) the loss must not fall beyond the frames' noise: where it does in all
    # but (1 - level) / 2 of the resamples, the fit sits on a saddle, short of the ridge's minimum, and where the
    # ridge bends (no power law holds it) the combination there is another
    along = V[:, 0]
    falls = float(np.mean(np.einsum("i,mij,j->m", along, H_draws, along) < 0.0))
    saddle = falls > 1.0 - (1.0 - level) / 2.0
    determined = bool(np.isfinite(lo) and np.isfinite(hi) and hi - lo <= WIDE_INTERVAL * box) and not saddle
    lvl = f"{100 * level:.0f} %"
    also = (f" (its interval reaches {len(at_rivals)} value(s) of the fit's search that fit as well)"
            if at_rivals else "")
    if saddle:
        note = (f"{a} and {b} are correlated (r = {r:+.2f}), but along their ridge the loss falls away from the fit "
                f"in {falls:.0%} of the resamples (a saddle): the fit is not the ridge's minimum, and where the ridge "
                f"bends {name} is another there: not determined either")
    elif determined:
        note = f"{a} and {b} are correlated (r = {r:+.2f}): the frames fix {name}, not either alone" + also
    elif not (np.isfinite(lo) and np.isfinite(hi)):
        note = (f"{a} and {b} are correlated (r = {r:+.2f}), and the loss has no minimum along {name} in more than "
                f"{(1.0 - level) / 2.0:.1%} of the resamples: not determined either")
    else:
        note = (f"{a} and {b} are correlated (r = {r:+.2f}), and even {name}'s {lvl} interval spans "
                f"{(hi - lo) / box:.0%} of {b}'s search box (log scale): not determined either" + also)
    if apart:
        note += "; " + "; ".join(apart)
    with np.errstate(over="ignore"):
        interval = [float(np.exp(lo)), float(np.exp(hi))]
        split_iv = {sp: {h: [float(np.exp(x)) for x in iv] for h, iv in hv.items()} for sp, hv in split_iv.items()}
    return {"value": float(np.exp(c_fit)), "interval": interval, "level": level,
            "unit": _power_unit(parameter(a).unit, parameter(b).unit, p), "of": [a, b], "exponent": p,
            "correlation": float(r), "determined": determined, "note": note, "splits": split_iv,
            "falls_along_ridge": falls, "dropped_pooled": pooled_dropped}


#: The halves a fit's loss is split into to check that each alone puts the values where the other does
#: (:func:`_splits`): the depth's and the tracks' terms; the first and the second half of the fitting frames. Each
#: with why the two may disagree beyond the frames' noise.
SPLITS = {"measurement": (("the depth", "the tracks"),
                          "one of the two measurements (or the frame-0 body) holds an error that the frames' noise "
                          "does not show"),
          "time": (("the first half of the fitting frames", "the second half"),
                   "the model does not hold alike over the recording (a missing effect, a wrong body, or a "
                   "measurement error that grows or changes with time)")}
#: A half of the fitting frames scores at least this many frames, or the split in time is not made.
MIN_HALF_FRAMES = 4


def _splits(obj, terms: list, seen: np.ndarray, dz: np.ndarray, *, n_boot: int, seed: int) -> Dict[str, dict]:
    """:func:`newton_bootstrap` of halves of the fitted body's loss (``terms``: per probe,
    :meth:`~.offline.Objective.per_frame_terms` of its simulation; ``seen``: the frames 1 .. F-1 scored), per
    :data:`SPLITS` entry ``{name: {half: result}}``: the depth's and the tracks' terms (where the loss has both), the
    first and the second half of the frames (where each holds :data:`MIN_HALF_FRAMES`)."""
    out = {}
    if obj.l_dist > 0.0 and all(t is not None for _, t in terms):
        out["measurement"] = {half: newton_bootstrap(np.stack([t[s] for t in terms])[:, seen], dz, n_boot=n_boot,
                                                     seed=seed) for s, half in enumerate(SPLITS["measurement"][0])}
    L = np.stack([d if t is None else d + t for d, t in terms])[:, seen]
    m = L.shape[1] // 2
    if m >= MIN_HALF_FRAMES:
        out["time"] = {half: newton_bootstrap(part, dz, n_boot=n_boot, seed=seed)
                       for half, part in zip(SPLITS["time"][0], (L[:, :m], L[:, m:]))}
    return out


#: Members of the fit's own search (CMA-ES's) simulated again beside the probes to look for another basin:
#: at most this many, each with a loss within :data:`FAR_LOSS` of the best (relative) and at least :data:`FAR_STEP`
#: of the search box (optimiser coordinates) from the fit and from each other in some parameter.
MAX_FAR = 3
FAR_LOSS = 0.25
FAR_STEP = 0.1
#: A fit without a population of its own (Adam's: one descent from one start, which ends in the basin it starts
#: in) is looked at across its search box instead: this many values of each fitted parameter, the others at the
#: fit (:func:`_scan_points`), simulated beside the probes; those within :data:`FAR_LOSS` of the fit's loss are
#: compared with it as the far members are.
SCAN_POINTS = 4


def _far_members(result, space, z0: np.ndarray) -> List[tuple]:
    """``[(values, loss)]``: the members of ``result``'s search (``extra["population"]``, CMA-ES's generations)
    nearly as good as the best (within :data:`FAR_LOSS`) and far from the fit ``z0`` and from each other (at least
    :data:`FAR_STEP` of the box in some parameter), lowest loss first, at most :data:`MAX_FAR`; [] for a fit
    without a population (Adam's) or without a finite loss."""
    pop, losses = result.extra.get("population") or [], result.extra.get("population_losses") or []
    best = float(result.loss) if result.loss is not None else float("nan")
    if not np.isfinite(best) or not pop:
        return []
    width = space.z_hi - space.z_lo
    members = sorted(((float(v), m) for gen, gl in zip(pop, losses) for m, v in zip(gen, gl)
                      if np.isfinite(v) and v <= best + FAR_LOSS * abs(best) and set(m) == set(space.names)),
                     key=lambda vm: vm[0])  # equal losses keep the search's order
    out, zs = [], [z0]
    for v, m in members:
        z = space.to_z(m)
        if all(np.max(np.abs(z - o) / width) >= FAR_STEP for o in zs):
            out.append((m, v))
            zs.append(z)
            if len(out) == MAX_FAR:
                break
    return out


def _scan_points(space, z0: np.ndarray) -> List[np.ndarray]:
    """A coarse scan of each fitted value across its search box, the others at the fit ``z0``: :data:`SCAN_POINTS`
    values of each parameter, the middles of as many equal parts of its box in optimiser coordinates (log scale,
    logit for nu), but those within :data:`FAR_STEP` of the box from the fit; optimiser coordinates, parameter by
    parameter, low to high."""
    width = space.z_hi - space.z_lo
    out = []
    for i in range(len(z0)):
        for f in (np.arange(SCAN_POINTS) + 0.5) / SCAN_POINTS:
            z = np.array(z0, float)
            z[i] = space.z_lo[i] + f * width[i]
            if abs(z[i] - z0[i]) >= FAR_STEP * width[i]:
                out.append(z)
    return out


def _basin_words(space, k: str, zm: np.ndarray, test: dict, q, source: str = "search") -> str:
    """Why the value ``zm`` (optimiser coordinates) of the fit's search (``source`` "search") or of the scan across
    the box (:func:`_scan_points`, "scan"), that :func:`paired_gain_test` (``test``: the fit's gain over it) cannot
    tell from the fit, leaves parameter ``k`` not determined."""
    vals = ", ".join(f"{n} = {_from_z(space, n, z):.4g}" for n, z in zip(space.names, zm))
    lvl = f"{100 * (q[1] - q[0]):.0f} %"
    where = "the fit's own search evaluated" if source == "search" else "a scan across the search box found"
    better = test["upper"] < 0.0  # the fit's loss higher than there beyond the frames' noise
    how = ("better than the fit, beyond their noise" if better else "within their noise as well as the fit")
    return (f"{where} {vals}, which fits these frames {how} "
            f"(the fit's loss lower by {100 * test['gain']:+.1f} %, {lvl} interval {100 * test['lower']:+.1f} to "
            f"{100 * test['upper']:+.1f} %): the loss has another basin or a flat stretch there, which the interval "
            f"about the fit did not hold; {k}'s interval spans both"
            + ("; the fit stopped in a worse basin: a fit started there may end lower" if better else ""))


def _quantiles(v: np.ndarray, q) -> tuple:
    """Quantiles ``q`` of draws ``v``, which may hold +-inf."""
    return tuple(np.quantile(v, q)) if np.all(np.isfinite(v)) else _inf_quantiles(v, q)


def _apart_within(lo_a: float, hi_a: float, lo_b: float, hi_b: float, lo: float, hi: float) -> bool:
    """Two intervals ``[lo_a, hi_a]`` and ``[lo_b, hi_b]`` that do not overlap, the ends that face each other
    within ``[lo, hi]`` (an open end, or one beyond it, places nothing there)."""
    facing = (hi_a, lo_b) if hi_a < lo_b else (hi_b, lo_a) if hi_b < lo_a else None
    return facing is not None and lo <= facing[0] < facing[1] <= hi


def _halves_apart(space, k: str, i: int, z0: np.ndarray, split: str, halves: dict, q) -> Optional[dict]:
    """Where the two ``halves`` of a :data:`SPLITS` entry ``split`` (:func:`_splits`) put parameter ``k``'s (index
    ``i``) minimum in intervals (quantiles ``q`` of their resamples) that do not overlap: ``{"warning", "lo_z",
    "hi_z"}`` (their ends, optimiser coordinates); None where they overlap, or where either's end that faces the
    other is open or outside the search box (the loss of that half alone is flat there, or its local model does
    not fit it: it places nothing there)."""
    (a, lo_a, hi_a), (b, lo_b, hi_b) = ((h, *_quantiles(z0[i] + nb["draws"][:, i], q)) for h, nb in halves.items())
    zl, zh = space.z_lo[i], space.z_hi[i]
    # the ends that face each other must lie in the box: a half whose minimum runs off that way, or lies beyond
    # the box, places nothing there
    if not _apart_within(lo_a, hi_a, lo_b, hi_b, zl, zh):
        return None
    words = [f"{_from_z(space, k, lo):.4g} to {_from_z(space, k, hi):.4g}" for lo, hi in ((lo_a, hi_a), (lo_b, hi_b))]
    lvl = f"{100 * (q[1] - q[0]):.0f} %"
    return {"warning": (f"{a} alone puts {k} at {words[0]} and {b} alone at {words[1]} ({lvl} intervals): they "
                        f"disagree beyond the frames' noise, so {SPLITS[split][1]}; {k}'s interval spans both"),
            "lo_z": (lo_a, lo_b), "hi_z": (hi_a, hi_b)}


def box_reasons(space, name: str, z_fit: float, z_min: float, lo_z: float, hi_z: float, *,
                level: float = 0.95) -> list:
    """Why parameter ``name`` is not determined by where its fit, its loss's minimum and its interval lie in the
    search box of ``space`` (a :class:`~.problem.ParamSpace`; all in its optimiser coordinates): the fit
    ``z_fit`` at a bound (within 2 % of the box), the loss's local minimum ``z_min`` outside the box, the
    ``level`` interval [``lo_z``, ``hi_z``] reaching past it, or spanning more than :data:`WIDE_INTERVAL` of
    it. The first that applies, as a list of one sentence; empty when none does."""
    i = list(space.names).index(name)
    zl, zh = space.z_lo[i], space.z_hi[i]
    box = list(space.bounds[name])
    tol = 0.02 * (zh - zl)
    if z_fit <= zl + tol or z_fit >= zh - tol:
        side = "lower" if z_fit <= zl + tol else "upper"
        return [f"at its {side} search bound {box[0 if side == 'lower' else 1]:.4g}: the data ask for a value "
                f"outside the box searched"]
    if z_min < zl - tol or z_min > zh + tol:
        side = "below" if z_min < zl else "above"
        near = f" (near {_from_z(space, name, z_min):.4g})" if np.isfinite(z_min) else ""
        return [f"the loss's minimum lies {side} the search box [{box[0]:.4g}, {box[1]:.4g}]{near}: the data ask "
                f"for a value outside the box searched"]
    side = one_sided_bound(space, name, lo_z, hi_z)
    if side:
        past = "below" if side == "upper" else "above"
        bound = bound_text(side, _from_z(space, name, hi_z if side == "upper" else lo_z))
        return [f"the loss is flat within the frame-to-frame noise {past} the fit: its {100 * level:.0f} % interval "
                f"reaches {past} the search box [{box[0]:.4g}, {box[1]:.4g}]; the data bound it {bound}"]
    if lo_z < zl - tol or hi_z > zh + tol:
        return [f"the loss is flat within the frame-to-frame noise along it: its {100 * level:.0f} % interval "
                f"reaches past the search box [{box[0]:.4g}, {box[1]:.4g}]"]
    if hi_z - lo_z > WIDE_INTERVAL * (zh - zl):
        return [f"the loss is nearly flat within the frame-to-frame noise along it: its {100 * level:.0f} % "
                f"interval [{_from_z(space, name, lo_z):.4g}, {_from_z(space, name, hi_z):.4g}] spans "
                f"{(hi_z - lo_z) / (zh - zl):.0%} of the search box [{box[0]:.4g}, {box[1]:.4g}] (optimiser scale)"]
    return []


def one_sided_bound(space, name: str, lo_z: float, hi_z: float) -> Optional[str]:
    """"upper" where the interval [``lo_z``, ``hi_z``] of parameter ``name`` (optimiser coordinates of ``space``)
    reaches below its search box and ends inside it (the data bound the value from above only: a yield stress
    that a recording never reaches, say), "lower" for the reverse, else None."""
    i = list(space.names).index(name)
    zl, zh = space.z_lo[i], space.z_hi[i]
    tol = 0.02 * (zh - zl)
    below, above = lo_z < zl - tol, hi_z > zh + tol
    if below and not above and np.isfinite(hi_z):
        return "upper"
    if above and not below and np.isfinite(lo_z):
        return "lower"
    return None


def bound_text(side: str, value: float, fmt: str = ".4g") -> str:
    """"from above only (at most 2576)" for ``side`` "upper" (:func:`one_sided_bound`), "from below only (at
    least ...)" for "lower"."""
    if side == "upper":
        return f"from above only (at most {value:{fmt}})"
    return f"from below only (at least {value:{fmt}})"


def uncertainty_bound(u: dict, fmt: str = ".4g") -> Optional[str]:
    """:func:`bound_text` of one parameter's entry of :func:`assess_fit`'s ``uncertainty`` (None where its
    interval is not one-sided)."""
    side = u.get("bounded_only")
    if not side:
        return None
    lo, hi = u["interval"]
    return bound_text(side, hi if side == "upper" else lo, fmt)


def _finer_grid_scene(scene):
    """``scene`` on a grid fine enough to resolve its body (:data:`MARGINAL_CELLS_ACROSS` cells across its thin
    parts, at most 1 / 0.6 times finer than its own), or None where its grid already does so, is too coarse
    to be a measurement at all, or the particles would fill the finer cells at fewer than 8 per cell."""
    from dataclasses import replace

    res, problem, note = grid_resolution(scene)
    if problem or note is None:
        return None
    dx = max(res["thickness_m"] / MARGINAL_CELLS_ACROSS, 0.6 * res["dx_m"])
    # the thickness is a whole number of particle spacings, so 8 per cell is often met exactly: not a rounding
    # error below it
    if dx ** 3 / float(np.median(scene.volumes)) < 8.0 * (1.0 - 1e-6):
        return None
    return replace(scene, dx=dx, grid=None)


#: The grid's share of a resolved body is probed on a grid this many times coarser (as far as the finer
#: grid of a marginal one is finer).
COARSER_GRID = 1.0 / 0.6


def coarser_grid_scene(scene):
    """``scene``, its particles unchanged, on a grid :data:`COARSER_GRID` times coarser, where its own grid resolves
    the body (at least :data:`MARGINAL_CELLS_ACROSS` cells across its thin parts) and the coarser one still has
    :data:`MIN_CELLS_ACROSS`; else None. A resolved grid is no converged one: ``empm synth``'s rope rebuilt at
    dx = 6.81 mm (3.4 cells) fitted E -7.1 %, -5.4 % at 8.5 mm and +6.8 % at 11.4 mm, and its interval without
    this share, [4.12e4, 4.76e4], missed the true 5e4 while saying E was determined."""
    from dataclasses import replace

    res, problem, note = grid_resolution(scene)
    if problem or note is not None:
        return None
    dx = COARSER_GRID * res["dx_m"]
    if res["thickness_m"] / dx < MIN_CELLS_ACROSS:
        return None
    return replace(scene, dx=dx, grid=None)


def _resampled_body(scene, rng):
    """``scene`` with its particles moved by independent uniform offsets of up to half their spacing (the
    same body on another lattice), kept above the table."""
    from dataclasses import replace

    h = float(np.cbrt(np.median(scene.volumes)))
    x = scene.particles + rng.uniform(-0.5, 0.5, scene.particles.shape) * h
    if scene.table is not None:
        x[:, 2] = np.maximum(x[:, 2], scene.table.height + 0.25 * h)
    return replace(scene, particles=x, grid=scene.grid_config())


def _inf_quantiles(v: np.ndarray, q) -> tuple:
    """Quantiles of draws that may hold +-inf (numpy's quantile interpolates inf into nan)."""
    s = np.sort(v)
    idx = [min(len(s) - 1, max(0, int(np.floor(p * (len(s) - 1) + 0.5)))) for p in q]
    return float(s[idx[0]]), float(s[idx[1]])


def _from_z(space, name: str, z: float) -> float:
    """SI value of optimiser coordinate z (+-inf map to the ends of the parameter's range)."""
    with np.errstate(over="ignore"):
        return float(space.from_z1(name, np.float64(z)))
