"""Differentiable multi-step rollouts on ``wp.Tape``, with segment checkpointing for long horizons.

A rollout advances ``steps`` substeps of dt from an initial state under a sequence of controls (one
Control per control period of ``substeps_per_control`` substeps) and records particle positions every
``record_every`` substeps. ``backward`` takes the gradient of a loss with respect to the recorded
positions and accumulates the gradients of that loss into the model's material arrays
(``world_E.grad`` ...), the controls (``ee_vel.grad``, ``ee_omega.grad``) and the initial state.

With ``checkpoint_every=S`` only every S-th state is kept in the forward pass; the backward pass
replays each segment of S substeps on a fresh tape (Warp's fluid-checkpoint pattern), so memory grows
with S, not with the horizon. ``checkpoint_every=None`` tapes the whole rollout at once.

On CUDA a rollout taped at once (``graph=True``, the default) captures its substeps and, separately, their
adjoints in two CUDA graphs the first time it runs, and replays them after: an identification rollout of a
few thousand particles over hundreds of substeps is otherwise bound by launching its kernels one at a time
from Python. The graphs hold the rollout's own arrays, so what changes between runs (the material, the
controls, the initial state, the seed gradients) is copied into those arrays, never swapped for new ones.

Checkpointed segments that align (S divides the horizon and is a whole number of control periods and of
record intervals; ``Rollout.aligned``) all run the same code on the same arrays: each segment's controls are
copied into control slots first. On CUDA that code is two graphs of one segment, captured once and replayed
for every segment, forward and (after recomputing the segment's forward) backward, so a long horizon costs
one segment's capture and memory.
"""


from typing import List, Optional, Sequence

import logging

import numpy as np
import warp as wp

from .model import Control, Model, State, StateBlock
from .solver import GridScratchBlock, SolverMPM

__all__ = ["Rollout"]

_log = logging.getLogger(__name__)


def _add_grad(arr: wp.array, g):
    """arr.grad += g (g: wp.array, numpy array or torch tensor of arr's shape; None adds nothing)."""
    if g is None:
        return
    if not isinstance(g, wp.array):
        if hasattr(g, "detach"):
            g = g.detach().cpu().numpy()
        shape = tuple(arr.shape) + tuple(getattr(arr.dtype, "_shape_", ()))
        g = wp.array(np.asarray(g, dtype=np.float32).reshape(shape), dtype=arr.dtype, device=arr.device)
    wp.launch(_axpy(arr.dtype), dim=arr.shape[0], inputs=[g, arr.grad], device=arr.device)


def _same_objects(a: Optional[list], b: list) -> bool:
    return a is not None and len(a) == len(b) and all(x is y for x, y in zip(a, b))


def _set_array(arr: wp.array, g):
    """arr = g (g: numpy array or torch tensor of arr's shape; None sets zeros), in place."""
    if g is None:
        arr.zero_()
        return
    if hasattr(g, "detach"):
        g = g.detach().cpu().numpy()
    shape = tuple(arr.shape) + tuple(getattr(arr.dtype, "_shape_", ()))
    arr.assign(np.asarray(g, dtype=np.float32).reshape(shape))


_AXPY = {}


def _axpy(dtype):
    if dtype not in _AXPY:
        @wp.kernel(module="unique")
        def axpy(src: wp.array(dtype=dtype), dst: wp.array(dtype=dtype)):
            """dst += src."""
            i = wp.tid()
            dst[i] = dst[i] + src[i]

        _AXPY[dtype] = axpy
    return _AXPY[dtype]


