"""The discrepancy doctor: where a model and a recording disagree, which effect of the catalogue the model
misses, and the gap once it is added (``empm doctor``; :func:`diagnose_recording`, :func:`diagnose`).

Modules: :mod:`.phases` (phases of the manipulation read from the controls), :mod:`.features` (residuals
per frame, point, region; summary features), :mod:`.core` (base fit, candidates, verdict), :mod:`.report`
(figures and ``report.md``).
"""

import dataclasses
import logging
from typing import Optional

import numpy as np

from .core import DoctorConfig, DoctorError, calibration_summary, candidate_params, diagnose

__all__ = ["DEFAULT_DX", "DOCTOR_CELLS_ACROSS", "DoctorConfig", "DoctorError", "candidate_params", "diagnose",
           "diagnose_recording", "load_for_doctor"]


#: The grid cell [m] the doctor starts from when none is given (:func:`diagnose_recording`).
DEFAULT_DX = 0.01
#: Largest relative loss of the frame-0 body's volume when :func:`load_for_doctor` fills it again on a finer grid:
#: beyond it the views leave holes in the finer lattice and it is not the same body (a rope imaged at 212 x 120
#: pixels, 2.7 mm each, filled on a 2.5 mm lattice to 117 cm^3 against 163 cm^3 on the 5 mm one) and the grid
#: is not refined. A gain is no such sign: a 2 cm rope in two clamps (150 cm^3) fills a 1 cm grid to 148 cm^3 and
#: a 5 mm one to 171 (the clamps' prior, resolved), and the 5 mm grid is the one that tells its motion right
#: (benchmarks/RESULTS.md, sessions 34-35).
REFILL_VOLUME_TOL = 0.1
#: Cells the doctor's grid puts across the frame-0 body's thin parts at least (:func:`load_for_doctor`), more than
#: identification's :data:`~empm_gym.identification.uncertainty.MARGINAL_CELLS_ACROSS`: what is at stake is not a
#: few per cent of E but a grid's artefact named as physics. On recordings made by a 5 mm simulation
#: (benchmarks/RESULTS.md, sessions 34-35) the doctor at 1 cm named an effect on 3 of 6 `none` ropes (1.9 cells
#: across) and on the dough lifted by one end on both seeds (3.4 cells, fracture, confidence 1.00); ropes at 5 mm
#: (4.2-4.6 cells): 0 of 12; the dough at 5 mm (6.8 cells): 0 of 7, and 16 of its 19 recordings named, against
#: 13 of 19 at 1 cm.
DOCTOR_CELLS_ACROSS = 4.0


def load_for_doctor(rec_dir, *, dx: Optional[float] = None, particles_per_cell: float = 8, device=None,
                    progress: bool = True, trim_to_surface: bool = False, refine_calibration: bool = True,
                    info: Optional[dict] = None):
    """``(scene, obs, views, info, notes)`` of a recording as the doctor simulates it: what
    :func:`~empm_gym.identification.data.load_recording` returns (``info`` filled), on the grid cell ``dx`` [m]
    or, without it, on one that resolves the body: :data:`DEFAULT_DX`, halved (at most twice) while the
    frame-0 body, filled again from the views on each finer cell and measured there, is fewer than
    :data:`DOCTOR_CELLS_ACROSS` cells across
    (:func:`~empm_gym.identification.uncertainty.resolving_dx`). ``notes``: what the loader says of the body
    and, where the cell was refined, why. ``trim_to_surface``: the body's particles outside the measured surface
    removed (:func:`~empm_gym.identification.data.frame0_body`; off by default). ``rec_dir`` is a path or a
    recording opened by :func:`~empm_gym.identification.data.open_recording` (whose ``info`` is then passed here);
    ``refine_calibration`` as there."""
    from ..data import _warn_body, load_recording, open_recording, rebuilt_scene
    from ..uncertainty import resolving_dx

    info = {} if info is None else info
    rec_dir = open_recording(rec_dir, refine_calibration=refine_calibration, info=info)
    scene, obs, views = load_recording(rec_dir, dx=DEFAULT_DX if dx is None else dx,
                                       particles_per_cell=particles_per_cell, device=device, progress=progress,
                                       info=info, warn=False, trim_to_surface=trim_to_surface)  # said below
    grid_notes = []
    if dx is None:
        coarse, refused = scene, []

        def refill(fine):
            # the same recording, the frame-0 body filled again at the finer cell (what the cameras saw is the same)
            report = {}
            finer = rebuilt_scene(rec_dir, dataclasses.replace(coarse, dx=fine), particles_per_cell=particles_per_cell,
                                  info=report, trim_to_surface=trim_to_surface)
            v0, v1 = float(np.sum(coarse.volumes)), float(np.sum(finer.volumes))
            if v1 < (1.0 - REFILL_VOLUME_TOL) * v0:
                refused.append((fine, v0, v1))
                return None
            info.update({k: report[k] for k in ("hidden_share", "hidden_note", "trimmed_share", "trim_note",
                                                 "body_completion")})
            info.pop("unseen_side", None)
            if "unseen_side" in report:
                info["unseen_side"] = report["unseen_side"]
            return finer

        scene, levels = resolving_dx(scene, refill, cells=DOCTOR_CELLS_ACROSS)
        res = levels[0]
        why = (f"at {res['dx_m']:g} m the body is {res['cells_across']:.1f} cells across its thin parts "
               f"({100 * res['thickness_m']:.1f} cm), too coarse to tell the grid's effect on its motion from a "
               f"missing physical effect")
        if len(levels) > 1:
            at = "; ".join(f"{r['cells_across']:.1f} cells across at {r['dx_m']:g} m" for r in levels[1:])
            grid_notes.append(f"grid: dx = {scene.dx:g} m, chosen for the body: {why} ({at}; give dx to choose)")
        if refused:
            fine, v0, v1 = refused[0]
            grid_notes.append(
                f"grid: {why if len(levels) == 1 else 'not refined further'}; the finer grid ({fine:g} m) was not "
                f"used: the views fill the body there to {1e6 * v1:.0f} cm^3 against {1e6 * v0:.0f} cm^3 (images too "
                f"coarse for its lattice?). Every verdict on this grid may be the grid's, not the material's")
    _warn_body(rec_dir, info)
    if grid_notes and scene.dx < DEFAULT_DX:
        import warp as wp

        # said before the fits start, not only in doctor.json: on the CPU the finer grid costs hours, not minutes
        slow = (f" On the CPU this costs up to {(DEFAULT_DX / scene.dx) ** 4:.0f}x the {DEFAULT_DX:g} m run "
                f"({len(scene.particles)} particles, and more substeps; a rope at 5 mm took 8x); --dx {DEFAULT_DX:g} "
                f"gives a quicker, coarser look." if wp.get_device(device).is_cpu else "")
        logging.getLogger("empm_gym.identification").warning("%s: %s.%s", rec_dir, grid_notes[0], slow)
    notes = [info[k] for k in ("calibration_note", "rim_note", "table_track_note", "track_note", "hidden_note",
                               "trim_note") if info.get(k)] + grid_notes
    if "unseen_side" in info:  # a side of the body the end-effectors hide from cameras all around: a prior's
        notes.insert(0, "frame-0 body: " + info["unseen_side"]["note"])
    return scene, obs, views, info, notes



