"""Configuration dataclasses of the simulator: material, grid, table, end-effectors, solver.

Every field carries its SI unit in its docstring. Each config validates itself on
construction and raises ``ValueError`` naming the field, the value and what is
allowed, so a bad parameter never turns into a NaN three layers later.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Dict, Mapping, Optional, Sequence, Tuple

__all__ = [
    "MaterialConfig",
    "GridConfig",
    "TableConfig",
    "EndEffectorConfig",
    "SolverConfig",
    "SHAPE_IDS",
    "end_effector_speed",
    "stable_dt",
]

#: End-effector shape names and their integer ids in the kernels.
SHAPE_IDS = {"sphere": 0, "capsule": 1, "box": 2}


def _finite(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return value


@dataclass(frozen=True)
class MaterialConfig:
    """Constitutive parameters of one object (fixed-corotated elasticity, optional von Mises plasticity)."""

    E: float = 1.0e5
    """Young's modulus [Pa]; > 0."""
    nu: float = 0.3
    """Poisson's ratio [-]; in (-1, 0.5)."""
    density: float = 1000.0
    """Mass density [kg/m^3]; > 0."""
    yield_stress: Optional[float] = None
    """Uniaxial von Mises yield stress [Pa]; ``None`` for a purely elastic material, else >= 0."""
    viscosity: float = 0.0
    """Newtonian (Kelvin-Voigt) viscosity eta [Pa s] adding tau = J eta (grad v + grad v^T); damps
    deformation, not rigid motion; >= 0 (0: none)."""
    params: Optional[Mapping[str, float]] = None
    """Values of the other effect parameters of :mod:`empm_gym.sim.effects` (``friction`` [-] of the table,
    ``grip_friction`` [-], ``stiffness_slope_1..3`` [-], ``fracture_strain`` [-], ``fracture_softening``
    [-]); an absent parameter takes its effect's ``off`` value. ``friction`` overrides the table's own."""

    def __post_init__(self):
        E = _finite("MaterialConfig.E", self.E)
        nu = _finite("MaterialConfig.nu", self.nu)
        rho = _finite("MaterialConfig.density", self.density)
        if E <= 0.0:
            raise ValueError(f"MaterialConfig.E must be > 0 Pa, got {self.E!r}")
        if not (-1.0 < nu < 0.5):
            raise ValueError(f"MaterialConfig.nu must lie in (-1, 0.5), got {self.nu!r}")
        if rho <= 0.0:
            raise ValueError(f"MaterialConfig.density must be > 0 kg/m^3, got {self.density!r}")
        object.__setattr__(self, "E", E)
        object.__setattr__(self, "nu", nu)
        object.__setattr__(self, "density", rho)
        eta = _finite("MaterialConfig.viscosity", self.viscosity)
        if eta < 0.0:
            raise ValueError(f"MaterialConfig.viscosity must be >= 0 Pa s, got {self.viscosity!r}")
        object.__setattr__(self, "viscosity", eta)
        if self.yield_stress is not None:
            ys = _finite("MaterialConfig.yield_stress", self.yield_stress)
            if ys < 0.0:
                raise ValueError(f"MaterialConfig.yield_stress must be >= 0 Pa or None, got {self.yield_stress!r}")
            object.__setattr__(self, "yield_stress", ys)
        from .effects import PARAMETERS

        extra = {}
        for k, v in dict(self.params or {}).items():
            if k in ("yield_stress", "viscosity") or k not in PARAMETERS:
                raise ValueError(f"MaterialConfig.params: unknown effect parameter {k!r}; allowed: "
                                 f"{', '.join(n for n in PARAMETERS if n not in ('yield_stress', 'viscosity'))}"
                                 f" (yield_stress and viscosity are fields)")
            if v is None:
                continue
            extra[k] = PARAMETERS[k].check(v, "MaterialConfig.params: ")
        if "fracture_strain" not in extra and "fracture_softening" in extra:
            raise ValueError("MaterialConfig.params: fracture_softening needs fracture_strain")
        object.__setattr__(self, "params", dict(sorted(extra.items())))

    @property
    def plastic(self) -> bool:
        return self.yield_stress is not None

    def get(self, name: str) -> Optional[float]:
        """Value of any effect parameter (``yield_stress``, ``viscosity`` or an entry of ``params``); None or
        the effect's ``off`` value when the effect is absent."""
        from .effects import PARAMETERS

        if name == "yield_stress":
            return self.yield_stress
        if name == "viscosity":
            return self.viscosity
        if name not in PARAMETERS:
            raise ValueError(f"unknown effect parameter {name!r}; known: {', '.join(PARAMETERS)}")
        return self.params.get(name, PARAMETERS[name].off)

    def kernel_value(self, name: str) -> float:
        """What the simulator's per-world array holds for parameter ``name`` (its ``kernel_off`` when absent)."""
        from .effects import PARAMETERS

        v = self.get(name)
        p = PARAMETERS[name]
        if v is None or (p.off is not None and v == p.off):
            if name == "fracture_softening" and self.params.get("fracture_strain") is not None:
                return p.start
            return p.kernel_off
        return float(v)

    def effects(self) -> Tuple[str, ...]:
        """Names of the effects this material simulates (table friction only when given in ``params``)."""
        from .effects import EFFECTS

        on = []
        for e in EFFECTS.values():
            for p in e.params:
                v = self.get(p.name)
                if v is not None and (p.off is None or v != p.off):
                    on.append(e.name)
                    break
        return tuple(on)

    def added_effects(self) -> Tuple[str, ...]:
        """:meth:`effects` less a table friction equal to the base model's assumed one
        (:data:`~empm_gym.sim.effects.BASE_TABLE_FRICTION`): the effects this material adds to the base model."""
        from .effects import BASE_TABLE_FRICTION

        return tuple(e for e in self.effects() if e != "table_friction" or self.get("friction") != BASE_TABLE_FRICTION)

    def replace(self, **values) -> "MaterialConfig":
        """A copy with base fields (E, nu, density) or effect parameters set; ``None`` removes an effect
        parameter."""
        kw = dict(E=self.E, nu=self.nu, density=self.density, yield_stress=self.yield_stress,
                  viscosity=self.viscosity)
        params = dict(self.params)
        for k, v in values.items():
            if k in kw:
                kw[k] = (0.0 if v is None else v) if k == "viscosity" else v
            else:
                params[k] = v
        return MaterialConfig(**kw, params={k: v for k, v in params.items() if v is not None})

    def to_dict(self) -> Dict[str, Optional[float]]:
        """Flat dict: E, nu, density, yield_stress, viscosity and every set effect parameter (SI)."""
        return {"E": self.E, "nu": self.nu, "density": self.density, "yield_stress": self.yield_stress,
                "viscosity": self.viscosity, **self.params}

    @property
    def lame(self) -> Tuple[float, float]:
        """(mu, lambda) [Pa]."""
        mu = self.E / (2.0 * (1.0 + self.nu))
        lam = self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))
        return mu, lam

    @property
    def wave_speed(self) -> float:
        """P-wave speed sqrt((lambda + 2 mu) / rho) [m/s]."""
        mu, lam = self.lame
        return math.sqrt((lam + 2.0 * mu) / self.density)

    @property
    def max_wave_speed(self) -> float:
        """Largest P-wave speed in the body [m/s]: the heterogeneous-stiffness field multiplies E by at most
        exp(sum_i |a_i|) (|u_i| <= 1), the speed by the square root of that."""
        return self.wave_speed * math.exp(0.5 * sum(abs(self.get(f"stiffness_slope_{i}")) for i in (1, 2, 3)))

    @classmethod
    def from_dict(cls, d: Mapping) -> "MaterialConfig":
        """Build from a flat dict of base fields and effect parameters (other keys are ignored; the
        material file is read strictly by :mod:`empm_gym.sim.material_file`)."""
        from .effects import PARAMETERS

        known = {f.name for f in fields(cls)} - {"params"}
        kw = {k: v for k, v in d.items() if k in known}
        extra = {k: v for k, v in d.items() if k in PARAMETERS and k not in known and v is not None}
        extra.update(d.get("params") or {})
        return cls(**kw, params=extra)


