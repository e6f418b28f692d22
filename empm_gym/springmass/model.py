"""The spring-mass network: particles, springs between neighbours, their parameters, and the stable step.

Units: metres, seconds, kilograms, Pascals. A spring between particles i and j of rest length L carries

    F = Y * w_ij * exp(s_ij) * (l - L)  +  eta * w_ij * (dl/dt)          [N]

along the spring, with ``Y`` the stiffness [Pa], ``eta`` the damping [Pa s], ``s_ij`` an optional per-spring
log multiplier (0 by default) and the geometric weight ``w_ij = 6 (v_i / n_i + v_j / n_j) / L^2`` [m]
(v: particle volume [m^3], n: its number of springs). The weight spreads each particle's volume over its
springs, so Y is an elastic modulus of the network, independent of the particle spacing: for an isotropic
network of central springs the energy density under a uniform strain gives C_11 = sum(V_s) Y / (5 V) and, by
Cauchy's relation (nu = 1/4 for central forces), E = C_11 / 1.2 = Y when the spring volumes sum to 6 V.
That holds for an isotropic network away from its surface; a lattice is not isotropic and a thin body is
mostly surface, so Y is a nominal modulus (not measured against the MPM's E). ``eta`` is likewise a
viscosity-like coefficient. This is PhysTwin's model (Jiang et al. 2025: springs with F = Y (l / L - 1) plus dashpot and
drag damping, control springs to the controller) with the spring constants normalised by geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import warp as wp

__all__ = ["SpringMassConfig", "SpringMassModel", "build_network", "downsample", "model_from_body"]

def _positive(name, v, *, allow_zero=False):
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise ValueError(f"{name} must be finite and {'>= 0' if allow_zero else '> 0'}, got {v!r}")
    return v


@dataclass(frozen=True)
class SpringMassConfig:
    """Parameters and construction settings of a spring-mass model (validated on construction)."""

    stiffness: float = 1.0e5
    """Y [Pa]: spring stiffness normalised by geometry (the network's Young's modulus, see the module); > 0."""
    damping: float = 1.0
    """eta [Pa s]: dashpot coefficient along the springs, normalised like Y; >= 0."""
    drag: float = 0.0
    """Global velocity damping [1/s] (PhysTwin's drag): v *= exp(-drag dt) every substep; >= 0."""
    spacing: Optional[float] = None
    """Particle spacing of the network [m]: the frame-0 body is voxel-downsampled to it (mass and volume
    kept). None: half the scene's MPM grid cell (``Scene.dx / 2``)."""
    radius_factor: float = 1.8
    """Springs join particles closer than ``radius_factor * spacing`` [-] (1.8: the 26 lattice neighbours)."""
    max_neighbors: int = 26
    """At most this many springs per particle (its nearest neighbours within the radius)."""
    control_omega: float = 300.0
    """Natural frequency [rad/s] of the critically damped control springs from held particles to a closed
    gripper (PhysTwin's control points): the hold lags by about (acceleration / omega^2)."""
    cfl: float = 0.5
    """Fraction [-] of the stable substep used (of 2 / omega_max and 1 / damping rate)."""

    def __post_init__(self):
        _positive("SpringMassConfig.stiffness [Pa]", self.stiffness)
        _positive("SpringMassConfig.damping [Pa s]", self.damping, allow_zero=True)
        _positive("SpringMassConfig.drag [1/s]", self.drag, allow_zero=True)
        if self.spacing is not None:
            _positive("SpringMassConfig.spacing [m]", self.spacing)
        if not (_positive("SpringMassConfig.radius_factor", self.radius_factor) > 1.0):
            raise ValueError(f"SpringMassConfig.radius_factor must be > 1 (springs reach the nearest neighbours), "
                             f"got {self.radius_factor!r}")
        if int(self.max_neighbors) != self.max_neighbors or self.max_neighbors < 1:
            raise ValueError(f"SpringMassConfig.max_neighbors must be a positive integer, got {self.max_neighbors!r}")
        _positive("SpringMassConfig.control_omega [rad/s]", self.control_omega)
        if not (0.0 < float(self.cfl) <= 1.0):
            raise ValueError(f"SpringMassConfig.cfl must lie in (0, 1], got {self.cfl!r}")

    def replace(self, **kw) -> "SpringMassConfig":
        from dataclasses import replace

        return replace(self, **kw)


def build_network(points: np.ndarray, volumes: np.ndarray, radius: float, max_neighbors: int):
    """Springs [S, 2] (i < j), rest lengths [S] (m) and weights w_ij [S] (m) between points closer than
    ``radius`` [m], each point keeping at most ``max_neighbors`` nearest (a spring is kept when either end
    keeps it). Raises ValueError when a point has no spring (the network would fall apart)."""
    from scipy.spatial import cKDTree

    x = np.asarray(points, np.float64)
    vol = np.asarray(volumes, np.float64)
    N = len(x)
    if N < 2:
        raise ValueError(f"a spring-mass body needs at least 2 particles, got {N}")
    tree = cKDTree(x)
    k = min(int(max_neighbors) + 1, N)
    dist, idx = tree.query(x, k=k, distance_upper_bound=float(radius))
    dist, idx = dist.reshape(N, k), idx.reshape(N, k)
    rows = np.repeat(np.arange(N), k - 1)
    cols = idx[:, 1:].reshape(-1)
    ok = cols < N
    i, j = rows[ok], cols[ok]
    pairs = np.unique(np.stack([np.minimum(i, j), np.maximum(i, j)], 1), axis=0)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    if len(pairs) == 0:
        raise ValueError(f"no two particles lie within the spring radius {radius:g} m")
    counts = np.bincount(pairs.reshape(-1), minlength=N)
    if np.any(counts == 0):
        lonely = int(np.sum(counts == 0))
        raise ValueError(f"{lonely} of {N} particles have no neighbour within the spring radius {radius:g} m; "
                         f"raise SpringMassConfig.radius_factor or check the particles")
    rest = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1)
    if np.any(rest <= 0):
        raise ValueError("two particles coincide (a spring of zero rest length)")
    share = vol / counts
    w = 6.0 * (share[pairs[:, 0]] + share[pairs[:, 1]]) / rest**2
    return pairs.astype(np.int32), rest, w


