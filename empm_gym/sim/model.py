"""Model (static), State (time-varying) and Control (per-step action) of a batch of MPM worlds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np
import warp as wp

from . import kernels as _kernels
from .config import (SHAPE_IDS, EndEffectorConfig, GridConfig, MaterialConfig, TableConfig, as_vec3,
                     end_effector_speed)
from .effects import PARAMETERS as _EFFECT_PARAMS

__all__ = ["Model", "ModelBuilder", "State", "StateBlock", "Control"]


def _arr(a, dtype, device, requires_grad=False):
    return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device, requires_grad=requires_grad)


class State:
    """Time-varying quantities: particle x [m], v [m/s], affine velocity C [1/s], elastic F [-], damage
    [-] (0 intact .. 1 broken; the fracture effect), end-effector positions [m] and orientations
    (quaternion x, y, z, w)."""

    def __init__(self, model: "Model", requires_grad: bool = False, *, arrays: Optional[dict] = None):
        """Zeroed arrays of their own, or (``arrays``, from :class:`StateBlock`) the given ones."""
        self.requires_grad = requires_grad
        if arrays is None:
            arrays = {name: wp.zeros(size, dtype=dtype, device=model.device, requires_grad=requires_grad)
                      for name, dtype, size in self.fields(model)}
        for name in self.ARRAYS:
            setattr(self, name, arrays[name])

    ARRAYS = ("particle_x", "particle_v", "particle_C", "particle_F", "particle_damage", "ee_pos", "ee_rot")

    @classmethod
    def fields(cls, model: "Model"):
        """(name, dtype, length) of each array, in the order of ``ARRAYS``."""
        n, e = model.particle_count, max(model.world_count * model.ee_count, 1)
        dtypes = (wp.vec3, wp.vec3, wp.mat33, wp.mat33, float, wp.vec3, wp.quat)
        return [(name, dtype, n if name.startswith("particle") else e) for name, dtype in zip(cls.ARRAYS, dtypes)]

    def arrays(self):
        return [getattr(self, a) for a in self.ARRAYS]

    def assign(self, other: "State") -> "State":
        """Copy the values (not the gradients) of another state into this one."""
        for a, b in zip(self.arrays(), other.arrays()):
            a.assign(b)
        return self

    def zero_grad(self):
        for a in self.arrays():
            if a.grad is not None:
                a.grad.zero_()

    def to_numpy(self) -> dict:
        return {name: arr.numpy().copy() for name, arr in zip(self.ARRAYS, self.arrays())}

    def from_numpy(self, data: dict) -> "State":
        for name, arr in zip(self.ARRAYS, self.arrays()):
            if name == "particle_damage" and name not in data:  # a state saved before the fracture effect
                arr.zero_()
                continue
            val = np.asarray(data[name], dtype=np.float32)
            if val.shape != tuple(arr.numpy().shape):
                raise ValueError(f"State.from_numpy: {name} has shape {val.shape}, expected {arr.numpy().shape}")
            arr.assign(wp.array(val, dtype=arr.dtype, device=arr.device))
        return self



class StateBlock:
    """``count`` states whose arrays are the rows of one array per field: a rollout of thousands of substeps
    allocates, and zeroes the gradients of, all its states with one call per field instead of one per state
    and field (on a GPU each call costs tens of microseconds, and each zeroing one node of a CUDA graph)."""

    def __init__(self, model: "Model", count: int, requires_grad: bool = False):
        if count <= 0:
            raise ValueError(f"StateBlock: count must be a positive number of states, got {count}")
        self.blocks = [wp.zeros((count, size), dtype=dtype, device=model.device, requires_grad=requires_grad)
                       for _, dtype, size in State.fields(model)]
        self.states = [State(model, requires_grad, arrays={name: b[i] for name, b in zip(State.ARRAYS, self.blocks)})
                       for i in range(count)]

    def zero_grad(self):
        for b in self.blocks:
            if b.grad is not None:
                b.grad.zero_()

class Control:
    """Action of one step: end-effector linear velocity [m/s], angular velocity [rad/s], grip flag."""

    def __init__(self, model: "Model", requires_grad: bool = False):
        e, d = max(model.world_count * model.ee_count, 1), model.device
        self.model = model
        self.ee_vel = wp.zeros(e, dtype=wp.vec3, device=d, requires_grad=requires_grad)
        self.ee_omega = wp.zeros(e, dtype=wp.vec3, device=d, requires_grad=requires_grad)
        self.ee_grip = wp.zeros(e, dtype=int, device=d)
        self.max_speed = 0.0
        """Largest commanded speed [m/s] of an end-effector's surface, its turn included (host copy, for the CFL
        check)."""
        shape = (model.world_count, model.ee_count, 3)
        self._vel, self._omega = np.zeros(shape), np.zeros(shape)   # host copies, for max_speed

    def set(self, velocity=None, omega=None, grip=None) -> "Control":
        """Set end-effector commands from arrays shaped [worlds, ee_count, 3] (grip: [worlds, ee_count]).

        Raises ``ValueError`` on a wrong shape or a NaN/inf value before anything reaches a kernel.
        """
        W, K = self.model.world_count, self.model.ee_count
        if velocity is not None:
            v = _checked(velocity, (W, K, 3), "Control.velocity")
            self.ee_vel.assign(wp.array(v.reshape(-1, 3), dtype=wp.vec3, device=self.ee_vel.device))
            self._vel = v
        if omega is not None:
            o = _checked(omega, (W, K, 3), "Control.omega")
            self.ee_omega.assign(wp.array(o.reshape(-1, 3), dtype=wp.vec3, device=self.ee_vel.device))
            self._omega = o
        if velocity is not None or omega is not None:
            self.max_speed = end_effector_speed(self._vel, self._omega, self.model.ee_reach[:W * K].reshape(W, K))
        if grip is not None:
            g = _checked_grip(grip, (W, K))
            self.ee_grip.assign(wp.array(g.reshape(-1).astype(np.int32), dtype=int, device=self.ee_vel.device))
        return self

    def sequence(self, velocity, omega, grip) -> "ControlSequence":
        """The commands of T steps, shaped as :meth:`set` takes them with a leading step axis (velocity, omega
        [T, worlds, ee_count, 3], grip [T, worlds, ee_count]), checked as :meth:`set` checks them and copied to
        the device once; :meth:`set_step` then sets step t's without a transfer from the host (which may
        wait for the stream: a simulation queued on a stream of its own would stall on it)."""
        W, K = self.model.world_count, self.model.ee_count
        T = len(velocity)
        v = _checked(velocity, (T, W, K, 3), "Control.velocity")
        o = _checked(omega, (T, W, K, 3), "Control.omega")
        g = _checked_grip(grip, (T, W, K))
        reach = self.model.ee_reach[:W * K].reshape(W, K)
        d = self.ee_vel.device
        return ControlSequence(steps=T, per_step=W * K,
                               velocity=wp.array(v.reshape(-1, 3), dtype=wp.vec3, device=d),
                               omega=wp.array(o.reshape(-1, 3), dtype=wp.vec3, device=d),
                               grip=wp.array(g.reshape(-1).astype(np.int32), dtype=int, device=d),
                               max_speed=np.array([end_effector_speed(v[t], o[t], reach) for t in range(T)]))

    def set_step(self, seq: "ControlSequence", t: int) -> "Control":
        """Set the commands of step ``t`` of ``seq`` (:meth:`sequence`), copied on the device on the current
        stream: the same values :meth:`set` would set from step t's arrays."""
        if not 0 <= t < seq.steps:
            raise IndexError(f"Control.set_step: step {t} of a sequence of {seq.steps}")
        n = seq.per_step
        if n:
            wp.copy(self.ee_vel, seq.velocity, src_offset=t * n, count=n)
            wp.copy(self.ee_omega, seq.omega, src_offset=t * n, count=n)
            wp.copy(self.ee_grip, seq.grip, src_offset=t * n, count=n)
        self.max_speed = float(seq.max_speed[t])
        return self