@dataclass(frozen=True)
class GridConfig:
    """The Eulerian background grid shared by all worlds (each world has its own copy)."""

    lower: Tuple[float, float, float] = (-0.5, -0.5, -0.05)
    """Lower corner of the grid [m]."""
    upper: Tuple[float, float, float] = (0.5, 0.5, 0.95)
    """Upper corner of the grid [m]; rounded up to whole cells."""
    dx: float = 0.02
    """Cell size [m]; > 0."""
    boundary_cells: int = 3
    """Number of node layers at each wall where outward velocity is removed [-]; >= 2."""

    def __post_init__(self):
        dx = _finite("GridConfig.dx", self.dx)
        if dx <= 0:
            raise ValueError(f"GridConfig.dx must be > 0 m, got {self.dx!r}")
        lo = tuple(_finite(f"GridConfig.lower[{i}]", v) for i, v in enumerate(self.lower))
        hi = tuple(_finite(f"GridConfig.upper[{i}]", v) for i, v in enumerate(self.upper))
        if len(lo) != 3 or len(hi) != 3:
            raise ValueError("GridConfig.lower and upper must have 3 components")
        for i in range(3):
            if hi[i] - lo[i] < 6 * dx:
                raise ValueError(
                    f"GridConfig: upper[{i}] - lower[{i}] = {hi[i] - lo[i]:.4g} m is smaller than 6 cells of dx={dx} m"
                )
        if int(self.boundary_cells) < 2:
            raise ValueError(f"GridConfig.boundary_cells must be >= 2, got {self.boundary_cells!r}")
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "dx", dx)

    @property
    def resolution(self) -> Tuple[int, int, int]:
        """Number of grid nodes along x, y, z."""
        return tuple(int(math.ceil((self.upper[i] - self.lower[i]) / self.dx - 1e-6)) + 1 for i in range(3))

    def shifted(self, cells: Sequence[float]) -> "GridConfig":
        """This grid with its nodes moved down by ``cells`` (x, y, z: fractions of a cell, each in [0, 1)) and, along
        each axis so moved, one cell more at the top: every point keeps at least the room it had, and a box whose
        usable part starts at the table stays there. ``(0, 0, 0)`` is this grid. The same body and material on two
        such grids are two discretisations of one scene (``bench_doctor.py --grid-offsets``); moved along z, the
        table acts on another node layer (the highest not above it), up to a cell lower."""
        c = tuple(float(v) for v in cells)
        if len(c) != 3 or not all(math.isfinite(v) and 0.0 <= v < 1.0 for v in c):
            raise ValueError(f"GridConfig.shifted: cells must be 3 fractions of a cell, each in [0, 1), got {cells!r}")
        return replace(self, lower=tuple(a - v * self.dx for a, v in zip(self.lower, c)),
                       upper=tuple(a - v * self.dx + (self.dx if v > 0 else 0.0) for a, v in zip(self.upper, c)))