class SpringMassModel:
    """What does not change during a rollout: particles, masses, springs and the parameter arrays.

    ``stiffness`` and ``damping`` are one-element Warp arrays (Pa, Pa s) and ``spring_log_scale`` a per-spring
    array, all with gradients when ``requires_grad``; ``set_params`` writes them.
    """

    def __init__(self, x0: np.ndarray, mass: np.ndarray, springs: np.ndarray, rest: np.ndarray, weight: np.ndarray,
                 config: SpringMassConfig, *, fixed: Optional[np.ndarray] = None, spacing: float,
                 gravity: Sequence[float] = (0.0, 0.0, -9.81), device: Optional[str] = None, requires_grad: bool = False):
        x0 = np.asarray(x0, np.float64)
        if x0.ndim != 2 or x0.shape[1] != 3 or len(x0) == 0:
            raise ValueError(f"spring-mass particles must have shape [N, 3] with N > 0, got {x0.shape}")
        if not np.all(np.isfinite(x0)):
            bad = int(np.sum(~np.isfinite(x0).all(1)))
            raise ValueError(f"spring-mass particles: {bad} of {len(x0)} positions are not finite")
        mass = np.broadcast_to(np.asarray(mass, np.float64), (len(x0),))
        if not np.all(np.isfinite(mass)) or np.any(mass <= 0):
            raise ValueError("spring-mass particle masses must be finite and > 0 kg")
        springs = np.asarray(springs, np.int32).reshape(-1, 2)
        if springs.size and (springs.min() < 0 or springs.max() >= len(x0)):
            raise ValueError(f"springs index particles outside [0, {len(x0)})")
        rest, weight = np.asarray(rest, np.float64), np.asarray(weight, np.float64)
        if rest.shape != (len(springs),) or weight.shape != (len(springs),):
            raise ValueError(f"rest lengths and weights must have shape [{len(springs)}]")
        if np.any(~np.isfinite(rest)) or np.any(rest < 0) or np.any(~np.isfinite(weight)) or np.any(weight < 0):
            raise ValueError("spring rest lengths (m) and weights (m) must be finite and >= 0")
        self.config = config
        self.device = device
        self.spacing = float(spacing)
        self.particle_count = len(x0)
        self.spring_count = len(springs)
        self.x0 = x0
        self.mass = mass.copy()
        self.fixed = np.zeros(len(x0), bool) if fixed is None else np.asarray(fixed, bool).reshape(len(x0))
        self.springs_np, self.rest_np, self.weight_np = springs, rest, weight
        self.gravity = tuple(float(g) for g in gravity)
        inv_m = np.where(self.fixed, 0.0, 1.0 / self.mass)
        self.inv_mass_np = inv_m
        d = device
        self.particle_mass = wp.array(self.mass.astype(np.float32), dtype=float, device=d)
        self.particle_inv_mass = wp.array(inv_m.astype(np.float32), dtype=float, device=d)
        self.spring_indices = wp.array(springs.astype(np.int32), dtype=wp.vec2i, device=d)
        self.spring_rest = wp.array(rest.astype(np.float32), dtype=float, device=d)
        self.spring_weight = wp.array(weight.astype(np.float32), dtype=float, device=d)
        self.spring_log_scale = wp.zeros(len(springs), dtype=float, device=d, requires_grad=requires_grad)
        self.stiffness = wp.zeros(1, dtype=float, device=d, requires_grad=requires_grad)
        self.damping = wp.zeros(1, dtype=float, device=d, requires_grad=requires_grad)
        self.requires_grad = requires_grad
        self.set_params(config.stiffness, config.damping)

    def set_params(self, stiffness: float, damping: float, log_scale: Optional[np.ndarray] = None):
        """Write Y [Pa], eta [Pa s] (and per-spring log multipliers [S]); ValueError on bad values."""
        Y = _positive("stiffness [Pa]", stiffness)
        eta = _positive("damping [Pa s]", damping, allow_zero=True)
        self.stiffness.assign(np.array([Y], np.float32))
        self.damping.assign(np.array([eta], np.float32))
        if log_scale is not None:
            s = np.asarray(log_scale, np.float64)
            if s.shape != (self.spring_count,) or not np.all(np.isfinite(s)):
                raise ValueError(f"spring log multipliers must be {self.spring_count} finite values")
            self.spring_log_scale.assign(s.astype(np.float32))

    def stable_dt(self, stiffness: float, damping: float, *, control: bool = False, log_scale_max: float = 0.0,
                  drag: Optional[float] = None) -> float:
        """Largest substep [s] kept stable for these parameters: ``cfl * min(2 / omega_max, 1 / gamma_max)`` with
        omega_max^2 and gamma_max (1/s) Gershgorin bounds of the network's stiffness and damping over mass (plus
        the control springs' omega_c^2 and 2 omega_c when ``control``, plus the drag)."""
        Y = _positive("stiffness [Pa]", stiffness)
        eta = _positive("damping [Pa s]", damping, allow_zero=True)
        drag = self.config.drag if drag is None else float(drag)
        N = self.particle_count
        pair_im = self.inv_mass_np[self.springs_np[:, 0]] + self.inv_mass_np[self.springs_np[:, 1]]
        w = self.weight_np * pair_im
        acc = np.zeros(N)
        np.add.at(acc, self.springs_np[:, 0], w)
        np.add.at(acc, self.springs_np[:, 1], w)
        wmax = float(acc.max()) if N else 0.0
        om2 = Y * math.exp(log_scale_max) * wmax
        gam = eta * wmax + drag
        if control:
            oc = self.config.control_omega
            om2 += oc * oc
            gam += 2.0 * oc
        lim = [2.0 / math.sqrt(om2)] if om2 > 0 else []
        if gam > 0:
            lim.append(1.0 / gam)
        if not lim:
            return float("inf")
        return self.config.cfl * min(lim)