@dataclass
class ControlSequence:
    """End-effector commands of several steps on the device (:meth:`Control.sequence`)."""

    steps: int
    per_step: int
    velocity: wp.array
    omega: wp.array
    grip: wp.array
    max_speed: np.ndarray


def _checked_grip(value, shape):
    """Grip flags of ``shape`` (:func:`_checked`), each 0 (open) or 1 (closed)."""
    g = _checked(value, shape, "Control.grip")
    if not np.all((g == 0) | (g == 1)):
        raise ValueError(f"Control.grip must hold only 0 (open) or 1 (closed), got {np.unique(g)}")
    return g


def _checked(value, shape, name):
    a = np.asarray(value, dtype=np.float32)
    if a.shape != shape:
        if a.size == int(np.prod(shape)):
            a = a.reshape(shape)
        else:
            raise ValueError(f"{name} must have shape {shape}, got {np.shape(value)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds non-finite values (NaN or inf): {a.reshape(-1)[~np.isfinite(a.reshape(-1))][:4]}")
    return a


def principal_coords(x: np.ndarray) -> np.ndarray:
    """Rest coordinates [n, 3] of points x [n, 3] (m) along their principal axes (1 = longest), each scaled
    to [-1, 1]; an axis points towards the world axis it is most aligned with (so the field is the same
    for two samplings of one body)."""
    x = np.asarray(x, np.float64)
    c = x.mean(0)
    r = x - c
    if len(x) < 2:
        return np.zeros_like(x)
    w, V = np.linalg.eigh(r.T @ r / len(x))
    order = np.argsort(w)[::-1]
    w, V = w[order], V[:, order]
    # two extents within 15 % of each other (a square slab's) leave their axes to sampling noise: take the
    # pair's plane and, in it, the world axis (x before y before z) that lies nearest to it
    close = [w[i] > 0 and (w[i] - w[i + 1]) / w[i] < 0.15 for i in (0, 1)]
    if all(close) or (w[0] > 0 and w[2] / w[0] > 0.7):  # three similar extents (a cube, a lump): world axes
        close = [True, True]
        V = np.eye(3)
    for i in (0, 1):
        if close[i] and not all(close):
            P = V[:, i:i + 2]
            proj = P @ P.T                                   # projector onto the pair's plane
            norms = np.linalg.norm(proj, axis=0)
            k = int(np.argmax(norms >= 0.98 * norms.max()))  # the first of the world axes nearly in the plane
            a = proj[:, k] / np.linalg.norm(proj[:, k])
            c = P[:, 0] if abs(P[:, 0] @ a) < 0.7 else P[:, 1]
            b = c - (c @ a) * a
            V[:, i], V[:, i + 1] = a, b / np.linalg.norm(b)
    for i in range(3):
        j = int(np.argmax(np.abs(V[:, i])))
        if V[j, i] < 0:
            V[:, i] = -V[:, i]
    u = r @ V
    ext = np.maximum(np.abs(u).max(0), 1e-9)
    return u / ext


