"""How long an offline fit will take, said before it starts, and a cheaper plan when that is too long.

The cost of a fit is measured, not guessed: one frame of the recording is simulated forward at the starting
material (after a warm-up frame that loads the kernels), and the fit's cost is that time times the frames
fitted, times :data:`ITER_PER_FORWARD` for an Adam iteration (forward, backward through ``wp.Tape`` and, when
the rollout does not fit in memory, the recomputation of checkpointed segments; measured 4-8x on the 2-core
CPU machine), times the iterations; the intervals afterwards (:func:`~.uncertainty.assess_fit`) cost forward
rollouts of a few worlds per body variant. Substeps grow as sqrt(E): a fit that stiffens the material takes
longer than the estimate at its start, so the plan allows :data:`STIFFENING` for that.

When the estimate exceeds the budget (by default :data:`CPU_BUDGET_S` on the CPU, where Warp runs a launch on
one core, and none on a GPU), :func:`plan_fit` takes these steps in order until it fits, each only where the
user did not set the option: a grid margin of 0 around the observed motion (the grid's empty nodes cost as
much as the particles on the CPU), 8 particles per cell instead of 27 (not for a body under
:data:`THIN_CELLS` cells thick), 12 Adam iterations at step 0.3
instead of 30 at 0.15, no extra particle lattices in the intervals, fewer fitted frames (down to
:data:`MIN_FIT_FRAMES`), fewer iterations (down to :data:`MIN_ITERS`). What it chose is printed and written to the material file's ``fit.plan``; a resumed fit
reuses it.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional


__all__ = ["FitPlan", "plan_fit", "estimate_s", "frame_seconds", "default_budget_s", "CPU_BUDGET_S", "ITER_PER_FORWARD"]

CPU_BUDGET_S = 540.0
"""Default budget of the fit and its intervals on the CPU (s): with perception and the rerun file, a default
``empm identify`` of a 60-frame recording then ends within about 15 minutes on the 2-core machine."""
ITER_PER_FORWARD = 8.0
"""An Adam iteration costs this many forward simulations of the same frames (measured 4-6.4 in session 7; 8.1
in session 24, stiffening included, after the forward had become faster than the taped steps: 12 steps over
30 frames of a rope fitted from 1e5 to 3.6e5 Pa took 716 s where 5.0 had estimated 440 s)."""
STIFFENING = 1.6
"""Allowance for the substeps growing as the fit stiffens E (E 2.5x its start; measured: a rope fitted from
1e5 to 4e5 Pa took 1.35x the estimate at its start)."""
MIN_FIT_FRAMES = 16
MIN_ITERS = 8
"""The fewest Adam iterations a plan goes down to (at step 0.3 a rope's E went from 1e5 to within 8 % of
3.7e5 in 8)."""
THIN_CELLS = 3.0
"""A body thinner than this many cells keeps its fill (particles across it decide its bending stiffness)."""
PROBE_COST = 3.0
"""The intervals' probes (5 worlds, forward only) of one body variant cost this many one-world forwards."""
SCAN_COST = 2.0
"""The intervals' scan of an Adam fit across its search box (:data:`~.uncertainty.SCAN_POINTS` values of each
fitted parameter beside the fit, one batch on the substeps of its stiffest value: E scanned up to 5.6 times the
start takes 2.4 times its substeps) costs this many body variants' probes per fitted parameter (measured: a rope's
intervals on 3 lattices took 2.0 s without it, 3.1 s with 5 values)."""


@dataclass
class FitPlan:
    """Settings of an offline fit chosen for a time budget, with the estimate behind them."""

    particles_per_cell: float
    fit_frames: int
    iters: int
    lr: Optional[float]
    motion_margin: Optional[float]
    resample_bodies: int
    memory_budget_bytes: Optional[float]  # None: identify's default (1 GB; only the CPU's "auto" checkpointing reads it)
    estimate_s: float
    budget_s: Optional[float]
    steps: List[str] = field(default_factory=list)
    default_estimate_s: Optional[float] = None

    def to_dict(self) -> Dict:
        return dataclasses.asdict(self)

    def describe(self) -> str:
        """One paragraph for the user: the estimate and, when the defaults would not fit, what changed."""
        est = f"about {_minutes(self.estimate_s)} for the fit and its intervals"
        if not self.steps:
            return f"estimated {est}" + (f" (budget {_minutes(self.budget_s)})" if self.budget_s else "")
        return (f"the defaults would take about {_minutes(self.default_estimate_s)}, over the budget of "
                f"{_minutes(self.budget_s)} (--budget-min); planned instead: {'; '.join(self.steps)}: estimated "
                f"{est}. Give --budget-min 0 to keep the defaults")


def _minutes(s: Optional[float]) -> str:
    if s is None:
        return "?"
    return f"{s / 60.0:.1f} min" if s >= 60 else f"{s:.0f} s"


def default_budget_s(device: Optional[str]) -> Optional[float]:
    """:data:`CPU_BUDGET_S` when the fit runs on the CPU, None (no limit) on a GPU."""
    import warp as wp

    dev = wp.get_device(device) if device else wp.get_device()
    return CPU_BUDGET_S if dev.is_cpu else None


def frame_seconds(scene, material, worlds: int = 1) -> float:
    """Seconds to simulate one frame of ``scene`` forward with ``worlds`` copies of ``material`` (measured
    after one warm-up frame)."""
    from .problem import _ForwardSim

    sim = _ForwardSim(scene, [material] * worlds, [scene.table_friction] * worlds)
    sim.run(2)
    t0 = time.perf_counter()
    sim.run(2)
    return time.perf_counter() - t0