def downsample(points: np.ndarray, volumes: np.ndarray, spacing: float):
    """Voxel-downsample a body to one particle per occupied cube of side ``spacing`` [m]: the particle sits at
    the volume-weighted mean of the points in it and carries their summed volume [m^3]. Returns (x, volumes)."""
    x = np.asarray(points, np.float64)
    vol = np.asarray(volumes, np.float64)
    spacing = _positive("spacing [m]", spacing)
    key = np.floor((x - x.min(0)) / spacing + 0.5).astype(np.int64)  # a lattice at this spacing keeps every point
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = int(inv.max()) + 1
    vsum = np.bincount(inv, weights=vol, minlength=n)
    xm = np.stack([np.bincount(inv, weights=vol * x[:, c], minlength=n) for c in range(3)], 1) / vsum[:, None]
    return xm, vsum


def model_from_body(points: np.ndarray, volumes: np.ndarray, *, density: float, config: SpringMassConfig,
                    spacing: float, gravity: Sequence[float] = (0.0, 0.0, -9.81), device: Optional[str] = None,
                    requires_grad: bool = False) -> SpringMassModel:
    """A spring-mass model of a body given by particles [N, 3] (m) and volumes [N] (m^3): voxel-downsampled to
    ``spacing`` [m], masses ``density`` [kg/m^3] times volume, springs within ``config.radius_factor * spacing``."""
    x = np.asarray(points, np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
        raise ValueError(f"body particles must have shape [N, 3] with N > 0, got {x.shape}")
    if not np.all(np.isfinite(x)):
        bad = int(np.sum(~np.isfinite(x).all(1)))
        raise ValueError(f"body particles: {bad} of {len(x)} positions are not finite")
    vol = np.broadcast_to(np.asarray(volumes, np.float64), (len(x),))
    if not np.all(np.isfinite(vol)) or np.any(vol <= 0):
        raise ValueError("body particle volumes must be finite and > 0 m^3")
    rho = _positive("density [kg/m^3]", density)
    xd, vd = downsample(x, vol, spacing)
    springs, rest, w = build_network(xd, vd, config.radius_factor * spacing, config.max_neighbors)
    return SpringMassModel(xd, rho * vd, springs, rest, w, config, spacing=spacing, gravity=gravity, device=device,
                           requires_grad=requires_grad)