def _principal_coords(per_world: List[np.ndarray]) -> np.ndarray:
    return np.concatenate([principal_coords(x) for x in per_world]).astype(np.float32)


@dataclass
class _World:
    material: MaterialConfig
    table_friction: float
    positions: List[np.ndarray]
    volumes: List[np.ndarray]
    stiffness: List[np.ndarray]
    ee: List[tuple]


class ModelBuilder:
    """Collects worlds, particles and end-effectors, then :meth:`finalize` makes a :class:`Model`.

    All worlds share the grid geometry; each has its own grid, material, particles and end-effectors,
    and all advance together in one kernel launch per substep.
    """

    def __init__(
        self,
        grid: GridConfig = GridConfig(),
        *,
        gravity: Sequence[float] = (0.0, 0.0, -9.81),
        table: Optional[TableConfig] = TableConfig(),
    ):
        self.grid = grid
        self.gravity = as_vec3("gravity", gravity)
        self.table = table
        self.worlds: List[_World] = []

    def add_world(self, material: MaterialConfig, *, table_friction: Optional[float] = None) -> int:
        """Add a world with its material; returns the world index."""
        if not isinstance(material, MaterialConfig):
            raise TypeError(f"material must be a MaterialConfig, got {type(material).__name__}")
        if table_friction is None:
            table_friction = material.get("friction")  # the material's own table friction, if it has one
        mu = self.table.friction if (table_friction is None and self.table is not None) else (table_friction or 0.0)
        TableConfig(friction=mu)  # validates
        self.worlds.append(_World(material, float(mu), [], [], [], []))
        return len(self.worlds) - 1

    def _world(self, world: int) -> _World:
        if not (0 <= world < len(self.worlds)):
            raise IndexError(f"world {world} does not exist (have {len(self.worlds)}); call add_world first")
        return self.worlds[world]

    def add_particles(self, world: int, positions, volumes, *, stiffness_scale=None) -> slice:
        """Add particles at positions [n, 3] (m) with rest volumes [n] (m^3); returns their index range."""
        w = self._world(world)
        x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        vol = np.broadcast_to(np.asarray(volumes, dtype=np.float64), (len(x),)).copy()
        if not np.all(np.isfinite(x)):
            raise ValueError("add_particles: positions hold non-finite values")
        if np.any(vol <= 0) or not np.all(np.isfinite(vol)):
            raise ValueError("add_particles: volumes must be finite and > 0 m^3")
        lo = np.asarray(self.grid.lower) + 2 * self.grid.dx
        hi = np.asarray(self.grid.upper) - 3 * self.grid.dx
        bad = np.any((x < lo) | (x > hi), axis=1)
        if np.any(bad):
            raise ValueError(
                f"add_particles: {int(bad.sum())} particles lie outside the usable grid box "
                f"[{lo.round(4).tolist()}, {hi.round(4).tolist()}] m, e.g. {x[bad][0].round(4).tolist()}"
            )
        s = np.ones(len(x)) if stiffness_scale is None else np.broadcast_to(stiffness_scale, (len(x),)).astype(float)
        if np.any(s <= 0):
            raise ValueError("add_particles: stiffness_scale must be > 0")
        start = sum(len(p) for p in w.positions)
        w.positions.append(x)
        w.volumes.append(vol)
        w.stiffness.append(s)
        return slice(start, start + len(x))

    def add_end_effector(self, world: int, config: EndEffectorConfig, position, orientation=(0, 0, 0, 1)) -> int:
        """Add a kinematic end-effector at position [m] with orientation quaternion (x, y, z, w)."""
        w = self._world(world)
        p = as_vec3("end-effector position", position)
        q = np.asarray(orientation, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
            raise ValueError(f"end-effector orientation must be a unit quaternion (x, y, z, w), got {orientation!r}")
        w.ee.append((config, p, q / np.linalg.norm(q)))
        return len(w.ee) - 1

    def finalize(self, device=None, *, requires_grad: bool = False) -> "Model":
        if not self.worlds:
            raise ValueError("ModelBuilder.finalize: add at least one world")
        for i, w in enumerate(self.worlds):
            if not w.positions:
                raise ValueError(f"ModelBuilder.finalize: world {i} has no particles")
        return Model(self, device=device, requires_grad=requires_grad)


class Model:
    """What does not change during a rollout: grid, particle rest volumes, materials, end-effector shapes.

    Material parameters are Warp arrays, one entry per world (``world_E`` [Pa], ``world_nu``,
    ``world_density`` [kg/m^3], ``world_yield`` [Pa], ``world_viscosity`` [Pa s], ``world_table_friction``), plus a per-particle
    stiffness multiplier ``particle_stiffness`` for spatially varying stiffness; with
    ``requires_grad=True`` they carry gradients.
    """

    def __init__(self, builder: ModelBuilder, device=None, requires_grad: bool = False):
        self.device = wp.get_device(device)
        self.requires_grad = requires_grad
        g = builder.grid
        self.grid = g
        self.dx = float(g.dx)
        self.inv_dx = 1.0 / self.dx
        self.grid_origin = tuple(float(v) for v in g.lower)
        self.grid_res = g.resolution
        self.gravity = builder.gravity
        self.table = builder.table
        self.world_count = len(builder.worlds)
        self.ee_count = max(len(w.ee) for w in builder.worlds)

        xs, vols, worlds, stiff = [], [], [], []
        self.world_particle_start = []
        for i, w in enumerate(builder.worlds):
            self.world_particle_start.append(sum(len(x) for x in xs))
            x = np.concatenate(w.positions)
            xs.append(x)
            vols.append(np.concatenate(w.volumes))
            stiff.append(np.concatenate(w.stiffness))
            worlds.append(np.full(len(x), i, dtype=np.int32))
        self.world_particle_start.append(sum(len(x) for x in xs))
        self.particle_count = self.world_particle_start[-1]
        self._x0 = np.concatenate(xs).astype(np.float32)
        d = self.device
        self.particle_world = _arr(np.concatenate(worlds), int, d)
        self.particle_vol = _arr(np.concatenate(vols).astype(np.float32), float, d)
        self.particle_stiffness = _arr(np.concatenate(stiff).astype(np.float32), float, d, requires_grad)

        self.materials = [w.material for w in builder.worlds]
        self.world_E = wp.zeros(self.world_count, dtype=float, device=d, requires_grad=requires_grad)
        self.world_nu = wp.zeros(self.world_count, dtype=float, device=d, requires_grad=requires_grad)
        self.world_density = wp.zeros(self.world_count, dtype=float, device=d, requires_grad=requires_grad)
        self.world_yield = wp.zeros(self.world_count, dtype=float, device=d, requires_grad=requires_grad)
        self.world_plastic = wp.zeros(self.world_count, dtype=int, device=d)
        self.world_viscosity = wp.zeros(self.world_count, dtype=float, device=d, requires_grad=requires_grad)
        self.world_table_friction = _arr(
            np.array([w.table_friction for w in builder.worlds], np.float32), float, d, requires_grad
        )
        # effects of empm_gym.sim.effects beyond plasticity, viscosity and table friction (per world)
        self.world_grip_friction = wp.zeros(self.world_count, dtype=float, device=d, requires_grad=requires_grad)
        self.world_stiffness_slope = wp.zeros(self.world_count, dtype=wp.vec3, device=d, requires_grad=requires_grad)
        self.world_fracture_strain = wp.zeros(self.world_count, dtype=float, device=d, requires_grad=requires_grad)
        self.world_fracture_softening = wp.zeros(self.world_count, dtype=float, device=d,
                                                 requires_grad=requires_grad)
        # rest coordinates along each world's principal axes, in [-1, 1] (heterogeneous stiffness)
        self.particle_body_coord = _arr(_principal_coords(xs), wp.vec3, d)
        # per-particle copies read by the kernels: no gradient contention on one address per world;
        # the rollout sums their gradients into the world arrays once per backward pass
        n = self.particle_count
        self.particle_E = wp.zeros(n, dtype=float, device=d, requires_grad=requires_grad)
        self.particle_nu = wp.zeros(n, dtype=float, device=d, requires_grad=requires_grad)
        self.particle_density = wp.zeros(n, dtype=float, device=d, requires_grad=requires_grad)
        self.particle_yield = wp.zeros(n, dtype=float, device=d, requires_grad=requires_grad)
        self.particle_plastic = wp.zeros(n, dtype=int, device=d)
        self.particle_viscosity = wp.zeros(n, dtype=float, device=d, requires_grad=requires_grad)
        self.particle_fracture_strain = wp.zeros(n, dtype=float, device=d, requires_grad=requires_grad)
        self.particle_fracture_softening = wp.zeros(n, dtype=float, device=d, requires_grad=requires_grad)
        self.particle_p2g = wp.zeros(n, dtype=wp.vec4, device=d)
        """(mu V, lambda V, eta V, mass) per particle, packed for the sorted P2G (no gradient; see
        update_particle_materials)."""
        self.set_materials(self.materials)

        K, W = self.ee_count, self.world_count
        n = max(W * K, 1)
        shape = -np.ones(n, np.int32)
        radius = np.zeros(n, np.float32)
        hh = np.zeros(n, np.float32)
        he = np.zeros((n, 3), np.float32)
        fr = np.zeros(n, np.float32)
        jaws = np.zeros(n, np.int32)
        self.ee_reach = np.zeros(n)
        """Host copy: each end-effector's :attr:`EndEffectorConfig.reach` [m] (worlds x ee_count)."""
        self._ee_pos0 = np.zeros((n, 3), np.float32)
        self._ee_rot0 = np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1))
        self.ee_configs: List[List[EndEffectorConfig]] = []
        for wi, w in enumerate(builder.worlds):
            self.ee_configs.append([c for c, _, _ in w.ee])
            for e, (cfg, p, q) in enumerate(w.ee):
                s = wi * K + e
                shape[s] = SHAPE_IDS[cfg.shape]
                radius[s] = cfg.radius
                hh[s] = cfg.half_height
                he[s] = cfg.half_extents
                fr[s] = cfg.friction
                jaws[s] = int(cfg.gripper)
                self.ee_reach[s] = cfg.reach
                self._ee_pos0[s] = p
                self._ee_rot0[s] = q
        self.ee_shape = _arr(shape, int, d)
        self.ee_radius = _arr(radius, float, d)
        self.ee_half_height = _arr(hh, float, d)
        self.ee_half_extents = _arr(he, wp.vec3, d)
        self.ee_friction = _arr(fr, float, d, requires_grad)
        self.ee_gripper = _arr(jaws, int, d)

    # -- materials ---------------------------------------------------------
    def set_materials(self, materials: Sequence[MaterialConfig]):
        """Set every world's material (one MaterialConfig per world)."""
        if len(materials) != self.world_count:
            raise ValueError(f"set_materials: expected {self.world_count} materials, got {len(materials)}")
        for m in materials:
            if not isinstance(m, MaterialConfig):
                raise TypeError(f"set_materials: expected MaterialConfig, got {type(m).__name__}")
        self.materials = list(materials)
        self.world_E.assign(np.array([m.E for m in materials], np.float32))
        self.world_nu.assign(np.array([m.nu for m in materials], np.float32))
        self.world_density.assign(np.array([m.density for m in materials], np.float32))
        self.world_yield.assign(np.array([m.yield_stress or 0.0 for m in materials], np.float32))
        self.world_plastic.assign(np.array([int(m.plastic) for m in materials], np.int32))
        self.world_viscosity.assign(np.array([m.viscosity for m in materials], np.float32))
        self._set_effect_arrays(materials)
        self.update_particle_materials()

    def _set_effect_arrays(self, materials: Sequence[MaterialConfig]):
        """Write every effect parameter of :mod:`empm_gym.sim.effects` held in ``params`` to its per-world
        array (the effect's ``kernel_off`` value when absent; table friction only where a material sets it)."""
        arrays = {}
        for p in _EFFECT_PARAMS.values():
            if p.name in ("yield_stress", "viscosity"):
                continue
            arr = getattr(self, p.array)
            if p.array not in arrays:
                arrays[p.array] = arr.numpy().copy()
            host = arrays[p.array]
            for w, m in enumerate(materials):
                if p.name == "friction" and m.get("friction") is None:
                    continue  # keep the world's table friction
                v = m.kernel_value(p.name)
                if p.component is None:
                    host[w] = v
                else:
                    host[w, p.component] = v
        for name, host in arrays.items():
            getattr(self, name).assign(host)

    def update_particle_materials(self):
        """Copy the world material arrays (and stiffness multipliers) to the per-particle arrays the kernels read.

        Call after writing ``world_E`` & co. directly; ``set_materials`` and ``Rollout.forward`` do it. It also
        refreshes ``particle_p2g``, the packed copy that the untaped CUDA step reads.
        """
        wp.launch(
            _kernels.expand_materials_kernel,
            dim=self.particle_count,
            inputs=[self.particle_world, self.particle_stiffness, self.particle_body_coord, self.world_E,
                    self.world_nu, self.world_density, self.world_yield, self.world_plastic, self.world_viscosity,
                    self.world_stiffness_slope, self.world_fracture_strain, self.world_fracture_softening],
            outputs=[self.particle_E, self.particle_nu, self.particle_density, self.particle_yield,
                     self.particle_plastic, self.particle_viscosity, self.particle_fracture_strain,
                     self.particle_fracture_softening],
            device=self.device,
        )
        wp.launch(_kernels.pack_p2g_materials_kernel, dim=self.particle_count,
                  inputs=[self.particle_vol, self.particle_E, self.particle_nu, self.particle_density,
                          self.particle_viscosity],
                  outputs=[self.particle_p2g], device=self.device, record_tape=False)

    def accumulate_material_grads(self):
        """Add the per-particle parameter gradients into the world arrays' gradients (adjoint of the copy)."""
        if self.particle_E.grad is None:
            return
        wp.launch(
            _kernels.reduce_material_grads_kernel,
            dim=self.particle_count,
            inputs=[self.particle_world, self.particle_stiffness, self.particle_body_coord, self.world_E,
                    self.world_stiffness_slope, self.particle_E.grad,
                    self.particle_nu.grad, self.particle_density.grad, self.particle_yield.grad,
                    self.particle_viscosity.grad, self.particle_fracture_strain.grad,
                    self.particle_fracture_softening.grad],
            outputs=[self.world_E.grad, self.world_nu.grad, self.world_density.grad, self.world_yield.grad,
                     self.world_viscosity.grad, self.particle_stiffness.grad, self.world_stiffness_slope.grad,
                     self.world_fracture_strain.grad, self.world_fracture_softening.grad, self.particle_count],
            device=self.device,
        )

    def parameter_arrays(self):
        """Arrays that can carry gradients: world materials, table and end-effector friction, per-particle copies."""
        return [self.world_E, self.world_nu, self.world_density, self.world_yield, self.world_viscosity,
                self.world_table_friction, self.world_grip_friction, self.world_stiffness_slope,
                self.world_fracture_strain, self.world_fracture_softening, self.particle_stiffness,
                self.ee_friction, *self.particle_parameter_arrays()]

    def particle_parameter_arrays(self):
        """Per-particle parameter copies read by the kernels (their gradients are summed into the world arrays)."""
        return [self.particle_E, self.particle_nu, self.particle_density, self.particle_yield,
                self.particle_viscosity, self.particle_fracture_strain, self.particle_fracture_softening]

    def sync_materials_from_device(self):
        """Refresh the host copies (``materials``) after the device arrays were changed (e.g. by an optimiser)."""
        E, nu, rho, ys, eta = (a.numpy() for a in (self.world_E, self.world_nu, self.world_density,
                                                    self.world_yield, self.world_viscosity))
        pl = self.world_plastic.numpy()
        host = {}
        mats = []
        for i in range(self.world_count):
            params = {}
            for p in _EFFECT_PARAMS.values():
                if p.name in ("yield_stress", "viscosity", "friction"):
                    continue
                if p.array not in host:
                    host[p.array] = getattr(self, p.array).numpy()
                v = float(host[p.array][i] if p.component is None else host[p.array][i, p.component])
                if np.float32(v) != np.float32(p.kernel_off) or (p.name == "fracture_softening" and "fracture_strain" in params):
                    params[p.name] = v
            if "fracture_strain" not in params:
                params.pop("fracture_softening", None)
            if self.materials[i].get("friction") is not None:
                params["friction"] = float(self.world_table_friction.numpy()[i])
            mats.append(MaterialConfig(E=float(E[i]), nu=float(nu[i]), density=float(rho[i]),
                                       yield_stress=float(ys[i]) if pl[i] else None, viscosity=float(eta[i]),
                                       params=params))
        self.materials = mats

    def max_viscous_rate(self) -> float:
        """Largest kinematic viscosity eta / rho over worlds [m^2/s] (limits the explicit step)."""
        return max(m.viscosity / m.density for m in self.materials)

    def max_wave_speed(self) -> float:
        """Largest elastic P-wave speed over worlds [m/s], including the stiffness field and the per-particle
        stiffness multiplier."""
        smax = float(np.max(self.particle_stiffness.numpy())) if self.particle_count else 1.0
        return max(m.max_wave_speed for m in self.materials) * np.sqrt(max(smax, 1e-12))

    def stiffness_max(self) -> float:
        """Largest per-particle stiffness multiplier [-] (host copy)."""
        return float(np.max(self.particle_stiffness.numpy())) if self.particle_count else 1.0

    def particle_mass(self) -> np.ndarray:
        """Particle masses [kg] (host copy)."""
        rho = np.array([m.density for m in self.materials], np.float32)
        return self.particle_vol.numpy() * rho[self.particle_world.numpy()]

    # -- factories ---------------------------------------------------------
    def state(self, requires_grad: Optional[bool] = None) -> State:
        """A new State at the rest configuration given to the builder (F = I, v = 0)."""
        rg = self.requires_grad if requires_grad is None else requires_grad
        s = State(self, requires_grad=rg)
        s.particle_x.assign(self._x0)
        s.particle_F.assign(np.tile(np.eye(3, dtype=np.float32), (self.particle_count, 1, 1)))
        s.ee_pos.assign(self._ee_pos0)
        s.ee_rot.assign(self._ee_rot0)
        return s

    def control(self, requires_grad: Optional[bool] = None) -> Control:
        rg = self.requires_grad if requires_grad is None else requires_grad
        return Control(self, requires_grad=rg)

    def world_slice(self, world: int) -> slice:
        """Particle index range of one world."""
        return slice(self.world_particle_start[world], self.world_particle_start[world + 1])
