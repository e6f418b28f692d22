"""The material file: one place that reads and writes it (imports only the standard library).

Schema 2 (what :func:`write_material` writes)::

    {
      "schema": 2,
      "E": 30000.0, "nu": 0.3, "density": 1000.0,
      "effects": {
        "plasticity": {"yield_stress": 2000.0},
        "viscosity": {"viscosity": 12.0},
        "table_friction": {"friction": 0.4},
        "gripper_slip": {"grip_friction": 0.4},
        "heterogeneous_stiffness": {"stiffness_slope_1": 0.3},
        "fracture": {"fracture_strain": 0.3, "fracture_softening": 0.05}
      },
      "fit": {...}
    }

Base parameters in SI units (:data:`~empm_gym.sim.effects.BASE_PARAMETERS`), then the effects to
simulate, keyed by their name in :data:`~empm_gym.sim.effects.EFFECTS`, each with that effect's parameters
(a parameter left out takes its effect's ``off`` value; ``fracture_softening`` defaults to its start
value); an effect that is not listed is not simulated. ``fit`` is the identification report (free form).

A file of another model family says so in ``"model"`` (default ``"mpm"``): ``"model": "spring-mass"`` files
(:mod:`empm_gym.springmass`) hold ``density``, the table friction effect and a ``"spring_mass"`` object of
that model's settings (``stiffness`` [Pa], ``damping`` [Pa s], ...), and no E / nu. :func:`read_material`
refuses a model family its caller did not ask for (``models=``), so an MPM consumer never runs a spring-mass
fit as if it were a material.

Older files still load: schema 1 / flat objects with the keys E, nu, density and any effect parameter
(yield_stress, viscosity, friction, ...; ``null`` means absent), optionally nested in a ``"material"``
object, optionally with a ``fit`` section. Unknown keys, effects and parameters raise ``ValueError``
naming the key and the file; out-of-range values raise naming the parameter, the value and the range.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Union

from .config import MaterialConfig
from .effects import BASE_PARAMETERS, EFFECTS, PARAMETERS

__all__ = ["MaterialFile", "read_material", "write_material", "SCHEMA", "MODELS"]

#: Version written by :func:`write_material`.
SCHEMA = 2

_BASE = ("E", "nu", "density")
_TOP_V2 = ("schema", "model", "E", "nu", "density", "effects", "spring_mass", "fit")
#: Model families a material file can hold.
MODELS = ("mpm", "spring-mass")
_TOP_FLAT = ("schema", *_BASE, *PARAMETERS, "fit")


@dataclass(frozen=True)
class MaterialFile:
    """What a material file holds."""

    material: MaterialConfig
    """Base parameters and every effect to simulate (the table friction is ``material.get("friction")``)."""
    fit: Optional[dict] = None
    """The identification report, if any."""
    source: Optional[str] = None
    """The path it was read from (None for a mapping)."""
    schema: int = SCHEMA
    """Schema version of the source (1 for flat files)."""
    model: str = "mpm"
    """Model family: "mpm" or "spring-mass" (then ``material`` carries only the density and the effects)."""
    spring_mass: Optional[dict] = None
    """The spring-mass model's settings (``model == "spring-mass"``): numbers (or null) by name, checked by
    :class:`empm_gym.springmass.SpringMassConfig`."""

    @property
    def table_friction(self) -> Optional[float]:
        """Table Coulomb coefficient the file sets, or None."""
        return self.material.get("friction")


def _label(source) -> str:
    return str(source) if source is not None else "<material mapping>"


def read_material(source: Union[str, os.PathLike, Mapping], *, base: Optional[MaterialConfig] = None,
                  models: tuple = ("mpm",)) -> MaterialFile:
    """Read a material file (a JSON path) or an already parsed mapping.

    ``models``: the model families the caller simulates; a file of another family raises ValueError naming it.

    ``base`` fills what the source leaves out: E, nu, density (without ``base`` they are required), and for
    flat (schema 1) sources also the effect parameters they do not mention (a flat source *overrides*
    ``base``; a schema 2 source lists *all* its effects). Errors name the file and the key.
    """
    if isinstance(source, (str, os.PathLike)):
        path = str(source)
        where = path
        try:
            with open(path, "r", encoding="utf-8") as f:
                text = f.read()
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: material file does not exist") from None
        except IsADirectoryError:
            raise ValueError(f"{path}: is a directory, not a material file") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from None
    elif isinstance(source, Mapping):
        path, where, data = None, _label(None), source
    else:
        raise ValueError(f"material must be a JSON file path or a dict, got {type(source).__name__}")
    if not isinstance(data, Mapping):
        raise ValueError(f"{where}: a material file holds a JSON object, got {type(data).__name__}")
    data = dict(data)
    schema = data.get("schema", 1)
    if schema not in (1, 2) or isinstance(schema, bool):
        raise ValueError(f"{where}: unknown schema {schema!r} (this version reads schema 1 and 2)")
    model = data.pop("model", "mpm")
    if model not in MODELS:
        raise ValueError(f"{where}: unknown model {model!r}; known: {', '.join(MODELS)}")
    if model not in models:
        raise ValueError(f"{where}: holds a {model} model (\"model\": {model!r}), not one of {', '.join(models)}; "
                         f"use it where that model family is simulated (empm evaluate reads the family from the file)")
    sm = None
    if model == "spring-mass":
        sm = _read_spring_mass(data, where)
        data.pop("spring_mass")
        base = base or MaterialConfig()  # E and nu are no part of a spring-mass file
    elif "spring_mass" in data:
        raise ValueError(f"{where}: a 'spring_mass' section needs \"model\": \"spring-mass\"")
    if schema == 2:
        mat, fit = _read_v2(data, where, base)
    elif model != "mpm":
        raise ValueError(f"{where}: a {model} model needs schema 2")
    else:
        mat, fit = _read_flat(data, where, base)
    if fit is not None and not isinstance(fit, Mapping):
        raise ValueError(f"{where}: 'fit' must be a JSON object, got {type(fit).__name__}")
    return MaterialFile(material=mat, fit=None if fit is None else dict(fit), source=path, schema=int(schema),
                        model=model, spring_mass=sm)


def _read_spring_mass(data: Mapping, where: str) -> dict:
    import math

    sec = data.get("spring_mass")
    if not isinstance(sec, Mapping) or not sec:
        raise ValueError(f"{where}: a spring-mass file needs a 'spring_mass' object of its settings "
                         f"(stiffness [Pa], damping [Pa s], ...)")
    out = {}
    for k, v in sec.items():
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
            raise ValueError(f"{where}: spring_mass.{k} must be a finite number or null, got {v!r}")
        out[str(k)] = v
    return out


def _base_values(data: Mapping, where: str, base: Optional[MaterialConfig]) -> Dict[str, float]:
    out = {}
    for k in _BASE:
        if k in data and data[k] is not None:
            out[k] = BASE_PARAMETERS[k].check(data[k], f"{where}: ")
        elif base is not None:
            out[k] = getattr(base, k)
        else:
            raise ValueError(f"{where}: missing key {k!r} (a material file needs E, nu, density)")
    return out


def _make(where: str, kw: Dict[str, Any]) -> MaterialConfig:
    params = {k: v for k, v in kw.items() if k not in (*_BASE, "yield_stress", "viscosity")}
    try:
        return MaterialConfig(E=kw["E"], nu=kw["nu"], density=kw["density"], yield_stress=kw.get("yield_stress"),
                              viscosity=kw.get("viscosity") or 0.0, params=params)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _read_v2(data: Mapping, where: str, base: Optional[MaterialConfig]):
    for k in data:
        if k not in _TOP_V2:
            raise ValueError(f"{where}: unknown key {k!r}; a schema 2 material file has {', '.join(_TOP_V2)}")
    kw: Dict[str, Any] = _base_values(data, where, base)
    effects = data.get("effects") or {}
    if not isinstance(effects, Mapping):
        raise ValueError(f"{where}: 'effects' must be an object {{effect name: {{parameter: value}}}}")
    for name, values in effects.items():
        if name not in EFFECTS:
            raise ValueError(f"{where}: unknown effect {name!r}; known: {', '.join(EFFECTS)}")
        eff = EFFECTS[name]
        if not isinstance(values, Mapping):
            raise ValueError(f"{where}: effects.{name} must be an object of its parameters "
                             f"({', '.join(eff.param_names)})")
        for k, v in values.items():
            if k not in eff.param_names:
                raise ValueError(f"{where}: unknown key {k!r} in effect {name!r}; its parameters: "
                                 f"{', '.join(eff.param_names)}")
            if v is None:
                raise ValueError(f"{where}: effects.{name}.{k} is null; leave the effect out to switch it off")
            kw[k] = PARAMETERS[k].check(v, f"{where}: effects.{name}.")
        if not values:
            raise ValueError(f"{where}: effects.{name} gives none of its parameters ({', '.join(eff.param_names)})")
    return _make(where, kw), data.get("fit")


def _read_flat(data: Mapping, where: str, base: Optional[MaterialConfig]):
    fit = data.get("fit")
    if isinstance(data.get("material"), Mapping):
        for k in data:
            if k not in ("schema", "material", "fit"):
                raise ValueError(f"{where}: unknown key {k!r} beside 'material'; allowed: schema, material, fit")
        data = data["material"]
    for k in data:
        if k not in _TOP_FLAT:
            raise ValueError(f"{where}: unknown key {k!r}; a material file has "
                             f"{', '.join(k for k in _TOP_FLAT if k != 'fit')} (and 'fit')")
    kw: Dict[str, Any] = _base_values(data, where, base)
    if base is not None:
        kw.update(yield_stress=base.yield_stress, viscosity=base.viscosity, **base.params)
    for k in PARAMETERS:
        if k not in data:
            continue
        v = data[k]
        kw[k] = None if v is None else PARAMETERS[k].check(v, f"{where}: ")
    return _make(where, kw), fit


def material_dict(material: MaterialConfig, fit: Optional[Mapping] = None, *,
                  spring_mass: Optional[Mapping] = None) -> dict:
    """The schema 2 JSON object of ``material`` (and the ``fit`` report); with ``spring_mass`` (that model's
    settings) a ``"model": "spring-mass"`` file, which keeps the density and the effects but not E and nu."""
    if not isinstance(material, MaterialConfig):
        raise TypeError(f"material must be a MaterialConfig, got {type(material).__name__}")
    effects = {}
    for e in EFFECTS.values():
        vals = {}
        for p in e.params:
            if p.name == "yield_stress":
                v = material.yield_stress
            elif p.name == "viscosity":
                v = material.viscosity if material.viscosity != 0.0 else None
            else:
                v = material.params.get(p.name)
            if v is not None:
                vals[p.name] = float(v)
        if vals:
            effects[e.name] = vals
    out = {"schema": SCHEMA, "E": material.E, "nu": material.nu, "density": material.density, "effects": effects}
    if spring_mass is not None:
        out = {"schema": SCHEMA, "model": "spring-mass", "density": material.density, "effects": effects,
               "spring_mass": dict(spring_mass)}
    if fit is not None:
        out["fit"] = dict(fit)
    return out


def _json_default(o):
    if hasattr(o, "tolist"):  # numpy scalars and arrays
        return o.tolist()
    if isinstance(o, (tuple, set, frozenset)):
        return list(o)
    raise TypeError(f"material file: cannot write {type(o).__name__} {o!r} as JSON")


def write_material(path: Union[str, os.PathLike], material: MaterialConfig, fit: Optional[Mapping] = None, *,
                   spring_mass: Optional[Mapping] = None) -> Path:
    """Write ``material`` (and the ``fit`` report) as a schema 2 file; returns the path (``spring_mass``: see
    :func:`material_dict`).

    Atomic: the text goes to a temporary file in the same folder, which then replaces ``path``, so a
    failure (unserialisable ``fit``, full disk) leaves any previous file untouched.
    """
    p = Path(path)
    text = json.dumps(material_dict(material, fit, spring_mass=spring_mass), indent=2, default=_json_default) + "\n"
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=str(p.parent))
    try:
        os.chmod(tmp, (p.stat().st_mode & 0o777) if p.exists() else 0o644)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return p
