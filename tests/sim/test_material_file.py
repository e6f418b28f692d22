"""The material file (empm_gym.sim.material_file): schema 2 round trip of every effect, old flat files,
strict errors naming the key and the file, atomic writes."""

import json
import os

import pytest

from empm_gym.sim import MaterialConfig, read_material, write_material
from empm_gym.sim.effects import EFFECTS, PARAMETERS


def _with_effect(name: str) -> MaterialConfig:
    """A material simulating effect ``name`` with non-default values of all its parameters."""
    vals = {}
    for i, p in enumerate(EFFECTS[name].params):
        lo, hi = p.search
        vals[p.name] = lo + (hi - lo) * (0.3 + 0.2 * i) if p.transform == "linear" else (lo * hi) ** 0.5
    return MaterialConfig(E=3.0e4, nu=0.3, density=1100.0).replace(**vals)


@pytest.mark.parametrize("effect", list(EFFECTS))
def test_round_trip_of_every_effect(tmp_path, effect):
    m = _with_effect(effect)
    assert effect in m.effects()
    p = write_material(tmp_path / "sub" / "material.json", m, fit={"method": "cmaes", "loss": 0.25})
    d = json.loads(p.read_text())
    assert d["schema"] == 2 and set(d) == {"schema", "E", "nu", "density", "effects", "fit"}
    assert list(d["effects"]) == [effect]
    assert set(d["effects"][effect]) == set(EFFECTS[effect].param_names)
    r = read_material(p)
    assert r.material == m and r.fit == {"method": "cmaes", "loss": 0.25} and r.source == str(p) and r.schema == 2


def test_round_trip_of_all_effects_together(tmp_path):
    m = MaterialConfig(E=3.0e4, nu=0.25, density=900.0, yield_stress=2000.0, viscosity=12.0,
                       params=dict(friction=0.4, grip_friction=0.7, stiffness_slope_1=-0.3, stiffness_slope_2=0.0,
                                   stiffness_slope_3=0.1, fracture_strain=0.3, fracture_softening=0.02))
    p = write_material(tmp_path / "m.json", m)
    r = read_material(p)
    assert r.material == m and r.fit is None
    assert set(r.material.effects()) == set(EFFECTS)
    assert r.table_friction == 0.4
    # a mapping reads the same
    assert read_material(json.loads(p.read_text())).material == m


def test_fracture_softening_may_be_left_out(tmp_path):
    p = tmp_path / "m.json"
    p.write_text(json.dumps({"schema": 2, "E": 3e4, "nu": 0.3, "density": 1000.0,
                             "effects": {"fracture": {"fracture_strain": 0.2}}}))
    m = read_material(p).material
    assert m.get("fracture_strain") == 0.2 and m.kernel_value("fracture_softening") == PARAMETERS["fracture_softening"].start


def test_old_flat_files_load(tmp_path):
    p = tmp_path / "old.json"
    p.write_text(json.dumps({"E": 5e4, "nu": 0.3, "density": 1000.0, "yield_stress": None, "friction": 0.5,
                             "fit": {"method": "adam"}}))
    r = read_material(p)
    assert r.schema == 1 and r.fit == {"method": "adam"}
    assert r.material == MaterialConfig(E=5e4, nu=0.3, density=1000.0, params={"friction": 0.5})
    p.write_text(json.dumps({"schema": 1, "material": {"E": 5e4, "nu": 0.2, "density": 800.0, "yield_stress": 900.0,
                                                       "viscosity": 3.0}, "fit": {}}))
    m = read_material(p).material
    assert (m.nu, m.density, m.yield_stress, m.viscosity, m.get("friction")) == (0.2, 800.0, 900.0, 3.0, None)
    # a partial flat mapping overrides a base; null removes an effect
    base = MaterialConfig(E=1e4, yield_stress=500.0, params={"friction": 0.3})
    m = read_material({"E": 2e4, "yield_stress": None}, base=base).material
    assert (m.E, m.yield_stress, m.get("friction")) == (2e4, None, 0.3)


@pytest.mark.parametrize("data, match", [
    ({"schema": 2, "E": 3e4, "nu": 0.3, "density": 1e3, "effects": {}, "colour": "red"}, "unknown key 'colour'"),
    ({"schema": 2, "E": 3e4, "nu": 0.3, "density": 1e3, "effects": {"magnetism": {"B": 1.0}}}, "unknown effect 'magnetism'"),
    ({"schema": 2, "E": 3e4, "nu": 0.3, "density": 1e3, "effects": {"viscosity": {"yield_stress": 1.0}}},
     "unknown key 'yield_stress' in effect 'viscosity'"),
    ({"E": 3e4, "nu": 0.3, "density": 1e3, "viscousness": 2.0}, "unknown key 'viscousness'"),
    ({"schema": 2, "nu": 0.3, "density": 1e3}, "missing key 'E'"),
    ({"schema": 7, "E": 3e4, "nu": 0.3, "density": 1e3}, "unknown schema 7"),
])
def test_unknown_keys_raise_naming_key_and_file(tmp_path, data, match):
    p = tmp_path / "bad_material.json"
    p.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=match) as exc:
        read_material(p)
    assert str(p) in str(exc.value)


@pytest.mark.parametrize("data, match", [
    ({"E": -3, "nu": 0.3, "density": 1000}, r"E must lie in \[1e-06, 1e\+15\] Pa, got -3"),
    ({"schema": 2, "E": 3e4, "nu": 0.3, "density": 1e3, "effects": {"viscosity": {"viscosity": -1.0}}},
     r"effects.viscosity.viscosity must lie in \[0, 1e\+06\] Pa s, got -1.0"),
    ({"schema": 2, "E": 3e4, "nu": 0.3, "density": 1e3, "effects": {"gripper_slip": {"grip_friction": "lots"}}},
     "grip_friction must be a number"),
    ({"E": 3e4, "nu": 0.7, "density": 1000}, "nu must lie in"),
])
def test_bad_values_raise_naming_param_value_range(tmp_path, data, match):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=match) as exc:
        read_material(p)
    assert str(p) in str(exc.value)


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="none.json: material file does not exist"):
        read_material(tmp_path / "none.json")
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(ValueError, match="x.json: not valid JSON"):
        read_material(tmp_path / "x.json")
    (tmp_path / "l.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="l.json: a material file holds a JSON object"):
        read_material(tmp_path / "l.json")


def test_failed_write_leaves_the_old_file_intact(tmp_path, monkeypatch):
    p = write_material(tmp_path / "material.json", MaterialConfig(E=2e4))
    before = p.read_text()
    with pytest.raises(TypeError):
        write_material(p, MaterialConfig(E=9e4), fit={"bad": object()})
    assert p.read_text() == before

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_material(p, MaterialConfig(E=9e4), fit={"ok": 1})
    assert p.read_text() == before
    assert sorted(os.listdir(tmp_path)) == ["material.json"], "no temporary file is left behind"
