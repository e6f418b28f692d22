"""Explicit MLS-MPM / APIC solver: ``SolverMPM.step(state_in, state_out, control, dt)``."""

from __future__ import annotations

from typing import Optional

import numpy as np
import warp as wp
import warp._src.context as _wp_context

from . import kernels as K
from .config import SolverConfig, stable_dt
from .model import Control, Model, State

__all__ = ["SolverMPM", "GridScratch", "GridScratchBlock", "SimulationDiverged", "UnstableTimeStep"]


class SimulationDiverged(RuntimeError):
    """The state became non-finite (or impossibly fast); ``step`` and ``worlds`` say where."""

    def __init__(self, message: str, *, step: int, worlds):
        super().__init__(message)
        self.step = step
        self.worlds = list(worlds)


class UnstableTimeStep(ValueError):
    """The requested dt is above the CFL / elastic-wave limit; ``max_dt`` is the largest safe value [s]."""

    def __init__(self, message: str, *, max_dt: float):
        super().__init__(message)
        self.max_dt = max_dt


class GridScratch:
    """Grid arrays of one substep for every world: ``mvm`` holds momentum [kg m/s] (xyz) and mass [kg] (w)
    in one vec4 per node, so that P2G adds both with one atomic; ``v`` is the velocity [m/s].

    A differentiable rollout keeps one per taped substep, since the tape replays kernels with the
    arrays' current values.
    """

    def __init__(self, model: Model, requires_grad: bool = False, *, arrays: Optional[dict] = None):
        """Zeroed arrays of their own, or (``arrays``, from :class:`GridScratchBlock`) the given ones."""
        if arrays is None:
            arrays = {name: wp.zeros(shape, dtype=dtype, device=model.device, requires_grad=requires_grad and grad)
                      for name, dtype, shape, grad in self.fields(model)}
        self.clean = True
        """The mass and momentum arrays and the active-column count are known to be zero (freshly allocated or
        cleared in place by an untaped step)."""
        self.cleared = False
        """Mass, momentum and the active-column count were zeroed for the next step (GridScratchBlock.clear),
        which then skips its own memsets."""
        self.mvm = arrays["mvm"]
        self.columns = arrays["columns"]
        """1 where P2G reached a column (world, i, j) of nodes; active_columns_kernel lists and clears them."""
        self.active = arrays["active"]
        """The flagged columns' flat indices, ``active_count[0]`` of them (in any order)."""
        self.active_count = arrays["active_count"]
        self.v = arrays["v"]
        self.columns_flat = self.columns.flatten()

    @staticmethod
    def fields(model: Model):
        """(name, dtype, shape, differentiable) of each array."""
        shape = (model.world_count, *model.grid_res)
        return [("mvm", wp.vec4, shape, True), ("columns", int, shape[:3], False),
                ("active", int, (int(np.prod(shape[:3])),), False), ("active_count", int, (1,), False),
                ("v", wp.vec3, shape, True)]


class GridScratchBlock:
    """``count`` grids whose arrays are consecutive slices of one array per field (see StateBlock): a taped
    rollout keeps one grid per substep."""

    def __init__(self, model: Model, count: int, requires_grad: bool = False):
        if count <= 0:
            raise ValueError(f"GridScratchBlock: count must be a positive number of grids, got {count}")
        self.blocks = {}
        views = [{} for _ in range(count)]
        for name, dtype, shape, grad in GridScratch.fields(model):
            # warp arrays have at most 4 dimensions: stack the grids along the first one
            block = wp.zeros((count * shape[0], *shape[1:]), dtype=dtype, device=model.device,
                             requires_grad=requires_grad and grad)
            self.blocks[name] = block
            for i in range(count):
                views[i][name] = block[i * shape[0]:(i + 1) * shape[0]]
        self.grids = [GridScratch(model, arrays=a) for a in views]

    def clear(self):
        """Zero every grid's mass, momentum and active-column count with one memset per field: the next step
        on each grid skips its own two (a taped rollout's forward has one grid per substep)."""
        for name in ("mvm", "active_count"):
            self.blocks[name].zero_()
        for g in self.grids:
            g.cleared = True

    def zero_grad(self):
        for b in self.blocks.values():
            if b.grad is not None:
                b.grad.zero_()


