"""The catalogue of physical effects beyond the base model, one registry for the whole package.

The base model is a fixed-corotated elastic body (E [Pa], nu [-], density [kg/m^3]) on a Coulomb table
of friction 0.5, held by rigid closed grippers. An *effect* is a mechanism that model may be missing.
Each entry of :data:`EFFECTS` declares its name, its parameters (SI units, the range a value must lie
in, the box identification searches, the value it starts from, how an optimiser sees it), what it
changes in the simulator and the signature it leaves in a recording. Identification, the synthesiser,
the environments, the material file and the discrepancy doctor all go through this registry, so adding
an effect means one entry here plus its kernel code (and the per-world array that carries it, see
``Parameter.array``).

Where each parameter lives at run time: every parameter is a per-world value on the
:class:`~empm_gym.sim.Model` (``Parameter.array`` names the array, ``Parameter.component`` the vector
component); the kernels read it there (or a per-particle copy of it). In a
:class:`~empm_gym.sim.MaterialConfig`, ``yield_stress`` and ``viscosity`` are fields and every other
parameter is an entry of ``MaterialConfig.params``; a parameter that is absent takes its ``off`` value
(the effect is not simulated).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

__all__ = ["Parameter", "Effect", "EFFECTS", "PARAMETERS", "BASE_PARAMETERS", "effect_of", "parameter",
           "BASE_TABLE_FRICTION", "describe"]

#: Table friction of the base model [-] (the table_friction effect fits it instead).
BASE_TABLE_FRICTION = 0.5


@dataclass(frozen=True)
class Parameter:
    """One identifiable parameter."""

    name: str
    """Key on the command line and in the material file."""
    unit: str
    """SI unit ("Pa", "Pa s", "-")."""
    doc: str
    """What it means, one sentence."""
    valid: Tuple[float, float]
    """Closed range a value must lie in (validation) [unit]."""
    search: Tuple[float, float]
    """Default search box of identification [unit]."""
    start: float
    """Default starting value of a fit [unit]."""
    transform: str = "log"
    """How optimisers see it: "log" (z = log(value / scale)) or "linear" (z = value / scale)."""
    scale: float = 1.0
    """Reference scale of the optimiser coordinate [unit]."""
    off: Optional[float] = None
    """Value meaning "effect absent" (None: absent when not given)."""
    array: str = ""
    """Per-world Model array that carries the value to the kernels."""
    component: Optional[int] = None
    """Component of a vector-valued ``array`` (None: scalar array)."""
    kernel_off: float = 0.0
    """Value written to ``array`` when the effect is absent."""
    plausible: Optional[Tuple[float, float]] = None
    """Range real objects and contacts usually show [unit] (None: no such range is set). A value outside it is
    valid but suspect: the discrepancy doctor doubts an effect fitted there, which may stand in for another
    that the catalogue lacks."""

    def check(self, value, where: str = "") -> float:
        """The value as a float, or ``ValueError`` naming the parameter, the value and the allowed range."""
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{where}{self.name} must be a number [{self.unit}], got {value!r}") from None
        lo, hi = self.valid
        if not math.isfinite(v) or not (lo <= v <= hi):
            raise ValueError(f"{where}{self.name} must lie in [{lo:g}, {hi:g}] {self.unit}, got {value!r}")
        return v

    def to_z(self, value: float) -> float:
        if self.transform == "log":
            return math.log(value / self.scale)
        return value / self.scale


@dataclass(frozen=True)
class Effect:
    """A physical mechanism the base model may lack."""

    name: str
    summary: str
    """How it changes the model."""
    signature: str
    """The trace it leaves in a recording, one line."""
    params: Tuple[Parameter, ...]

    @property
    def param_names(self) -> Tuple[str, ...]:
        return tuple(p.name for p in self.params)


EFFECTS: Dict[str, Effect] = {}


def _register(effect: Effect) -> Effect:
    if effect.name in EFFECTS:
        raise ValueError(f"effect {effect.name!r} registered twice")
    EFFECTS[effect.name] = effect
    return effect


_register(Effect(
    name="plasticity",
    summary="von Mises return mapping of the elastic deformation gradient (Hencky strain, volume preserving)",
    signature="keeps a permanent set after release: the shape does not return to where it started",
    params=(Parameter("yield_stress", "Pa", "uniaxial von Mises yield stress", valid=(0.0, 1e9),
                      search=(50.0, 1e6), start=2.0e3, scale=1.0e3, array="world_yield"),),
))
_register(Effect(
    name="viscosity",
    summary="Kelvin-Voigt viscous stress J eta (grad v + grad v^T) added to the elastic stress",
    signature="motion decays: oscillations die out faster and the body lags behind its elastic shape",
    params=(Parameter("viscosity", "Pa s", "Newtonian (Kelvin-Voigt) viscosity eta", valid=(0.0, 1e6),
                      search=(0.5, 500.0), start=10.0, scale=10.0, off=0.0, array="world_viscosity"),),
))
_register(Effect(
    name="table_friction",
    summary=f"the table's Coulomb coefficient is fitted instead of the base model's {BASE_TABLE_FRICTION}",
    signature="the object slides on the table further (or less far) than the base friction allows",
    params=(Parameter("friction", "-", "Coulomb friction coefficient between object and table",
                      valid=(0.0, 100.0), search=(0.01, 3.0), start=BASE_TABLE_FRICTION, scale=1.0,
                      off=None, array="world_table_friction", kernel_off=BASE_TABLE_FRICTION,
                      # dry contacts of rubber, dough, cloth or rope on a table lie well under 1.5; a fit beyond
                      # it stands in for what Coulomb friction is not (adhesion, a grasp that gives, a body that
                      # rolls where the model slides; benchmarks/RESULTS.md, session 49)
                      plausible=(0.0, 1.5)),),
))
#: The grip friction's search box reaches the rigid grip: at 1e4 a closed gripper may remove about 10 m/s of
#: relative velocity per 0.1 ms substep, more than a body as stiff as 500 kPa builds up, so a fit (and the doctor's
#: slip candidate) can hold the base model's rigid grip. A box ending at 30 did not: a gripper pulling such a body
#: apart slipped by about 1 cm in ``test_each_candidate_at_its_absent_start_moves_as_the_base_model``.
_register(Effect(
    name="gripper_slip",
    summary="a closed gripper holds the material it covers by friction (velocity change per substep at most "
            "grip_friction * g * dt, the squeeze pressing with the grasped weight) instead of imposing "
            "its velocity; very large values are the rigid grip",
    signature="the object moves relative to a closed gripper: it sags or slides out when lifted or pulled",
    params=(Parameter("grip_friction", "-", "Coulomb coefficient of a closed gripper, the normal load being "
                      "the grasped material's weight (held while grip_friction * grasped mass >= carried mass)",
                      valid=(0.0, 1e30), search=(0.1, 1.0e4), start=2.0, scale=1.0, off=None,
                      array="world_grip_friction", kernel_off=1.0e30,
                      # gripper pads on dough, rope or cloth hold with a Coulomb coefficient of a few at most. Of
                      # the stored diagnoses named gripper slip (benchmarks/RESULTS.md, session 54), the 196 right
                      # ones fitted 0.1 to 11.2 (true 1.0), while 20 of the 63 wrong ones fitted 20.6 to 734: doughs
                      # torn at the clamps, spring-mass bodies whose grasp gives. So far above, the grip holds and
                      # what gains is the grip model's give standing in for a tear or a grasp that yields
                      plausible=(0.0, 15.0)),),
))
_register(Effect(
    name="heterogeneous_stiffness",
    summary="E varies smoothly over the body: E(x) = E exp(sum_i a_i u_i) with u_i in [-1, 1] the rest "
            "position along principal axis i of the body (1 = longest; axes of similar extent, within 15 %, "
            "follow the world axes x, y, z, and a lump whose extents all lie within 30 % takes the world axes)",
    signature="uneven deformation: one side of the body stretches or compresses more than the other",
    params=tuple(
        Parameter(f"stiffness_slope_{i + 1}", "-", f"natural-log change of the stiffness from the body's centre "
                  f"to its end along principal axis {i + 1}", valid=(-4.0, 4.0), search=(-1.5, 1.5), start=0.0,
                  transform="linear", scale=1.0, off=0.0, array="world_stiffness_slope", component=i)
        for i in range(3)),
))
_register(Effect(
    name="fracture",
    summary="a per-particle damage d in [0, 1] grows smoothly from 0 to 1 as the largest principal stretch "
            "of the elastic F exceeds 1 + fracture_strain by up to fracture_softening, and scales the "
            "deviatoric and tensile stress by (1 - d), so the body tears into pieces; a fully broken particle "
            "keeps only its volume (F = J^(1/3) I with J <= 1), the stretch it no longer resists being forgotten",
    signature="separation into pieces: points that moved together drift apart where the body was pulled",
    params=(Parameter("fracture_strain", "-", "principal strain at which damage starts", valid=(1e-4, 1e30),
                      search=(0.02, 1.5), start=0.3, scale=0.1, off=None, array="world_fracture_strain",
                      kernel_off=1.0e30),
            Parameter("fracture_softening", "-", "strain over which damage grows from 0 to 1", valid=(1e-4, 10.0),
                      search=(0.005, 0.5), start=0.05, scale=0.01, off=None, array="world_fracture_softening",
                      kernel_off=0.05)),
))

#: Every effect parameter by name.
PARAMETERS: Dict[str, Parameter] = {p.name: p for e in EFFECTS.values() for p in e.params}

#: The base model's parameters (not effects): Young's modulus, Poisson's ratio, density.
BASE_PARAMETERS: Dict[str, Parameter] = {
    "E": Parameter("E", "Pa", "Young's modulus", valid=(1e-6, 1e15), search=(1e3, 1e7), start=1e5, scale=1e6),
    "nu": Parameter("nu", "-", "Poisson's ratio", valid=(-0.999, 0.499), search=(-0.9, 0.49), start=0.3,
                    transform="sigmoid"),
    "density": Parameter("density", "kg/m^3", "mass density", valid=(1e-6, 1e6), search=(100.0, 2e4),
                         start=1000.0, scale=1e3),
}


def effect_of(param: str) -> str:
    """Name of the effect that owns parameter ``param``."""
    for e in EFFECTS.values():
        if param in e.param_names:
            return e.name
    raise KeyError(f"{param!r} is not an effect parameter; known: {', '.join(PARAMETERS)}")


def parameter(name: str) -> Parameter:
    """A base or effect parameter by name, or ``ValueError`` listing the known ones."""
    if name in BASE_PARAMETERS:
        return BASE_PARAMETERS[name]
    if name in PARAMETERS:
        return PARAMETERS[name]
    raise ValueError(f"unknown parameter {name!r}; known: {', '.join([*BASE_PARAMETERS, *PARAMETERS])}")


def describe() -> str:
    """A human-readable table of the catalogue (``empm effects``)."""
    lines = []
    for e in EFFECTS.values():
        lines.append(f"{e.name}: {e.summary}")
        lines.append(f"    signature: {e.signature}")
        for p in e.params:
            lines.append(f"    {p.name} [{p.unit}]: {p.doc}; search {p.search[0]:g}-{p.search[1]:g}, "
                         f"start {p.start:g}")
    return "\n".join(lines)