class Rollout:
    """A differentiable rollout of ``steps`` substeps of ``dt`` [s] (see the module docstring)."""

    def __init__(self, model: Model, solver: SolverMPM, *, steps: int, dt: float,
                 substeps_per_control: int = 1, record_every: int = 1, checkpoint_every: Optional[int] = None,
                 graph: bool = True):
        if steps <= 0 or substeps_per_control <= 0 or record_every <= 0:
            raise ValueError("steps, substeps_per_control and record_every must be positive integers")
        if checkpoint_every is not None and checkpoint_every <= 0:
            raise ValueError(f"checkpoint_every must be a positive number of substeps or None, got {checkpoint_every}")
        self.model, self.solver = model, solver
        self.steps, self.dt = int(steps), float(dt)
        self.substeps_per_control = int(substeps_per_control)
        self.record_every = int(record_every)
        self.segment = int(checkpoint_every) if checkpoint_every else self.steps
        self.checkpointed = checkpoint_every is not None and checkpoint_every < steps
        S = self.segment
        # one array per field for all states (and grids): allocated, and their gradients zeroed, at once
        self._state_block = StateBlock(model, S + 1, requires_grad=True)
        self._grid_block = GridScratchBlock(model, S, requires_grad=True)
        self._states, self._grids = self._state_block.states, self._grid_block.grids
        self.control_count = -(-self.steps // self.substeps_per_control)
        self.record_steps = list(range(0, self.steps + 1, self.record_every))
        self._checkpoints: List[State] = []
        self._records: List[wp.array] = []
        self._tape: Optional[wp.Tape] = None
        self.initial_grad: Optional[dict] = None
        self.final_state: Optional[State] = None
        # CUDA graphs of the forward substeps and of their adjoints (see the module docstring); the controls
        # they were captured with, and the buffers that feed the seed gradients into the backward graph
        # Segments that start on a control period and hold the same record positions run one segment's code
        # for all of them: on CUDA two graphs (its substeps, their adjoints) captured once and replayed per
        # segment, whatever the horizon (see _segment_forward)
        self.aligned = (self.checkpointed and self.steps % S == 0 and S % self.substeps_per_control == 0
                        and S % self.record_every == 0)
        self.graph = (bool(graph) and model.device.is_cuda and (not self.checkpointed or self.aligned)
                      and solver.config.check_every == 0)
        self._fwd_graph = self._bwd_graph = None
        self._graph_controls: Optional[list] = None
        self._seed_bufs: dict = {}
        if self.aligned:
            n_seg = self.steps // S
            self._slots = [model.control(requires_grad=True) for _ in range(S // self.substeps_per_control)]
            """The controls a segment's steps read: each segment's are copied in before it runs."""
            self._ckpt_block = StateBlock(model, n_seg)
            self._checkpoints = self._ckpt_block.states
            self._record_block = wp.zeros((len(self.record_steps), model.particle_count), dtype=wp.vec3,
                                          device=model.device)
            self._seed_bufs = {r: wp.zeros(model.particle_count, dtype=wp.vec3, device=model.device)
                               for r in range(self.record_every, S + 1, self.record_every)}
            self._carry = [wp.zeros_like(a) for a in self._states[0].arrays()]
            """The gradient at a segment's last state, carried from the backward pass of the segment after it."""
            self._final = State(model)

    def make_controls(self) -> List[Control]:
        """One Control (with gradients) per control period."""
        return [self.model.control(requires_grad=True) for _ in range(self.control_count)]

    def _control(self, controls, t):
        return controls[min(t // self.substeps_per_control, len(controls) - 1)]

    # -- forward ---------------------------------------------------------------
    def forward(self, state0: State, controls: Sequence[Control]) -> List[wp.array]:
        """Run the rollout; returns the recorded particle positions (one [N] vec3 array per recorded step)."""
        if len(controls) < self.control_count:
            raise ValueError(f"Rollout.forward: need {self.control_count} controls, got {len(controls)}")
        self.model.update_particle_materials()
        self.solver.check_dt(self.dt, max((c.max_speed for c in controls), default=0.0))
        self._controls = list(controls)
        if self.aligned:
            return self._segments_forward(state0)
        S, states = self.segment, self._states
        states[0].assign(state0)
        self._records, self._checkpoints = [], []
        check_every = self.solver.config.check_every
        if self.graph and (self._fwd_graph is None or not _same_objects(self._graph_controls, self._controls)):
            self._bwd_graph = None
            self._tape = wp.Tape()
            self._fwd_graph = self._capture(lambda: self._taped_steps(controls, check_every=0), "forward")
            self._graph_controls = list(self._controls)  # held, so that the graph's arrays stay alive
        if self.graph:
            wp.capture_launch(self._fwd_graph)
            self._records = [states[t].particle_x for t in self.record_steps]
            self.final_state = states[self.steps]
        elif not self.checkpointed:
            self._tape = wp.Tape()
            self._taped_steps(controls, check_every)
            self._records = [states[t].particle_x for t in self.record_steps]
            self.final_state = states[self.steps]
        else:
            self._tape = None
            a, b = states[0], states[1]
            if 0 in self.record_steps:
                self._records.append(wp.clone(a.particle_x))
            for t in range(self.steps):
                if t % S == 0:
                    self._checkpoints.append(State(self.model).assign(a))
                self.solver.step(a, b, self._control(controls, t), self.dt, self._grids[0], guards=False)
                if check_every and (t + 1) % check_every == 0:
                    self.solver.check_state(b, step=t + 1)
                if (t + 1) in self.record_steps:
                    self._records.append(wp.clone(b.particle_x))
                a, b = b, a
            self.final_state = State(self.model).assign(a)
        if not check_every:
            self.solver.check_state(self.final_state, step=self.steps)
        return self._records

    def _capture(self, launches, what: str):
        """A CUDA graph of what ``launches()`` launches (captured, not yet run); None, with graphs off from
        then on, where the device or driver cannot capture: the kernels are then launched one by one (a
        backward pass can fall back so, since the forward's tape still holds every launch)."""
        try:
            with wp.ScopedCapture(device=self.model.device) as cap:
                launches()
            return cap.graph
        except Exception as exc:
            _log.warning("Rollout: CUDA graph capture of the %s pass failed (%s); launching kernels one by one",
                         what, exc)
            self.graph, self._fwd_graph = False, None
            return None

    def _taped_steps(self, controls, check_every: int, steps: Optional[int] = None, first_step: int = 0):
        """``steps`` substeps (default: all) on ``self._tape``, each into its own state and grid (the rollout
        taped at once, or the segment that starts at substep ``first_step``)."""
        states = self._states
        with self._tape:
            self._grid_block.clear()
            for t in range(steps or self.steps):
                self.solver.step(states[t], states[t + 1], self._control(controls, t), self.dt, self._grids[t],
                                 guards=False)
                if check_every and (first_step + t + 1) % check_every == 0:
                    self.solver.check_state(states[t + 1], step=first_step + t + 1)

    # -- aligned segments ------------------------------------------------------
    def _segment_controls(self, seg: int) -> List[Control]:
        """The caller's controls of segment ``seg``, one per slot (the last one repeats past their end)."""
        n = len(self._slots)
        return [self._controls[min(seg * n + j, len(self._controls) - 1)] for j in range(n)]

    def _load_segment_controls(self, seg: int):
        """Copy the controls of segment ``seg`` into the slots its steps read."""
        for slot, c in zip(self._slots, self._segment_controls(seg)):
            slot.ee_vel.assign(c.ee_vel)
            slot.ee_omega.assign(c.ee_omega)
            slot.ee_grip.assign(c.ee_grip)

    def _segment_forward(self, seg: int):
        """Run segment ``seg``'s substeps from states[0] on a tape (replayed from its CUDA graph on CUDA)."""
        if self.graph and self._fwd_graph is None:
            self._tape = wp.Tape()
            self._fwd_graph = self._capture(lambda: self._taped_steps(self._slots, 0, self.segment), "forward")
        if self.graph:
            wp.capture_launch(self._fwd_graph)
        else:
            self._tape = wp.Tape()
            self._taped_steps(self._slots, self.solver.config.check_every, self.segment, seg * self.segment)

    def _segment_adjoint(self):
        """The adjoint of the segment just run: seeds from ``_seed_bufs``, the carried gradient added at its last
        state, and the gradient at its first state left in ``_carry`` for the segment before it."""
        self._zero_rollout_grads()
        for slot in self._slots:
            slot.ee_vel.grad.zero_()
            slot.ee_omega.grad.zero_()
        for r, buf in self._seed_bufs.items():
            _add_grad(self._states[r].particle_x, buf)
        for a, c in zip(self._states[self.segment].arrays(), self._carry):
            _add_grad(a, c)
        self._tape.backward()
        for a, c in zip(self._states[0].arrays(), self._carry):
            wp.copy(c, a.grad)

    def _segments_forward(self, state0: State) -> List[wp.array]:
        S, states = self.segment, self._states
        states[0].assign(state0)
        rows = {t: self._record_block[i] for i, t in enumerate(self.record_steps)}
        if 0 in rows:
            wp.copy(rows[0], states[0].particle_x)
        for seg, ckpt in enumerate(self._checkpoints):
            ckpt.assign(states[0])
            self._load_segment_controls(seg)
            self._segment_forward(seg)
            for r in self._seed_bufs:
                wp.copy(rows[seg * S + r], states[r].particle_x)
            states[0].assign(states[S])
        self.final_state = self._final.assign(states[0])
        self._records = [rows[t] for t in self.record_steps]
        if not self.solver.config.check_every:
            self.solver.check_state(self.final_state, step=self.steps)
        return self._records

    def _segments_backward(self, seeds: dict):
        S = self.segment
        for c in self._carry:
            c.zero_()
        for seg in reversed(range(len(self._checkpoints))):
            self._states[0].assign(self._checkpoints[seg])
            self._load_segment_controls(seg)
            self._segment_forward(seg)  # recompute the segment's states (and grids) for its adjoint
            for r, buf in self._seed_bufs.items():
                _set_array(buf, seeds.get(seg * S + r))
            if self.graph and self._bwd_graph is None:
                _axpy(self._states[0].particle_x.dtype)  # made (and their modules loaded) before the capture
                for a in self._carry:
                    _axpy(a.dtype)
                self._bwd_graph = self._capture(self._segment_adjoint, "backward")
            if self.graph:
                wp.capture_launch(self._bwd_graph)
            else:
                self._segment_adjoint()
            for slot, c in zip(self._slots, self._segment_controls(seg)):
                for arr, g in ((c.ee_vel, slot.ee_vel.grad), (c.ee_omega, slot.ee_omega.grad)):
                    if arr.grad is not None:
                        _add_grad(arr, g)
        if 0 in seeds:
            _add_grad(self._states[0].particle_x, seeds[0])

    # -- backward --------------------------------------------------------------
    def _taped_backward(self, seeds: dict):
        """The adjoint of :meth:`_taped_steps` from the seed gradients ``{record step: gradient}``."""
        self._zero_rollout_grads()
        for t, g in seeds.items():
            _add_grad(self._states[t].particle_x, g)
        self._tape.backward()

    def _zero_rollout_grads(self):
        """Zero the gradients of every state and grid of the rollout."""
        self._state_block.zero_grad()
        self._grid_block.zero_grad()

    def zero_grad(self, controls: Optional[Sequence[Control]] = None):
        """Zero the gradients of the model's parameters and of the controls."""
        for a in self.model.parameter_arrays():
            if a.grad is not None:
                a.grad.zero_()
        for c in controls or self._controls:
            for a in (c.ee_vel, c.ee_omega):
                if a.grad is not None:
                    a.grad.zero_()

    def _whole_backward(self, seeds: dict):
        """The backward pass of a rollout taped at once (replayed from its CUDA graph) or of unaligned
        checkpointed segments (each re-taped)."""
        states, grids = self._states, self._grids
        if self.graph and self._bwd_graph is None:
            self._seed_bufs = {t: wp.zeros_like(states[t].particle_x) for t in self.record_steps}
            _axpy(states[0].particle_x.dtype)  # made (and its module loaded) before the capture
            self._bwd_graph = self._capture(lambda: self._taped_backward(self._seed_bufs), "backward")
        if self.graph:
            for t, buf in self._seed_bufs.items():
                _set_array(buf, seeds[t])
            wp.capture_launch(self._bwd_graph)
        elif not self.checkpointed:
            self._taped_backward(seeds)
        else:
            S = self.segment
            adj = None
            for seg in reversed(range(len(self._checkpoints))):
                t0, t1 = seg * S, min(seg * S + S, self.steps)
                self._zero_rollout_grads()
                states[0].assign(self._checkpoints[seg])
                tape = wp.Tape()
                with tape:
                    for t in range(t0, t1):
                        self.solver.step(states[t - t0], states[t - t0 + 1], self._control(self._controls, t),
                                         self.dt, grids[t - t0], guards=False)
                for t in range(t0 + 1, t1 + 1):
                    if t in seeds:
                        _add_grad(states[t - t0].particle_x, seeds[t])
                if adj is not None:
                    for arr, g in zip(states[t1 - t0].arrays(), adj):
                        _add_grad(arr, g)
                tape.backward()
                adj = [wp.clone(a.grad) for a in states[0].arrays()]
                # no tape.reset(): it would zero the accumulated parameter gradients
            if 0 in seeds:
                _add_grad(states[0].particle_x, seeds[0])

    def backward(self, record_grads: Sequence, state0: Optional[State] = None):
        """Back-propagate d loss / d recorded positions (one [N, 3] array per record, None for zero).

        Gradients accumulate into the model arrays and controls; the gradient with respect to the initial
        state is left in ``self.initial_grad`` (and added to ``state0``'s gradients if it has them).
        """
        if len(record_grads) != len(self.record_steps):
            raise ValueError(f"Rollout.backward: expected {len(self.record_steps)} record gradients, got {len(record_grads)}")
        seeds = dict(zip(self.record_steps, record_grads))
        if self.aligned:
            self._segments_backward(seeds)
        else:
            self._whole_backward(seeds)
        first = self._states[0]
        # the kernels read per-particle parameter copies: sum their gradients into the world arrays
        m = self.model
        m.accumulate_material_grads()
        if m.particle_E.grad is not None:  # zero them so that a second backward does not add them twice
            for a in m.particle_parameter_arrays():
                a.grad.zero_()
        self.initial_grad = {name: wp.clone(a.grad) for name, a in zip(State.ARRAYS, first.arrays())}
        if state0 is not None and state0.requires_grad:
            for name, a in zip(State.ARRAYS, state0.arrays()):
                _add_grad(a, self.initial_grad[name])

    def memory_bytes(self) -> int:
        """Bytes held by the rollout's states, grids and checkpoints (values and gradients)."""
        total = 0
        for s in self._states + self._checkpoints:
            total += sum(a.capacity * (2 if a.grad is not None else 1) for a in s.arrays())
        for g in self._grids:
            total += sum(a.capacity * (2 if a.grad is not None else 1) for a in (g.mvm, g.v)) + g.columns.capacity
        return total