_GRID_KERNELS = {}


def _grid_kernel(ee_count: int):
    """Grid-update kernel specialised to the number of end-effectors per world (unrolled loop)."""
    if ee_count not in _GRID_KERNELS:
        _GRID_KERNELS[ee_count] = K.make_grid_update_kernel(ee_count)
    return _GRID_KERNELS[ee_count]


def fixed_point_scales(mass: np.ndarray, world: np.ndarray, worlds: int, max_speed: float,
                       headroom: float = 2.0 ** 12) -> tuple:
    """Integer units of the deterministic P2G (``SolverConfig.deterministic``): (momentum units per kg m/s, mass
    units per kg) such that a world's whole mass moving at ``max_speed`` m/s times ``headroom`` fills 2^62 of
    the 2^63 a signed 64-bit integer holds. A grid node holds at most its world's mass, and a state faster than
    ``max_speed`` counts as diverged (:meth:`SolverMPM.check_state`): the headroom leaves room for the stress
    impulses inside one substep and for materials made denser after the solver (``Model.set_materials``).
    Powers of two, so that integers and floats convert by exact scalings. Resolution: under 2e-15 of a world's
    mass, and of its mass times ``max_speed``, far below float32's rounding of any node's own value."""
    totals = np.bincount(np.asarray(world, np.int64), weights=np.asarray(mass, np.float64), minlength=worlds)
    heaviest = float(np.max(totals)) if totals.size else 0.0
    if not np.isfinite(heaviest) or heaviest <= 0.0:
        raise ValueError(f"deterministic P2G: the worlds' masses must be finite and positive, got a largest total "
                         f"of {heaviest!r} kg")
    full = 2.0 ** 62 / headroom

    def unit(v):  # a power of two: the integers and their float values differ by an exact scaling
        return 2.0 ** np.floor(np.log2(v))

    return unit(full / (heaviest * max(float(max_speed), 1.0))), unit(full / heaviest)