def _memory_bytes() -> float:
    """Half the machine's physical memory, at most 8 GB (the rollout's tape on the CPU)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1.0e9
    return float(min(8.0e9, max(1.0e9, 0.5 * total)))


def estimate_s(t_frame: float, fit_frames: int, iters: int, variants: int) -> float:
    """Seconds of a fit of ``iters`` Adam iterations over ``fit_frames`` frames plus its intervals' probes on
    ``variants`` bodies (0: no intervals), from ``t_frame``, the measured seconds of one forward frame."""
    fwd = t_frame * STIFFENING * (fit_frames - 1)
    return fwd * ITER_PER_FORWARD * iters + fwd * PROBE_COST * variants


def plan_fit(scene, material, *, fit_frames: int, iters: int, particles_per_cell: float, budget_s: Optional[float],
             fixed: Dict[str, bool], views: int, rebuild_body=None, lr: Optional[float] = None,
             resample_bodies: int = 2, uncertainty: bool = True, fitted: int = 1):
    """``(FitPlan, scene)``: the fit's settings for ``budget_s`` seconds (None or 0: the defaults, with the
    estimate) and the scene to fit (``scene`` with the plan's grid margin and body).

    ``fixed`` names the options the user set (``particles_per_cell``, ``iters``, ``lr``, ``frames``,
    ``margin``): those are never changed. ``views`` is the count of extra bodies the intervals will probe (one
    per camera for more than one camera, two for a single-view completion's axis), ``rebuild_body(scene, ppc)`` returns ``scene`` with its frame-0 body
    built at another fill (None: the fill is not changed). ``fitted``: how many parameters the fit has (the
    intervals scan each across its box, :data:`SCAN_COST`). The estimate is measured on the scene itself.
    """
    def variants():
        return (1 + plan.resample_bodies + views + SCAN_COST * fitted) if uncertainty else 0

    plan = FitPlan(particles_per_cell=particles_per_cell, fit_frames=fit_frames, iters=iters, lr=lr,
                   motion_margin=None, resample_bodies=resample_bodies, memory_budget_bytes=None,
                   estimate_s=0.0, budget_s=budget_s)
    t_frame = frame_seconds(scene, material)
    plan.estimate_s = plan.default_estimate_s = estimate_s(t_frame, fit_frames, iters, variants())
    if not budget_s or plan.estimate_s <= budget_s:
        return plan, scene
    sc = scene
    plan.memory_budget_bytes = _memory_bytes()  # no recomputation of checkpointed segments where memory allows
    if not fixed.get("margin") and sc.motion_bounds is not None and sc.grid is None and sc.motion_margin > 0:
        sc = dataclasses.replace(sc, motion_margin=0.0)
        plan.motion_margin = 0.0
        plan.steps.append("a grid 4 cells beyond the observed motion (no extra margin)")
        t_frame = frame_seconds(sc, material)
    if not fixed.get("particles_per_cell") and rebuild_body is not None and particles_per_cell > 8 \
            and estimate_s(t_frame, plan.fit_frames, plan.iters, variants()) > budget_s:
        from .uncertainty import body_thickness

        cells = body_thickness(sc.particles, sc.volumes) / sc.dx
        if cells >= THIN_CELLS:
            sc = rebuild_body(sc, 8.0)
            plan.particles_per_cell = 8.0
            plan.steps.append("8 particles per cell")
            t_frame = frame_seconds(sc, material)
        else:
            plan.steps.append(f"{particles_per_cell:g} particles per cell kept: the body is {cells:.1f} cells thick, "
                              f"and a coarser fill rounds its cross-section (+15 % on a rope's E at 8 per cell)")
    if not fixed.get("iters") and not fixed.get("lr") and iters > 12 \
            and estimate_s(t_frame, plan.fit_frames, plan.iters, variants()) > budget_s:
        plan.iters, plan.lr = 12, 0.3
        plan.steps.append("12 Adam iterations at step 0.3")
    if plan.resample_bodies > 0 and uncertainty and estimate_s(t_frame, plan.fit_frames, plan.iters,
                                                               variants()) > budget_s:
        plan.resample_bodies = 0
        plan.steps.append("intervals without extra particle lattices")
    if not fixed.get("frames") and plan.fit_frames > MIN_FIT_FRAMES:
        F = plan.fit_frames
        while F > MIN_FIT_FRAMES and estimate_s(t_frame, F, plan.iters, variants()) > budget_s:
            F -= 1
        if F < plan.fit_frames:
            plan.steps.append(f"frames 0-{F - 1} fitted (of 0-{plan.fit_frames - 1})")
            plan.fit_frames = F
    if not fixed.get("iters") and plan.iters > MIN_ITERS:
        it = plan.iters
        while it > MIN_ITERS and estimate_s(t_frame, plan.fit_frames, it, variants()) > budget_s:
            it -= 1
        if it < plan.iters:
            plan.steps.append(f"{it} Adam iterations")
            plan.iters = it
    plan.estimate_s = estimate_s(t_frame, plan.fit_frames, plan.iters, variants())
    if plan.estimate_s > budget_s:
        plan.steps.append("still over the budget: nothing more is reduced without losing the fit")
    return plan, sc