def diagnose_recording(rec_dir, *, out_dir=None, base=None, config=None, dx: Optional[float] = None,
                       particles_per_cell: float = 8, device=None, progress: bool = True, effects=None,
                       view_bodies: bool = True, trimmed_body: bool = True, control_delay: float = 0.0,
                       refine_calibration: bool = True) -> dict:
    """Load a recording directory (our / PhysTwin's layout) and :func:`diagnose` it.

    ``base`` is a MaterialConfig or a material file path (its effects are part of the base model); ``dx`` [m]
    and ``particles_per_cell`` set the simulated body's resolution (without ``dx``, a cell that resolves the
    body: :func:`load_for_doctor`). ``view_bodies``: the frame-0 body rebuilt with each camera left out
    (:func:`~empm_gym.identification.data.view_jackknife_bodies`) joins the discretisation variants on which a
    named effect must hold its gain. ``trimmed_body``: so does the frame-0 body trimmed to the measured surface
    (:func:`~empm_gym.identification.data.trimmed_body`), on which a named effect must hold its gain whatever the
    other variants say. On seed 24 of the doctor's benchmark (fresh, one H200, benchmarks/RESULTS.md, session 64)
    it refused the one effect given to a `none` recording (dough pushed across the table: viscosity, 21.7 % held out
    on the rebuilt body and holding on 4 of its 5 variants, -2.8 % on the trimmed one) and kept all 18 right
    verdicts of the 24 recordings it ran (their gains on the trimmed body 17-98 %). ``control_delay``: the
    controls are delayed by this many frames (:func:`~empm_gym.identification.data.delayed_controls`) before
    anything is fitted, for a recording whose images trail its controls (the lag ``doctor.json``'s
    ``control_lag`` reads; a note says it was applied). ``refine_calibration``: cameras that disagree are moved
    onto one surface in memory before anything is fused (:func:`~empm_gym.identification.data.open_recording`;
    the notes say by how much).
    """
    from empm_gym.sim import MaterialConfig
    from empm_gym.sim.material_file import read_material

    from ..data import open_recording, trimmed_body as trim, view_jackknife_bodies

    if base is not None and not isinstance(base, MaterialConfig):
        base = read_material(base).material
    info = {}
    rec_dir = open_recording(rec_dir, refine_calibration=refine_calibration, info=info)  # once for every body
    scene, obs, views, info, notes = load_for_doctor(rec_dir, dx=dx, particles_per_cell=particles_per_cell,
                                                     device=device, progress=progress, info=info)
    if control_delay:
        from ..data import delayed_controls

        scene = delayed_controls(scene, control_delay)
        d = float(control_delay)
        notes = list(notes) + [f"the controls are delayed by {d:g} frame{'' if abs(d) == 1 else 's'} (as asked) before "
                               f"every fit: the lag read below is what remains"]

    def others():  # built only when a candidate is to be checked
        bodies = (view_jackknife_bodies(rec_dir, scene, particles_per_cell=particles_per_cell,
                                        symmetry=info.get("symmetry")) if view_bodies else [])
        return bodies + ([(*trim(rec_dir, scene, particles_per_cell=particles_per_cell), "trimmed")]
                         if trimmed_body else [])

    return diagnose(scene, obs, views, base=base, config=config, out_dir=out_dir, progress=progress, effects=effects,
                    other_bodies=others, body_notes=notes, calibration=calibration_summary(info.get("calibration")))