class SolverMPM:
    """Explicit MLS-MPM (APIC transfers, quadratic B-splines) with fixed-corotated elasticity,
    optional von Mises plasticity, Dirichlet/Coulomb end-effectors and a frictional table.

    ``step`` advances every world of the model by one substep dt [s]."""

    def __init__(self, model: Model, config: Optional[SolverConfig] = None):
        self.model = model
        self.config = config or SolverConfig()
        if self.config.deterministic and model.device.is_cuda:
            # float atomics of P2G (and of every adjoint) otherwise sum in a run-dependent order on GPUs
            wp.set_module_options({"deterministic": wp.DeterministicMode.RUN_TO_RUN}, module=K)
        self.scratch = GridScratch(model)
        self.step_count = 0
        self._order = None
        self._keys = None
        self._fixed = None
        self._packed = int(model.device.is_cuda and not self.config.deterministic)
        nodes = model.world_count * int(np.prod(model.grid_res))
        n = model.particle_count
        # P2G with warp-summed atomics visits particles in cell order (CUDA only); the key must fit an int32
        if model.device.is_cuda and self.config.sort_every > 0 and nodes < 2**31:
            self._keys = wp.zeros(2 * n, dtype=int, device=model.device)
            self._values = wp.zeros(2 * n, dtype=int, device=model.device)
            self._key_bits = max(int(nodes - 1).bit_length(), 1)
            self._order = self._values[:n]
            self.sort_particles(model.state())  # also allocates the sort's scratch outside any graph capture
        elif self.config.deterministic and not model.device.is_cuda:
            self._order = wp.array(np.arange(n, dtype=np.int32), dtype=int, device=model.device)
        if self.config.deterministic and self._order is not None:
            # untaped steps: P2G sums in 64-bit fixed point (K.warp_segment_add_fixed), the same on every run;
            # on the CPU too, so that this path is tested where CI runs. Taped steps, and CUDA without the
            # sorted order, keep Warp's deterministic atomics (set above)
            self._fixed = wp.zeros((model.world_count, *model.grid_res), dtype=K.vec4l, device=model.device)
            self._fixed_scale = fixed_point_scales(model.particle_mass(), model.particle_world.numpy(),
                                                   model.world_count, self.config.max_speed)
        self._flags = wp.zeros(model.world_count, dtype=int, device=model.device)
        self._adjoint_sink = None
        self._grid_kernel = _grid_kernel(model.ee_count)
        # threads of the grid update, striding over the active nodes (on the CPU, which runs a launch as one
        # loop, as many as there are active nodes: step reads the count, which costs no transfer there)
        self._grid_threads = min(nodes, 2**17) if model.device.is_cuda else None

    # -- guards --------------------------------------------------------------
    def max_stable_dt(self, max_speed: float = 0.0) -> float:
        """Largest stable substep [s]: C * dx / (c + |v|max) with c the elastic P-wave speed, and, with
        viscosity, C * dx^2 / (3 eta / rho) (explicit diffusion of momentum)."""
        return stable_dt(self.model.materials, self.model.dx, self.config.cfl, max_speed, self.model.stiffness_max())

    def check_dt(self, dt: float, max_speed: float = 0.0):
        """Raise :class:`UnstableTimeStep` if dt [s] exceeds the stable limit."""
        if not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt must be a finite positive time step in seconds, got {dt!r}")
        limit = self.max_stable_dt(max_speed)
        if dt > limit * (1.0 + 1e-6):
            raise UnstableTimeStep(
                f"dt={dt:.3g} s exceeds the stable limit {limit:.3g} s "
                f"(CFL {self.config.cfl} * dx {self.model.dx:.3g} m / (wave speed "
                f"{self.model.max_wave_speed():.3g} m/s + end-effector speed {max_speed:.3g} m/s)"
                f"{', or the viscous limit' if self.model.max_viscous_rate() > 0 else ''}); "
                f"use dt <= {limit:.3g} s",
                max_dt=limit,
            )

    def check_state(self, state: State, step: Optional[int] = None):
        """Raise :class:`SimulationDiverged` if any world's state is non-finite or too fast."""
        self.queue_check(state, self._flags)
        flags = self._flags.numpy()
        if np.any(flags):
            bad = np.nonzero(flags)[0].tolist()
            why = "non-finite values" if np.any(flags == 1) else f"particle speed above {self.config.max_speed} m/s"
            step = self.step_count if step is None else step
            raise SimulationDiverged(
                f"simulation diverged at step {step} in world(s) {bad}: {why}; lower dt, stiffen the CFL number "
                f"(SolverConfig.cfl) or check the material and end-effector speeds",
                step=step,
                worlds=bad,
            )

    def queue_check(self, state: State, flags: wp.array):
        """Queue on the current stream the check of :meth:`check_state` into ``flags`` [worlds] (zeroed first):
        1 where a world holds non-finite values, 2 where a particle is faster than ``config.max_speed``, else 0.
        Read later, it lets a simulation run on without waiting for the check (``problem._ForwardSim``)."""
        m = self.model
        flags.zero_()
        wp.launch(
            K.check_state_kernel,
            dim=m.particle_count,
            inputs=[state.particle_x, state.particle_v, state.particle_F, m.particle_world, self.config.max_speed],
            outputs=[flags],
            device=m.device,
            record_tape=False,  # a guard, not part of the differentiable computation
        )

    def sort_particles(self, state: State):
        """Order P2G's threads by (world, stencil base node) of the particles of ``state`` (CUDA). Only the
        visiting order changes: particle arrays keep their order, and any order gives the same physics."""
        if self._keys is None:
            return
        m = self.model
        n = m.particle_count
        wp.launch(K.sort_keys_kernel, dim=n,
                  inputs=[state.particle_x, m.particle_world, wp.vec3(*m.grid_origin), m.inv_dx, wp.vec3i(*m.grid_res)],
                  outputs=[self._keys, self._values], device=m.device, record_tape=False)
        wp.utils.radix_sort_pairs(self._keys, self._values, n, end_bit=self._key_bits)

    def _sink(self) -> wp.array:
        """The grid-shaped vec4 array into which a taped step's G2P adjoint adds the grid velocity's gradient
        (zero between backward steps: each flush zeroes what it moves)."""
        if self._adjoint_sink is None:
            m = self.model
            self._adjoint_sink = wp.zeros((m.world_count, *m.grid_res), dtype=wp.vec4, device=m.device)
        return self._adjoint_sink

    def _flush_sink(self, g: GridScratch, threads: int):
        m = self.model
        grad = g.v.grad
        wp.launch(K.flush_adjoint_sink_kernel, dim=threads,
                  inputs=[g.active, g.active_count, wp.vec3i(*m.grid_res), threads, int(grad is not None),
                          self._adjoint_sink, grad if grad is not None else g.v],
                  device=m.device, record_tape=False)

    # -- step ----------------------------------------------------------------
    def step(self, state_in: State, state_out: State, control: Control, dt: float,
             scratch: Optional[GridScratch] = None, *, guards: bool = True, sort: Optional[bool] = None):
        """Advance all worlds by one substep of dt [s] from ``state_in`` into ``state_out``.

        ``scratch`` gives the grid arrays to use (one per taped substep in a differentiable rollout);
        ``guards=False`` skips the dt and divergence checks (a rollout that already made them).
        ``sort`` re-sorts P2G's particle order by cell first (CUDA, untaped steps on the solver's own grid;
        None: every ``config.sort_every`` steps; a caller that captures a fixed group of substeps in a CUDA
        graph passes True on its first one).
        """
        if guards:
            self.check_dt(dt, control.max_speed)
        m = self.model
        g = scratch or self.scratch
        # the solver's own grid, outside any tape, is cleared inside the grid kernel (saves two passes);
        # a taped substep keeps its grid values for the backward pass and is cleared here instead
        fused = scratch is None and _wp_context.runtime.tape is None
        if g.cleared:
            g.cleared = False
        elif not (fused and g.clean):  # (the column flags are always clear: active_columns_kernel clears them)
            g.mvm.zero_()
            g.active_count.zero_()
        origin = wp.vec3(*m.grid_origin)
        res = wp.vec3i(*m.grid_res)
        particles = [
            state_in.particle_x, state_in.particle_v, state_in.particle_C, state_in.particle_F,
            state_in.particle_damage, m.particle_world, m.particle_vol, m.particle_E, m.particle_nu, m.particle_density,
            m.particle_viscosity,
        ]
        # taped steps: per-particle atomics and transfers with hand-written adjoints (Warp's deterministic mode
        # keeps Warp's own adjoints). The warp-summed P2G serves untaped steps only: on one H100 an
        # identification fit taped through it gave non-finite material gradients in blocks of 32 threads (not
        # reproduced on the CPU, not yet understood)
        native = not fused and not self.config.deterministic
        fixed = False  # whether P2G summed into the fixed-point grid (then turned into floats below)
        if native:
            wp.launch(K.p2g_native_kernel, dim=m.particle_count,
                      inputs=[*particles, origin, m.dx, m.inv_dx, res, dt, self._packed], outputs=[g.mvm, g.columns],
                      device=m.device)
        elif self._order is None or not fused:
            wp.launch(K.p2g_kernel, dim=m.particle_count,
                      inputs=[*particles, origin, m.dx, m.inv_dx, res, dt, self._packed], outputs=[g.mvm],
                      device=m.device)
            wp.launch(K.mark_columns_kernel, dim=m.particle_count,
                      inputs=[state_in.particle_x, m.particle_world, origin, m.inv_dx, res], outputs=[g.columns],
                      device=m.device, record_tape=False)
        else:
            if sort is None:
                sort = self.step_count % self.config.sort_every == 0
            if sort:
                self.sort_particles(state_in)
            fixed = self._fixed is not None
            wp.launch(K.p2g_sorted_kernel, dim=m.particle_count,
                      inputs=[self._order, state_in.particle_x, state_in.particle_v, state_in.particle_C,
                              state_in.particle_F, state_in.particle_damage, m.particle_world, m.particle_p2g,
                              origin, m.dx, m.inv_dx, res, dt, m.particle_count, int(fixed),
                              wp.vec2(*self._fixed_scale) if fixed else wp.vec2(0.0)],
                      outputs=[g.mvm, g.columns, self._fixed], device=m.device)
        has_table = 1 if m.table is not None else 0
        table_z = float(m.table.height) if m.table is not None else 0.0
        wp.launch(K.active_columns_kernel, dim=g.columns.size, inputs=[g.columns_flat, g.columns.size],
                  outputs=[g.active, g.active_count], device=m.device, record_tape=False)
        threads = self._grid_threads or max(int(g.active_count.numpy()[0]) * m.grid_res[2], 1)
        threads = max(threads, m.world_count * m.ee_count)  # its first threads also move the end-effectors
        if fixed:
            wp.launch(K.fixed_grid_to_float_kernel, dim=threads,
                      inputs=[self._fixed, g.active, g.active_count, res, 1.0 / self._fixed_scale[0],
                              1.0 / self._fixed_scale[1], threads], outputs=[g.mvm], device=m.device,
                      record_tape=False)
        wp.launch(
            self._grid_kernel,
            dim=threads,
            inputs=[
                g.mvm, g.active, g.active_count, origin, m.dx, res, dt, wp.vec3(*m.gravity), m.grid.boundary_cells,
                has_table, table_z, m.world_table_friction,
                m.ee_shape, m.ee_radius, m.ee_half_height, m.ee_half_extents, m.ee_friction,
                m.ee_gripper, state_in.ee_pos, state_in.ee_rot, control.ee_vel, control.ee_omega, control.ee_grip,
                m.world_grip_friction, int(fused), threads,
            ],
            outputs=[g.v, state_out.ee_pos, state_out.ee_rot],
            device=m.device,
        )
        g.clean = fused
        if native:
            # G2P's adjoint leaves grid_v's gradient in the solver's sink (16-byte atomics); the tape, replayed
            # backwards, moves it into this grid's gradient right after G2P's adjoint
            sink = self._sink()
            tape = _wp_context.runtime.tape
            if tape is not None:
                tape.record_func(backward=lambda: self._flush_sink(g, threads), arrays=[])
        # G2P keeps the particles' own order: in cell order its reads and writes scatter (measured slower)
        wp.launch(
            K.g2p_native_kernel if native else K.g2p_kernel,
            dim=m.particle_count,
            inputs=[
                state_in.particle_x, state_in.particle_F, state_in.particle_damage, m.particle_world,
                m.particle_E, m.particle_nu, m.particle_yield, m.particle_plastic,
                m.particle_fracture_strain, m.particle_fracture_softening,
                g.v, *([sink] if native else []), origin, m.dx, m.inv_dx, res, dt,
                self.config.plasticity_min_singular, *([] if native else [g.active_count, int(fused)]),
            ],
            outputs=[state_out.particle_x, state_out.particle_v, state_out.particle_C, state_out.particle_F,
                     state_out.particle_damage],
            device=m.device,
        )
        self.step_count += 1
        ce = self.config.check_every
        if guards and ce > 0 and self.step_count % ce == 0:
            self.check_state(state_out)
