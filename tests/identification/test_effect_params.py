"""Every effect parameter is identifiable: the parameter space follows the registry, and Adam (through the
simulator) and CMA-ES recover viscosity and a stiffness slope on a tiny directly simulated scene.

The scene: a 12 x 6 x 4 cm block (288 particles at dx 2 cm) on the table, one closed spherical gripper at
one end pulling it up and out for 10 frames at 30 fps. Observations are the true particle positions (and
tracks), so only the optimiser is tested, not perception."""

import math

import numpy as np
import pytest

from empm_gym.identification.offline import _initial_values, default_bounds, identify, load_material
from empm_gym.identification.problem import PARAM_NAMES, Observations, ParamSpace, Scene, simulate_frames
from empm_gym.sim import EndEffectorConfig, MaterialConfig, TableConfig, read_material, sample_box
from empm_gym.sim.effects import BASE_PARAMETERS, PARAMETERS

FPS, T = 30.0, 10
BASE = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0)


def _scene(material: MaterialConfig) -> Scene:
    x, v = sample_box((-0.06, -0.03, 0.0), (0.06, 0.03, 0.04), 0.02, 8)
    p0, vel = np.array([0.05, 0.0, 0.02]), np.array([0.25, 0.0, 0.35])
    ee = np.stack([p0 + vel * t / FPS for t in range(T)])[:, None]
    return Scene(x, v, FPS, ee_configs=[EndEffectorConfig(shape="sphere", radius=0.025, friction=0.8)],
                 ee_positions=ee, ee_grip=np.ones((T, 1)), material=material, table=TableConfig(), dx=0.02,
                 device="cpu")


def _observe(truth: MaterialConfig) -> Observations:
    X = simulate_frames(_scene(truth), [truth])[:, 0]
    return Observations(FPS, list(X), tracks=X, visibility=np.ones(X.shape[:2], bool))


def test_param_names_cover_the_registry():
    assert set(PARAM_NAMES) == set(BASE_PARAMETERS) | set(PARAMETERS)


@pytest.mark.parametrize("name", [n for n in PARAMETERS])
def test_param_space_round_trip_and_start_values(name):
    p = PARAMETERS[name]
    sc = _scene(BASE if name != "fracture_softening" else BASE.replace(fracture_strain=0.3))
    init = _initial_values(sc, (name,), None)
    start = sc.table_friction if name == "friction" else p.start
    assert init == {name: pytest.approx(start)}
    bounds = default_bounds(init)[name]
    assert bounds[0] <= init[name] <= bounds[1]
    if p.transform == "linear":
        assert bounds[0] < 0 < bounds[1]  # slopes may be negative
    space = ParamSpace((name,), {name: bounds})
    for v in (bounds[0], init[name], bounds[1]):
        assert space.from_z(space.to_z({name: v}))[name] == pytest.approx(v, rel=1e-9, abs=1e-12)
    mat, mu = space.material({name: bounds[1]}, sc.material, 0.5)
    if name == "friction":
        assert mu == pytest.approx(bounds[1]) and mat.get("friction") == pytest.approx(bounds[1])
    else:
        assert mat.get(name) == pytest.approx(bounds[1]) and mu == 0.5
        assert mat.E == BASE.E


def test_linear_bounds_are_checked():
    with pytest.raises(ValueError, match="stiffness_slope_2"):
        ParamSpace(("stiffness_slope_2",), {"stiffness_slope_2": (-9.0, 1.0)})
    space = ParamSpace(("stiffness_slope_2",), {"stiffness_slope_2": (-1.0, 1.0)})
    assert list(space.z_lo) == [-1.0]


def test_fit_result_of_effects_round_trips_through_the_material_file(tmp_path):
    truth = BASE.replace(viscosity=20.0)
    obs = _observe(truth)
    r = identify(obs, _scene(BASE), params=("viscosity", "grip_friction"), method="cmaes",
                 init={"viscosity": 10.0, "grip_friction": 5.0}, iters=1, popsize=2, progress=False,
                 observation="particles")
    p = r.save(tmp_path / "material.json")
    mf = read_material(p)
    assert mf.material.viscosity == pytest.approx(r.params["viscosity"])
    assert mf.material.get("grip_friction") == pytest.approx(r.params["grip_friction"])
    assert mf.table_friction == pytest.approx(0.5) and mf.fit["params"] == ["viscosity", "grip_friction"]
    assert load_material(p) == (mf.material, mf.table_friction)


@pytest.mark.slow
@pytest.mark.parametrize("method, iters, tol", [("adam", 8, 0.05), ("cmaes", 10, 0.20)])
def test_recover_viscosity(method, iters, tol):
    obs = _observe(BASE.replace(viscosity=20.0))
    r = identify(obs, _scene(BASE), params=("viscosity",), method=method, init={"viscosity": 6.0}, iters=iters,
                 popsize=4, lr=0.3, progress=False, observation="particles")
    assert abs(math.log(r.params["viscosity"] / 20.0)) < math.log(1 + tol), r.params
    assert r.material.viscosity == pytest.approx(r.params["viscosity"])
    assert r.loss < 0.2 * r.loss_history[0]


@pytest.mark.slow
@pytest.mark.parametrize("method, iters, tol", [("adam", 8, 0.05), ("cmaes", 10, 0.12)])
def test_recover_stiffness_slope(method, iters, tol):
    obs = _observe(BASE.replace(stiffness_slope_1=0.6))
    r = identify(obs, _scene(BASE), params=("stiffness_slope_1",), method=method, init={"stiffness_slope_1": 0.2},
                 iters=iters, popsize=4, lr=0.3, progress=False, observation="particles")
    assert abs(r.params["stiffness_slope_1"] - 0.6) < tol, r.params
    assert r.material.get("stiffness_slope_1") == pytest.approx(r.params["stiffness_slope_1"])
    assert r.loss < 0.5 * r.loss_history[0]


def test_cmaes_extra_starts_are_members_of_the_first_generation():
    """A start given in ``extra_starts`` is simulated as it is in generation 0: with the truth among them and a
    search too narrow to find it from ``init``, one generation returns the truth and its (zero) loss."""
    obs = _observe(BASE.replace(viscosity=20.0))
    kw = dict(params=("viscosity",), method="cmaes", init={"viscosity": 1.0}, bounds={"viscosity": (0.5, 100.0)}, iters=1, popsize=3, sigma0=0.01,
              progress=False, observation="particles")
    alone = identify(obs, _scene(BASE), **kw)
    r = identify(obs, _scene(BASE), extra_starts=[{"viscosity": 20.0}], **kw)
    assert alone.params["viscosity"] < 1.1 and alone.loss > 1e-5
    assert r.params["viscosity"] == pytest.approx(20.0, rel=1e-9) and r.loss < 1e-3 * alone.loss
    with pytest.raises(ValueError, match="CMA-ES starting points"):
        identify(obs, _scene(BASE), extra_starts=[{"viscosity": 20.0}], **{**kw, "method": "adam"})
    with pytest.raises(ValueError, match="leave no sampled member"):
        identify(obs, _scene(BASE), extra_starts=[{"viscosity": 20.0}] * 3, **kw)
