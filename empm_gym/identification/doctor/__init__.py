"""The discrepancy doctor: where a model and a recording disagree, which effect of the catalogue the model
misses, and the gap once it is added (``empm doctor``; :func:`diagnose_recording`, :func:`diagnose`).

Modules: :mod:`.phases` (phases of the manipulation read from the controls), :mod:`.features` (residuals
per frame, point, region; summary features), :mod:`.core` (base fit, candidates, verdict), :mod:`.report`
(figures and ``report.md``).
"""

from .core import DoctorConfig, DoctorError, candidate_params, diagnose

__all__ = ["DoctorConfig", "DoctorError", "candidate_params", "diagnose", "diagnose_recording"]


def diagnose_recording(rec_dir, *, out_dir=None, base=None, config=None, dx: float = 0.01,
                       particles_per_cell: float = 8, device=None, progress: bool = True, effects=None,
                       view_bodies: bool = True) -> dict:
    """Load a recording directory (our / PhysTwin's layout) and :func:`diagnose` it.

    ``base`` is a MaterialConfig or a material file path (its effects are part of the base model); ``dx`` [m]
    and ``particles_per_cell`` set the simulated body's resolution. ``view_bodies``: the frame-0 body rebuilt
    with each camera left out (:func:`~empm_gym.identification.data.view_jackknife_bodies`) joins the
    discretisation variants on which a named effect must hold its gain.
    """
    from empm_gym.sim import MaterialConfig
    from empm_gym.sim.material_file import read_material

    from ..data import load_recording, view_jackknife_bodies

    if base is not None and not isinstance(base, MaterialConfig):
        base = read_material(base).material
    info = {}
    scene, obs, views = load_recording(rec_dir, dx=dx, particles_per_cell=particles_per_cell, device=device,
                                       progress=progress, info=info)
    others = ((lambda: view_jackknife_bodies(rec_dir, scene, particles_per_cell=particles_per_cell,
                                             symmetry=info.get("symmetry"))) if view_bodies
              else ())
    return diagnose(scene, obs, views, base=base, config=config, out_dir=out_dir, progress=progress, effects=effects,
                    other_bodies=others, body_notes=[info["hidden_note"]] if info.get("hidden_note") else ())