@dataclass(frozen=True)
class TableConfig:
    """A horizontal table plane z = height with Coulomb friction."""

    height: float = 0.0
    """Height of the table plane [m]."""
    friction: float = 0.5
    """Coulomb friction coefficient between object and table [-]; >= 0."""

    def __post_init__(self):
        _finite("TableConfig.height", self.height)
        mu = _finite("TableConfig.friction", self.friction)
        if mu < 0:
            raise ValueError(f"TableConfig.friction must be >= 0, got {self.friction!r}")


@dataclass(frozen=True)
class EndEffectorConfig:
    """A kinematic end-effector (gripper finger, pusher, hand) of a fixed shape."""

    shape: str = "sphere"
    """One of "sphere", "capsule", "box"."""
    radius: float = 0.02
    """Radius [m] of a sphere or capsule."""
    half_height: float = 0.02
    """Half length [m] of a capsule's axis (local z)."""
    half_extents: Tuple[float, float, float] = (0.02, 0.02, 0.02)
    """Half sizes [m] of a box along its local axes."""
    friction: float = 0.8
    """Coulomb friction coefficient [-] between object and end-effector when not gripping; >= 0."""
    gripper: bool = False
    """Whether the end-effector is a gripper's jaws, which close on the object and open again. Open, a gripper
    acts only on the grid nodes within half a cell of its surface: what it held lies free inside once it
    opens, and is left behind when it moves on or up. A tool (False: a pusher, a plate, a hand that never
    lets go) pushes everything it covers out through its nearest face; an opened box gripper did the same to
    the material it had held, which then rode along on its bottom face (issue 9)."""

    def __post_init__(self):
        if self.shape not in SHAPE_IDS:
            raise ValueError(f"EndEffectorConfig.shape must be one of {sorted(SHAPE_IDS)}, got {self.shape!r}")
        for name in ("radius", "half_height", "friction"):
            v = _finite(f"EndEffectorConfig.{name}", getattr(self, name))
            if v < 0 or (name == "radius" and self.shape in ("sphere", "capsule") and v <= 0):
                raise ValueError(f"EndEffectorConfig.{name} must be > 0 (>= 0 for friction), got {v!r}")
        he = tuple(_finite(f"EndEffectorConfig.half_extents[{i}]", v) for i, v in enumerate(self.half_extents))
        if len(he) != 3 or (self.shape == "box" and min(he) <= 0):
            raise ValueError(f"EndEffectorConfig.half_extents must be 3 positive lengths, got {self.half_extents!r}")
        object.__setattr__(self, "half_extents", he)
        if self.gripper not in (True, False):
            raise ValueError(f"EndEffectorConfig.gripper must be True or False, got {self.gripper!r}")
        object.__setattr__(self, "gripper", bool(self.gripper))

    @property
    def reach(self) -> float:
        """Farthest distance [m] from the centre to the surface: what a turn at omega rad/s moves at up to
        omega * reach m/s (a sphere turning about its centre moves its surface as fast as a box its corners)."""
        if self.shape == "sphere":
            return float(self.radius)
        if self.shape == "capsule":
            return float(self.half_height + self.radius)
        return math.sqrt(sum(h * h for h in self.half_extents))


def end_effector_speed(velocity, omega, configs) -> float:
    """Largest speed [m/s] of a point on an end-effector's surface, for the time step: over every leading index
    of ``velocity`` [..., K, 3] (m/s) and ``omega`` [..., K, 3] (rad/s), its centre's speed plus its turn's
    (angular speed times :attr:`EndEffectorConfig.reach`). ``configs``: the K end-effectors, or an array of
    their reaches (m) that broadcasts against ``velocity[..., 0]``. 0 without any command."""
    import numpy as np

    v, w = np.asarray(velocity, float), np.asarray(omega, float)
    if not v.size:
        return 0.0
    reach = configs if isinstance(configs, np.ndarray) else np.array([c.reach for c in configs], float)
    return float(np.max(np.linalg.norm(v, axis=-1) + np.linalg.norm(w, axis=-1) * reach))


@dataclass
class SolverConfig:
    """Options of :class:`empm_gym.sim.SolverMPM`."""

    cfl: float = 0.4
    """CFL number C of the stable step dt <= C * dx / (c + |v|max) [-]; in (0, 1]."""
    check_every: int = 1
    """Check the state for non-finite values every this many steps [-]; 0 disables the check."""
    max_speed: float = 50.0
    """Particle speed [m/s] above which the state counts as diverged."""
    plasticity_min_singular: float = 1e-3
    """Lower clamp of singular values of F in the plastic return mapping [-]."""
    deterministic: bool = False
    """Bit-identical runs on CUDA. Untaped steps sum P2G in 64-bit fixed point (integer atomics give the same
    total in any order; on the CPU as well, where runs are deterministic anyway, so that the path is tested
    there); taped steps, and CUDA with ``sort_every=0``, switch the MPM kernel module (for every solver in the
    process) to Warp's run-to-run deterministic atomics. Results differ from the default's in float32's last
    bits, as two default CUDA runs differ from each other."""
    sort_every: int = 16
    """On CUDA, re-sort P2G's particle order by grid cell every this many steps [-] (0: never sort, and
    scatter with one atomic per component as on the CPU). The order changes speed only, not results."""

    def __post_init__(self):
        if not (0 < self.cfl <= 1.0):
            raise ValueError(f"SolverConfig.cfl must lie in (0, 1], got {self.cfl!r}")
        if self.check_every < 0:
            raise ValueError(f"SolverConfig.check_every must be >= 0, got {self.check_every!r}")
        if self.sort_every < 0:
            raise ValueError(f"SolverConfig.sort_every must be >= 0, got {self.sort_every!r}")


def stable_dt(materials: Sequence[MaterialConfig], dx: float, cfl: float, max_speed: float = 0.0,
              stiffness_max: float = 1.0) -> float:
    """Largest stable explicit MPM substep [s] for every material given: C dx / (c + |v|max) with c the largest
    elastic wave speed (times sqrt of the largest per-particle stiffness multiplier), and, with viscosity,
    C dx^2 / (3 eta / rho) (explicit diffusion of momentum). The one formula of the package."""
    c = max(m.max_wave_speed for m in materials) * math.sqrt(max(stiffness_max, 1e-12))
    dt = cfl * dx / (c + max(0.0, float(max_speed)))
    nu_k = max(m.viscosity / m.density for m in materials)
    if nu_k > 0.0:
        dt = min(dt, cfl * dx ** 2 / (3.0 * nu_k))
    return dt


def as_vec3(name: str, value: Sequence[float]) -> Tuple[float, float, float]:
    vals = tuple(_finite(f"{name}[{i}]", v) for i, v in enumerate(value))
    if len(vals) != 3:
        raise ValueError(f"{name} must have 3 components, got {value!r}")
    return vals
