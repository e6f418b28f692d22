"""The doctor benchmark's scoring (benchmarks/bench_doctor.py), on constructed result rows: no simulation."""

import json
import warnings

import pytest

from tests import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_doctor")


def _row(name, truth, verdict, script, base_loss):
    return {"recording": name, "script": script, "truth": truth, "verdict": verdict, "confidence": 1.0,
            "reduction": 0.3, "base_chamfer_m": 0.004, "true_effect_chamfer_m": 0.003, "base_loss": base_loss,
            "before_variants": verdict, "signature_m": 0.01, "wall_s": 60.0}


def _summarise(bench, tmp_path, capsys, rows) -> str:
    """What ``bench_doctor.py --summarise`` prints for the result rows ``rows``."""
    (tmp_path / "rows.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert bench.main(["--summarise", str(tmp_path / "rows.jsonl")]) == 0
    return capsys.readouterr().out


def test_accuracy_over_the_recordings_whose_true_material_beats_the_base_fit(bench, tmp_path, capsys):
    """An effect recording counts as shown on the doctor's body when the true material's held-out loss is below
    the base model's fit by more than the doctor's penalty (4 % for one parameter): a viscosity whose true material
    scores 2 % below the base fit does not show; a fracture 40 % below does; `none` always counts."""
    rows = [_row("dough-squeeze-ring-0-viscosity", "viscosity", "none", "squeeze-ring", 0.0050),
            _row("dough-pull-apart-0-fracture", "fracture", "gripper_slip", "pull-apart", 0.0100),
            _row("dough-lift-end-0-fracture", "fracture", "fracture", "lift-end", 0.0100),
            _row("dough-drag-0-none", "none", "none", "drag", 0.0040)]
    floors = [{"recording": "dough-squeeze-ring-0-viscosity", "truth": "viscosity", "floor_chamfer_m": 0.004,
               "floor_loss": 0.0049},
              {"recording": "dough-pull-apart-0-fracture", "truth": "fracture", "floor_chamfer_m": 0.003,
               "floor_loss": 0.0060},
              {"recording": "dough-lift-end-0-fracture", "truth": "fracture", "floor_chamfer_m": 0.003,
               "floor_loss": 0.0058}]
    (tmp_path / "rows.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (tmp_path / "floors.jsonl").write_text("".join(json.dumps(r) + "\n" for r in floors))
    assert bench.main(["--summarise", str(tmp_path / "rows.jsonl"), "--floors", str(tmp_path / "floors.jsonl")]) == 0
    out = capsys.readouterr().out
    assert "2 of 3 effect recordings show their effect beyond the penalty" in out
    assert "accuracy 66.7 % of 3" in out  # the two fractures (one called gripper slip) and the none recording
    assert "does not show it: dough-squeeze-ring-0-viscosity" in out and "+2.0 %" in out


def test_the_signature_checks_doubts_are_tallied_right_and_wrong(bench, tmp_path, capsys):
    """Rows carry ``signature_doubted`` from doctor.json (``evidence.signature_check``) or from a slim dump line;
    the table counts the doubted verdicts and how many of them were right, and the wrong verdicts it let pass.
    Rows without the check (older runs, or `none`) are left out of that count."""
    res = {"effect": "gripper_slip", "confidence": 0.5, "evidence": {"signature_check": {"doubted": True}}}
    assert bench._row(res, "fracture", "r", "lift-end", None, 1.0)["signature_doubted"] is True
    assert bench._row({"effect": "plasticity", "signature_check": {"doubted": False}}, "plasticity", "r",
                      "press-release", None, 1.0)["signature_doubted"] is False
    assert bench._row({"effect": "none"}, "none", "r", "drag", None, 1.0)["signature_doubted"] is None
    rows = [dict(_row("dough-lift-end-2-fracture", "fracture", "gripper_slip", "lift-end", 0.01), signature_doubted=True),
            dict(_row("dough-lift-end-1-fracture", "fracture", "gripper_slip", "lift-end", 0.01), signature_doubted=False),
            dict(_row("dough-press-release-0-plasticity", "plasticity", "plasticity", "press-release", 0.01),
                 signature_doubted=False),
            _row("dough-drag-0-none", "none", "none", "drag", 0.004)]
    out = _summarise(bench, tmp_path, capsys, rows)
    assert "checked against their signature: 3 named verdicts" in out
    assert "doubted (the named effect's fit does not bring its trusted feature closer): 1, of them right 0" in out
    assert "not doubted and wrong: 1" in out


def test_rescore_applies_the_signature_veto_to_dumps_that_hold_the_check_for_their_verdict_alone(bench, tmp_path):
    """A dump written before the doctor checked every candidate's signature (session 44) holds the check of its
    verdict alone: rescored, a verdict its own trusted signature contradicted beyond the depth noise goes to the
    next candidate; one whose discrepancy lay under the noise (older dumps lack ``unsupported``: it is taken from
    the discrepancy and ``noise_sigma_m``) stays."""
    def test(gain):
        return {"gain": gain, "lower": gain - 0.01, "upper": gain + 0.01, "threshold": 0.04, "significant": True}

    def res(name, d0, d1, **extra):
        sc = {"feature": "track_slip_m", "unit": "m", "discrepancy_base": d0, "discrepancy_with_effect": d1,
              "explained": d1 < d0, "trusted": True, **extra}
        return {"recording": name, "script": "pull-apart", "truth": "fracture", "effect": "gripper_slip",
                "confidence": 0.4, "wall_s": 1.0, "noise_sigma_m": 1.4e-3, "signature_check": sc,
                "base": {"heldout": {"chamfer_m": 2e-3, "loss": 5e-3}, "params": {"E": 1e4}},
                "candidates": [{"effect": "gripper_slip", "heldout": {"chamfer_m": 1.7e-3, "loss": 4.1e-3},
                                "gain": test(0.18)},
                               {"effect": "fracture", "heldout": {"chamfer_m": 1.8e-3, "loss": 4.2e-3},
                                "gain": test(0.16)}]}

    rows = [res("torn", 5.81e-3, 6.99e-3, unsupported=False), res("torn-old", 3.96e-3, 5.89e-3),
            res("quiet-old", 1.2e-4, 2.2e-4), res("explained", 5.8e-3, 1.0e-3, unsupported=False)]
    (tmp_path / "dump.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    got = {r["recording"]: r["verdict"] for r in bench.rescore([tmp_path / "dump.jsonl"])}
    assert got == {"torn": "fracture", "torn-old": "fracture", "quiet-old": "gripper_slip", "explained": "gripper_slip"}


def test_rescore_sets_aside_old_dumps_fits_that_end_where_their_effect_vanishes(bench, tmp_path):
    """Dumps older than session 53 lack ``toward_absence``: rescored, it is taken from the fitted values and the
    registry's boxes, so a fracture named at a strain at the top of its box (dough lifted by one end without any
    effect) goes to ``none``; the same fit at a strain inside the box stays named."""
    def res(name, strain):
        return {"recording": name, "script": "lift-end", "truth": "none", "effect": "fracture", "confidence": 0.6,
                "wall_s": 1.0, "base": {"heldout": {"chamfer_m": 2e-3, "loss": 5e-3}, "params": {"E": 2.3e4}},
                "candidates": [{"effect": "fracture", "params": {"E": 2.7e4, "fracture_strain": strain},
                                "heldout": {"chamfer_m": 1.9e-3, "loss": 4.7e-3},
                                "gain": {"gain": 0.061, "lower": 0.044, "upper": 0.102, "threshold": 0.04,
                                         "significant": True}}]}

    (tmp_path / "dump.jsonl").write_text(json.dumps(res("at-top", 1.5)) + "\n" + json.dumps(res("inside", 1.3)) + "\n")
    got = {r["recording"]: r["verdict"] for r in bench.rescore([tmp_path / "dump.jsonl"])}
    assert got == {"at-top": "none", "inside": "fracture"}

    # and the variants' refits: a fracture that holds on two shifted grids, one of them at the top of the box, does
    # not hold there (with fewer than five variants it must hold on all)
    def varied(name, strains):
        r = res(name, 1.3)
        r["variants"] = {"variants": ["grid 1", "grid 2"], "base": [], "base_E": 2.3e4, "candidates": {"fracture": {
            "tests": [{"variant": f"grid shifted and particles resampled ({i + 1})", "kind": "discretisation",
                       "params": {"E": 2.7e4, "fracture_strain": s}, "gain": 0.06, "threshold": 0.04}
                      for i, s in enumerate(strains)]}}}
        return r

    (tmp_path / "dump.jsonl").write_text(json.dumps(varied("grid-at-top", [1.3, 1.5])) + "\n"
                                         + json.dumps(varied("grids-inside", [1.3, 1.2])) + "\n")
    got = {r["recording"]: r["verdict"] for r in bench.rescore([tmp_path / "dump.jsonl"])}
    assert got == {"grid-at-top": "none", "grids-inside": "fracture"}


def test_rescore_applies_the_trimmed_bodys_check_and_keeps_the_verdict_without_it(bench, tmp_path, capsys):
    """A dump whose candidate holds on every variant but not on the body trimmed to the measured surface scores
    `none` (the doctor's rule), its row's ``before_trim`` the verdict without that check; the summary tallies both."""
    def res(name, trimmed_gain):
        tests = [{"variant": f"grid shifted and particles resampled ({i + 1})", "kind": "discretisation",
                  "params": {"E": 1.0e4, "viscosity": 2.0}, "gain": 0.1, "threshold": 0.04, "toward_absence": []}
                 for i in range(2)]
        trimmed = {"variant": "body trimmed to the measured surface", "kind": "trimmed", "toward_absence": [],
                   "params": {"E": 1.0e4, "viscosity": 2.0}, "gain": trimmed_gain, "threshold": 0.04}
        return {"recording": name, "script": "push-slide", "truth": "none", "effect": "viscosity", "confidence": 0.3,
                "wall_s": 1.0, "base": {"heldout": {"chamfer_m": 2e-3, "loss": 5e-3}, "params": {"E": 1.0e4}},
                "candidates": [{"effect": "viscosity", "params": {"E": 1.0e4, "viscosity": 2.0}, "toward_absence": [],
                                "heldout": {"chamfer_m": 1.9e-3, "loss": 4.4e-3},
                                "gain": {"gain": 0.12, "lower": 0.1, "upper": 0.14, "threshold": 0.04,
                                         "significant": True}}],
                "variants": {"variants": [t["variant"] for t in tests] + [trimmed["variant"]], "base": [],
                             "base_E": 1.0e4, "candidates": {"viscosity": {"tests": tests, "trimmed": trimmed}}}}

    (tmp_path / "dump.jsonl").write_text(json.dumps(res("refused", -0.028)) + "\n" + json.dumps(res("holds", 0.05))
                                         + "\n")
    rows = {r["recording"]: r for r in bench.rescore([tmp_path / "dump.jsonl"])}
    assert (rows["refused"]["verdict"], rows["refused"]["before_trim"]) == ("none", "viscosity")
    assert (rows["holds"]["verdict"], rows["holds"]["before_trim"]) == ("viscosity", "viscosity")
    assert rows["refused"]["trim_checked"] and rows["holds"]["trim_checked"]
    # the run's confidence (0.3) was for its own verdict: the kept one keeps it, the changed one has none
    assert rows["holds"]["confidence"] == 0.3 and rows["refused"]["confidence"] is None
    out = _summarise(bench, tmp_path, capsys, list(rows.values()))
    assert ("checked on the body trimmed to the measured surface: 2 recordings; without that check: accuracy 0.0 % "
            "(with it 50.0 %), false effects on none 2 of 2; verdicts it changed: refused viscosity -> none") in out, out
    assert ("accuracy by the verdict's confidence: 0.0-0.5: 0 of 1 right; 0.5-0.9: 0 of 0 right; 0.9-1.0: 0 of 0 "
            "right; 1 rescored to another verdict than their run's, without a confidence") in out, out

def test_make_with_effect_params_synthesises_them_and_keeps_them_for_scoring(bench, tmp_path):
    """``--make --effect-params viscosity=80 --base-params E=3e4,density=900``: the recording is made with that
    viscosity on that base material (its ground truth says so), its problem's name ends with them, and the pickle
    keeps them (for ``--floor``'s true material)."""
    import pickle

    rc = bench.main(["--object", "block", "--make", str(tmp_path / "rec"), "--problems", str(tmp_path / "prob"),
                     "--effects", "viscosity", "--effect-params", "viscosity=80", "--base-params", "E=3e4,density=900",
                     "--scripts", "1", "--seeds", "1",
                     "--frames", "4", "--cameras", "2", "--width", "160", "--height", "120", "--only-make"])
    assert rc == 0
    (pkl,) = (tmp_path / "prob").glob("*.pkl")
    assert pkl.stem == "block-squeeze-ring-0-viscosity-E30000-density900-viscosity80"
    with open(pkl, "rb") as f:
        prob = pickle.load(f)
    assert prob["truth"] == "viscosity" and prob["truth_params"] == {"viscosity": 80.0}
    assert prob["base_params"] == {"E": 3.0e4, "density": 900.0} and prob["object"] == "block"
    gt = json.loads((tmp_path / "rec" / pkl.stem / "ground_truth.json").read_text())
    assert gt["effects"] == [{"name": "viscosity", "params": {"viscosity": 80.0}}]
    assert gt["material"]["E"] == 3.0e4 and gt["material"]["density"] == 900.0


def test_make_on_another_grid_than_the_doctors(bench, tmp_path):
    """``--synth-dx``: the recording is simulated on its own grid cell (its ground truth says so) while the
    problem holds the body on the doctor's (``--dx``): recordings of physics the doctor's grid does not share, as
    another simulator's would be (benchmarks/RESULTS.md, session 34). Without it both are the doctor's."""
    import pickle

    for synth_dx, expect in (("0.02", 0.02), (None, 0.01)):
        out = tmp_path / (synth_dx or "same")
        rc = bench.main(["--object", "block", "--make", str(out / "rec"), "--problems", str(out / "prob"),
                         "--effects", "none", "--only-scripts", "squeeze-ring", "--seeds", "1", "--dx", "0.01",
                         *(["--synth-dx", synth_dx] if synth_dx else []),
                         "--frames", "4", "--cameras", "2", "--width", "160", "--height", "120", "--only-make"])
        assert rc == 0
        (pkl,) = (out / "prob").glob("*.pkl")
        gt = json.loads((out / "rec" / pkl.stem / "ground_truth.json").read_text())
        assert gt["scene"]["grid"]["dx"] == expect
        with open(pkl, "rb") as f:
            prob = pickle.load(f)
        assert prob["scene"].dx == 0.01 and isinstance(prob["body_notes"], list)


def test_reload_rebuilds_kept_problems_from_their_recordings_and_keeps_their_signature(bench, tmp_path):
    """``--reload`` (with ``--make --keep-existing``): after a change to the loader, each kept problem's scene and
    observations are those a fresh load of its recording gives (here with ``--trim-bodies``), and what the make
    measured of the synthesiser (the signature) stays; without ``--keep-existing`` it is refused."""
    import dataclasses
    import pickle

    import numpy as np

    from empm_gym.identification.doctor import load_for_doctor

    args = ["--object", "block", "--make", str(tmp_path / "rec"), "--problems", str(tmp_path / "prob"),
            "--effects", "none", "--only-scripts", "squeeze-ring", "--seeds", "1", "--dx", "0.01",
            "--frames", "4", "--cameras", "2", "--width", "160", "--height", "120", "--only-make"]
    assert bench.main(args) == 0
    (pkl,) = (tmp_path / "prob").glob("*.pkl")
    with open(pkl, "rb") as f:
        prob = pickle.load(f)
    n_points = [len(p) for p in prob["obs"].points]
    prob["signature_m"] = 0.123                           # stands for what the make measured
    prob["scene"] = dataclasses.replace(prob["scene"], particles=prob["scene"].particles[:10],
                                        volumes=prob["scene"].volumes[:10])  # not what the loader builds
    with open(pkl, "wb") as f:
        pickle.dump(prob, f)
    with pytest.raises(SystemExit):
        bench.main(args + ["--reload"])
    assert bench.main(args + ["--keep-existing", "--reload", "--trim-bodies"]) == 0
    with open(pkl, "rb") as f:
        again = pickle.load(f)
    fresh, _, _, _, _ = load_for_doctor(tmp_path / "rec" / pkl.stem, dx=0.01, progress=False, trim_to_surface=True)
    np.testing.assert_array_equal(again["scene"].particles, fresh.particles)
    assert again["signature_m"] == 0.123 and again["trim_to_surface"] is True
    assert [len(p) for p in again["obs"].points] == n_points


@pytest.mark.parametrize("flag, text, said", [("--effect-params", "viscosty=200", "'viscosty' is no parameter"),
                                              ("--effect-params", "viscosity", "NAME=VALUE"),
                                              ("--effect-params", "viscosity=lots", "must be a number"),
                                              ("--base-params", "youngs=1e4", "E, nu or density"),
                                              ("--base-params", "E=soft", "E must be a number")])
def test_bad_effect_params_are_refused_before_anything_is_made(bench, tmp_path, flag, text, said):
    """A misspelt, bare or non-numeric ``--effect-params`` or ``--base-params`` entry stops ``--make`` with a
    message naming it, before any recording is written (a misspelt name would otherwise leave the default
    silently)."""
    with pytest.raises(SystemExit, match=said):
        bench.main(["--object", "block", "--make", str(tmp_path / "rec"), "--problems", str(tmp_path / "prob"),
                    "--effects", "viscosity", flag, text, "--only-make"])
    assert not (tmp_path / "rec").exists() and not (tmp_path / "prob").exists()


def test_accuracy_is_tallied_by_the_verdicts_confidence(bench, tmp_path, capsys):
    """Each verdict falls in one confidence bin, [0, 0.5), [0.5, 0.9) or [0.9, 1.0] (1.0 in the last, 0.5 and 0.9
    in the upper of the two they border), and each bin says how many of its verdicts were right."""
    rows = [dict(_row("a-0-none", "none", "none", "drag", 0.01), confidence=1.0),
            dict(_row("b-0-fracture", "fracture", "gripper_slip", "lift-end", 0.01), confidence=0.9),
            dict(_row("c-0-plasticity", "plasticity", "plasticity", "press-release", 0.01), confidence=0.5),
            dict(_row("d-0-viscosity", "viscosity", "none", "push-slide", 0.01), confidence=0.4),
            dict(_row("e-0-none", "none", "none", "lift-end", 0.01), confidence=0.0)]
    bins = bench._by_confidence(rows)
    assert [(lo, hi, ok) for lo, hi, ok in bins] == [(0.0, 0.5, [False, True]), (0.5, 0.9, [True]),
                                                     (0.9, 1.0, [True, False])]
    assert ("0.0-0.5: 1 of 2 right; 0.5-0.9: 1 of 1 right; 0.9-1.0: 1 of 2 right"
            in _summarise(bench, tmp_path, capsys, rows))


def test_a_table_of_none_recordings_alone_has_no_reduction_to_give(bench, tmp_path, capsys):
    """A run of `none` recordings alone (one process of bench_doctor_gpus.sh) has no held-out reduction with a true
    effect: its tables say n/a, without numpy's warning over an empty slice; with an effect row they give it."""
    rows = [_row("a-0-none", "none", "none", "drag", 0.01), _row("b-0-none", "none", "none", "lift-end", 0.01)]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out = _summarise(bench, tmp_path, capsys, rows)
    assert "median held-out Chamfer reduction with the true effect n/a;" in out
    assert "median Chamfer reduction on them n/a" in out and "nan %" not in out
    rows.append(_row("c-0-plasticity", "plasticity", "plasticity", "press-release", 0.01))
    assert "median held-out Chamfer reduction with the true effect n/a;" not in _summarise(bench, tmp_path, capsys, rows)



def test_the_median_reduction_where_the_true_effect_was_named_is_given_beside_the_benchmarks(bench, tmp_path, capsys):
    """Beside the median held-out reduction over every effect recording (the true effect's fit, named or not), the
    table gives the median over those whose true effect was named: a missed effect with a large reduction counts
    in the first and not in the second, a wrong effect named on a none recording in neither."""
    rows = [dict(_row("a-0-plasticity", "plasticity", "plasticity", "press-release", 0.01), reduction=0.6),
            dict(_row("b-0-plasticity", "plasticity", "plasticity", "press-release", 0.01), reduction=0.5),
            dict(_row("c-0-viscosity", "viscosity", "none", "squeeze-ring", 0.01), reduction=0.05),
            dict(_row("d-0-viscosity", "viscosity", "plasticity", "squeeze-ring", 0.01), reduction=0.9),
            _row("e-0-none", "none", "viscosity", "drag", 0.01)]
    out = _summarise(bench, tmp_path, capsys, rows)
    assert "median held-out Chamfer reduction with the true effect 55.0 %;" in out  # 0.05, 0.5, 0.6, 0.9
    assert "where the true effect was named: median held-out Chamfer reduction 55.0 % of 2 " in out  # 0.5, 0.6
    rows[3]["reduction"] = 0.2
    out = _summarise(bench, tmp_path, capsys, rows)
    assert "with the true effect 35.0 %;" in out and "where the true effect was named: median held-out Chamfer " \
        "reduction 55.0 % of 2 " in out
    rows = [r for r in rows if r["verdict"] != r["truth"]]
    assert "where the true effect was named" not in _summarise(bench, tmp_path, capsys, rows)

@pytest.fixture(scope="module")
def slide_problems(bench, tmp_path_factory):
    """A folder of one problem: a block pushed across a slippery table (friction 0.05), made on a 2-cm grid."""
    out = tmp_path_factory.mktemp("slide")
    rc = bench.main(["--object", "block", "--make", str(out / "rec"), "--problems", str(out / "prob"),
                     "--effects", "table_friction", "--only-scripts", "push-slide", "--scripts", "1", "--seeds", "1",
                     "--dx", "0.02", "--synth-dx", "0.02", "--frames", "8", "--cameras", "2", "--width", "160",
                     "--height", "120", "--only-make"])
    assert rc == 0
    return out / "prob"


def test_the_recordings_own_simulation_reproduces_it_and_only_it(bench, slide_problems, tmp_path):
    """``--oracle`` runs the synthesiser again with the recording's ground truth on the grid the problem says it was
    made on and scores its own particles as the doctor scores a fit: a block pushed across a slippery table
    (friction 0.05) scores at the depth noise's level, and the same run with the table's friction at 0.5 tens of
    millimetres away. A grid other than the recording's, or none known, is refused by name."""
    import pickle

    (pkl,) = slide_problems.glob("*.pkl")
    with open(pkl, "rb") as f:
        prob = pickle.load(f)
    assert prob["synth_dx"] == 0.02
    own = bench.oracles(slide_problems, bench.parse_args(["--object", "block"]))
    for friction, d in ((0.5, "slow"), (None, "unknown")):
        (tmp_path / d).mkdir()
        with open(tmp_path / d / pkl.name, "wb") as f:
            pickle.dump(dict(prob, truth_params={"friction": friction}) if friction else
                        {k: v for k, v in prob.items() if k != "synth_dx"}, f)
    slow = bench.oracles(tmp_path / "slow", bench.parse_args(["--object", "block"]))
    mine, other = own[0], slow[0]
    assert mine["oracle_chamfer_m"] < 8e-3 and other["oracle_chamfer_m"] > 4 * mine["oracle_chamfer_m"], (own, slow)
    assert mine["oracle_chamfer_m"] == pytest.approx(0.5 * (mine["oracle_obs_to_pred_m"] + mine["oracle_pred_to_obs_m"]))
    assert mine["unseen_surface"] is True  # scored as the doctor scores by default
    with pytest.raises(SystemExit, match="made on a 0.02 m grid, not --synth-dx 0.01"):
        bench.oracles(slide_problems, bench.parse_args(["--object", "block", "--synth-dx", "0.01"]))
    with pytest.raises(SystemExit, match="does not say which grid"):
        bench.oracles(tmp_path / "unknown", bench.parse_args(["--object", "block"]))


def test_vary_physics_gives_each_seed_its_own_material_and_grid_and_the_oracle_follows(bench, tmp_path):
    """``--make --vary-physics``: each seed draws its own E, effect parameter, grid offset and particle jitter
    (within VARY_FACTORS), the same for its ``none`` as for its effect; the recording's ground truth and the problem
    hold what was drawn, and the recording's own simulation (``--oracle``), run with them, reproduces it at the
    depth noise's level."""
    import pickle

    from empm_gym.perception.synth import OBJECT_DEFAULTS

    rc = bench.main(["--object", "block", "--make", str(tmp_path / "rec"), "--problems", str(tmp_path / "prob"),
                     "--effects", "table_friction", "--only-scripts", "push-slide", "--scripts", "1", "--seeds", "2",
                     "--dx", "0.02", "--synth-dx", "0.02", "--frames", "8", "--cameras", "2", "--width", "160",
                     "--height", "120", "--only-make", "--vary-physics"])
    assert rc == 0
    probs = {}
    for seed in (0, 1):
        name = f"v_block-push-slide-{seed}-table_friction"
        with open(tmp_path / "prob" / f"{name}.pkl", "rb") as f:
            probs[seed] = pickle.load(f)
        prob = probs[seed]
        gt = json.loads((tmp_path / "rec" / name / "ground_truth.json").read_text())
        assert gt["material"]["E"] == pytest.approx(prob["base_params"]["E"])
        assert gt["table_friction"] == pytest.approx(prob["truth_params"]["friction"])
        assert gt["scene"]["grid_offset_cells"] == pytest.approx(prob["synth_kw"]["grid_offset"])
        assert 0.5 <= prob["base_params"]["E"] / OBJECT_DEFAULTS["block"]["E"] <= 2.0
        assert 0.025 <= prob["truth_params"]["friction"] <= 0.1
        none_base, _, none_kw = bench.varied_physics(seed, "block", "none", {}, {})
        assert none_base == prob["base_params"] and none_kw == prob["synth_kw"]
    assert probs[0]["base_params"]["E"] != probs[1]["base_params"]["E"]
    assert probs[0]["synth_kw"]["grid_offset"] != probs[1]["synth_kw"]["grid_offset"]
    assert all(p["synth_kw"]["grid_offset"][2] == 0.0 for p in probs.values())  # the table's node layer stays
    own = bench.oracles(tmp_path / "prob", bench.parse_args(["--object", "block"]))
    assert len(own) == 2 and all(r["oracle_chamfer_m"] < 8e-3 for r in own), own


def test_the_doctors_simulator_is_the_synthesisers_on_its_grid_and_another_offset_moves_it(bench, slide_problems,
                                                                                         capsys):
    """``--grid-offsets``: on the recording's own grid (offset 0) the doctor's simulator, given the synthesiser's
    body and the true material, reproduces the recording's own simulation particle for particle and scores at the
    depth noise's level; on the grid shifted by half a cell along x the coarse block (50 particles, 2-cm cells)
    slides on another discretisation, ends elsewhere and scores worse. An offset outside [0, 1) cells, or not
    three numbers, is refused by name."""
    rows = bench.grid_offsets(slide_problems, bench.parse_args(["--object", "block",
                                                                "--grid-offsets", "0,0,0;0.5,0,0"]))
    assert [r["grid_offset_cells"] for r in rows] == [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]
    same, moved = rows
    assert same["max_from_own_m"] < 1e-5, same
    assert moved["max_from_own_m"] > 1e-4, moved
    assert same["heldout_chamfer_m"] < 8e-3 and same["heldout_loss"] < 0.8 * moved["heldout_loss"], rows
    assert same["parts_from_frame"] is None and same["own_parts_from_frame"] is None and same["last_pieces"] == 1
    assert "parts on 0 of 2 grid offsets" in capsys.readouterr().out
    for bad in ("1,0,0", "0.5,0", "a,0,0"):
        with pytest.raises(SystemExit):
            bench.parse_args(["--object", "block", "--grid-offsets", bad])
        assert "--grid-offsets wants X,Y,Z in cells" in capsys.readouterr().err


def test_the_discretisations_score_the_true_material_on_the_doctors_body_as_the_floor_does_and_on_its_variants(
        bench, slide_problems, capsys):
    """``--discretisations K``: the true material on the doctor's own body scores what ``--floor`` scores, and on
    each of the doctor's discretisation variants (grid shifted by part of a cell, particles on another lattice)
    something else: the coarse block (2-cm cells) slides on another discretisation. The spread is the largest over
    the smallest; K under 1 is refused by name."""
    (floor,) = bench.floors(slide_problems, bench.parse_args(["--object", "block"]))
    (row,) = bench.discretisations(slide_problems, bench.parse_args(["--object", "block", "--discretisations", "2"]))
    assert len(row["heldout_loss"]) == 3 and len(row["heldout_chamfer_m"]) == 3
    assert row["heldout_loss"][0] == pytest.approx(floor["floor_loss"], rel=1e-6)
    assert row["heldout_chamfer_m"][0] == pytest.approx(floor["floor_chamfer_m"], rel=1e-6)
    assert len(set(row["heldout_loss"])) == 3, row  # each discretisation its own outcome
    assert row["spread"] == pytest.approx(max(row["heldout_loss"]) / min(row["heldout_loss"])) and row["spread"] > 1.0
    capsys.readouterr()
    with pytest.raises(SystemExit):
        bench.main(["--problems", str(slide_problems), "--object", "block", "--discretisations", "0"])
    assert "--discretisations takes the number of variants, at least 1, got 0" in capsys.readouterr().err


def test_the_gap_closed_is_measured_above_the_recordings_own_simulation(bench, tmp_path, capsys):
    """With ``--oracle`` rows among ``--floors``: a base model at 4 mm, the fit at 3 mm and the recording's own
    simulation at 2 mm show 25 % of a possible 50 %, half the gap above the noise closed; the median is taken over
    the recordings."""
    rows = [dict(_row("dough-drag-0-table_friction", "table_friction", "table_friction", "drag", 0.01),
                 base_chamfer_m=0.004, true_effect_chamfer_m=0.003, reduction=0.25),
            dict(_row("dough-push-slide-0-table_friction", "table_friction", "table_friction", "push-slide", 0.01),
                 base_chamfer_m=0.010, true_effect_chamfer_m=0.002, reduction=0.8)]
    oracle = [{"recording": "dough-drag-0-table_friction", "truth": "table_friction", "oracle_chamfer_m": 0.002,
               "oracle_obs_to_pred_m": 0.003, "oracle_pred_to_obs_m": 0.001},
              {"recording": "dough-push-slide-0-table_friction", "truth": "table_friction", "oracle_chamfer_m": 0.002}]
    (tmp_path / "rows.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (tmp_path / "oracle.jsonl").write_text("".join(json.dumps(r) + "\n" for r in oracle))
    assert bench.main(["--summarise", str(tmp_path / "rows.jsonl"), "--floors", str(tmp_path / "oracle.jsonl")]) == 0
    out = capsys.readouterr().out
    # possible: 50 % and 80 %, median 65 %; gap closed: 50 % and 100 %, median 75 %
    assert "table_friction           2 recordings: shown   52.5 %, possible   65.0 %" in out
    assert "gap closed   75.0 % (medians)" in out
    assert ("its two halves, dough (1): observed points to the carried ones (noise, and surface seen later but not "
            "at frame 0) 3.00 mm") in out
    assert "carried to observed 1.00 mm" in out
    # rows scored as the doctor now scores (observed points may match the simulated body's unseen surface)
    oracle[0]["unseen_surface"] = True
    (tmp_path / "oracle.jsonl").write_text("".join(json.dumps(r) + "\n" for r in oracle))
    assert bench.main(["--summarise", str(tmp_path / "rows.jsonl"), "--floors", str(tmp_path / "oracle.jsonl")]) == 0
    assert "its two halves, dough (1): observed points to the simulation (noise) 3.00 mm" in capsys.readouterr().out


def test_a_none_recording_the_synthesiser_tore_may_be_called_fracture_against_what_it_shows(bench, tmp_path,
                                                                                           capsys):
    """A `none` recording whose body the synthesiser tore (ground_truth.json's parted) shows a fracture: called
    fracture, it is wrong as made but right against what it shows; called gripper slip, wrong either way. A torn
    recording of the fracture itself is no such recording."""
    torn = {"pieces": 2, "from_frame": 18, "link_m": 0.01}
    rows = [dict(_row("a-0-none", "none", "fracture", "lift-end", 0.01), parted=torn),
            dict(_row("b-0-none", "none", "gripper_slip", "lift-end", 0.01), parted=torn),
            dict(_row("c-0-none", "none", "none", "drag", 0.01), parted=None),
            dict(_row("d-0-fracture", "fracture", "fracture", "lift-end", 0.01), parted=torn)]
    out = _summarise(bench, tmp_path, capsys, rows)
    assert "naming accuracy 50.0 %" in out
    assert "fracture: 2 such, 1 called fracture): accuracy 75.0 % of 4" in out


def test_the_second_script_is_the_objects_own_where_the_dough_s_does_not_show_on_it(bench, tmp_path, capsys):
    """The rope's viscosity is benchmarked on squeeze-lift (push-slide shows it by under EXPRESSED_M on the rope);
    the dough's stays on push-slide. A rope pushed across the table with viscosity falls among the other
    recordings."""
    assert bench.second_script("rope", "viscosity") == "squeeze-lift"
    assert bench.second_script("dough", "viscosity") == "push-slide"
    assert bench.second_script("rope", "fracture") == bench.OTHER["fracture"]
    assert bench.object_of("sm_rope-drag-10-none") == "rope" and bench.object_of("dough-drag-1-none") == "dough"
    rows = [_row("rope-squeeze-lift-0-viscosity", "viscosity", "viscosity", "squeeze-lift", 0.01),
            _row("rope-push-slide-0-viscosity", "viscosity", "none", "push-slide", 0.01),
            _row("dough-push-slide-0-viscosity", "viscosity", "viscosity", "push-slide", 0.01),
            _row("dough-squeeze-lift-0-viscosity", "viscosity", "none", "squeeze-lift", 0.01)]
    out = _summarise(bench, tmp_path, capsys, rows)
    assert "none on every script (2 recordings)" in out
    assert "push-slide with viscosity; 2 recordings)" in out
    ours, others = out.split("=== other recordings")
    assert "recordings 2; naming accuracy 100.0 %" in ours and "recordings 2; naming accuracy 0.0 %" in others


def test_the_stored_tally_takes_each_recordings_last_run_in_session_order(tmp_path):
    """tally_doctor.stored_rows: the run of a later session (by number: s12 after s3) replaces an earlier one,
    an excluded experiment's file is not read, and recordings off the benchmark's scripts or seeds are left out."""
    tally = load_benchmark("tally_doctor")

    def write(name, rows):
        (tmp_path / name).write_text("".join(json.dumps(r) + "\n" for r in rows))

    write("doctor_s3_first.jsonl", [_row("rope-squeeze-lift-10-viscosity", "viscosity", "none", "squeeze-lift", 0.01),
                                    _row("dough-drag-11-none", "none", "none", "drag", 0.01),
                                    _row("rope-push-slide-10-viscosity", "viscosity", "none", "push-slide", 0.01),
                                    _row("dough-drag-9-none", "none", "none", "drag", 0.01)])
    write("doctor_s12_again.jsonl", [_row("rope-squeeze-lift-10-viscosity", "viscosity", "viscosity", "squeeze-lift",
                                          0.01)])
    write("doctor_s20_probe_x.jsonl", [_row("dough-drag-11-none", "none", "table_friction", "drag", 0.01)])
    rows = {r["recording"]: r for r in tally.stored_rows(10, 18, tmp_path)}
    assert sorted(rows) == ["dough-drag-11-none", "rope-squeeze-lift-10-viscosity"]
    assert rows["rope-squeeze-lift-10-viscosity"]["verdict"] == "viscosity"
    assert rows["rope-squeeze-lift-10-viscosity"]["source"] == "doctor_s12_again.jsonl"
    assert rows["dough-drag-11-none"]["verdict"] == "none"
    assert tally.by_session(rows.values()) == "s3 1, s12 1"
    # the recordings made with --vary-physics are their own set
    write("doctor_s13_varied.jsonl", [_row("v_dough-drag-11-none", "none", "none", "drag", 0.01)])
    assert [r["recording"] for r in tally.stored_rows(10, 18, tmp_path, varied=True)] == ["v_dough-drag-11-none"]
    assert "v_dough-drag-11-none" not in {r["recording"] for r in tally.stored_rows(10, 18, tmp_path)}
    with pytest.raises(SystemExit, match="FIRST must not exceed LAST; got '18-10'"):
        tally.main(["--seeds", "18-10"])


def test_the_tally_counts_each_simulation_once_over_its_seeds():
    """tally_doctor.by_simulation: the seeds of one object, script and truth are one simulation; its count is of
    the right verdicts among them, and another script or object is another simulation."""
    tally = load_benchmark("tally_doctor")
    rows = [_row("dough-pull-apart-10-fracture", "fracture", "gripper_slip", "pull-apart", 0.01),
            _row("dough-pull-apart-11-fracture", "fracture", "fracture", "pull-apart", 0.01),
            _row("dough-pull-apart-12-fracture", "fracture", "gripper_slip", "pull-apart", 0.01),
            _row("rope-pull-apart-10-fracture", "fracture", "fracture", "pull-apart", 0.01),
            _row("dough-lift-end-10-fracture", "fracture", "fracture", "lift-end", 0.01)]
    assert tally.by_simulation(rows) == {("dough", "pull-apart", "fracture"): (1, 3),
                                         ("rope", "pull-apart", "fracture"): (1, 1),
                                         ("dough", "lift-end", "fracture"): (1, 1)}


def test_the_stored_floors_are_each_recordings_last_of_each_kind(tmp_path):
    """tally_doctor.stored_floors: a floor (true material on the doctor's body) and an oracle (the recording's own
    simulation) of one recording are both kept, a later session's floor replaces an earlier one, and a floor
    measured on a body changed to compare (trimmed_bodies) is not read."""
    tally = load_benchmark("tally_doctor")
    rec = "rope-squeeze-ring-15-viscosity"
    (tmp_path / "doctor_floors_s29_a.jsonl").write_text(json.dumps({"recording": rec, "floor_chamfer_m": 0.003}) + "\n")
    (tmp_path / "doctor_s55_floors_b.jsonl").write_text(json.dumps({"recording": rec, "floor_chamfer_m": 0.0025}) + "\n")
    (tmp_path / "doctor_s56_floors_trimmed_bodies.jsonl").write_text(
        json.dumps({"recording": rec, "floor_chamfer_m": 0.001}) + "\n")
    (tmp_path / "doctor_s42_oracle_c.jsonl").write_text(json.dumps({"recording": rec, "oracle_chamfer_m": 0.0016}) + "\n")
    rows = tally.stored_floors(tmp_path)
    assert len(rows) == 2
    assert [r["floor_chamfer_m"] for r in rows if "floor_chamfer_m" in r] == [0.0025]
    assert [r["oracle_chamfer_m"] for r in rows if "oracle_chamfer_m" in r] == [0.0016]


def test_the_tally_finds_the_stored_runs_the_raised_viscosity_box_would_fit_again():
    """tally_doctor.would_raise: a stored viscosity candidate at the top of its capped box that gained held out
    (the rope squeezed in the ring, seed 18: 18.1 Pa s, gain 12.4 %) would be fitted again, its box recomputed
    from the E window at the recording's cell where the row predates stored boxes (5 mm and 41.4 kPa: 22.7 Pa s);
    not one lower in its box, one the run already raised, or a row without a viscosity candidate."""
    tally = load_benchmark("tally_doctor")

    def row(v, **extra):
        cand = {"effect": "viscosity", "params": {"E": 1.4e4, "viscosity": v}, "fit_loss": 0.004,
                "gain": {"gain": 0.124, "threshold": 0.04, "lower": -0.027, "upper": 0.2},
                "material": {"E": 1.4e4, "nu": 0.3, "density": 1000.0}, "E_window": [4597.0, 41374.0]}
        return {"recording": "rope-squeeze-ring-18-viscosity", "grid": {"dx_m": 0.005},
                "candidates": [{"effect": "plasticity", "params": {"E": 1.5e4, "yield_stress": 900.0}}, cand], **extra}

    why = tally.would_raise(row(18.1))
    assert why.startswith("the viscosity candidate's fit ended at 18.1 Pa s, at the top of its box (0.5 to 22.7")
    assert tally.would_raise(row(10.0)) == ""
    assert tally.would_raise(row(18.1, viscosity_box_raised=3.0)) == ""
    assert tally.would_raise({**row(18.1), "candidates": row(18.1)["candidates"][:1]}) == ""
    # a stored box is used as it is: 18.1 Pa s near the top of 0.5-19 Pa s but low in a raised 0.5-68 Pa s one
    stored = row(18.1)
    stored["candidates"][1]["search_box"] = {"E": [4597.0, 41374.0], "viscosity": [0.5, 68.0]}
    assert tally.would_raise(stored) == ""


def test_the_summary_reports_the_shared_clocks_damping(bench, capsys):
    """bench_doctor._clock_damping: the median change of the base model's held-out loss from the diagnosis's clock
    to its own, and the recordings beyond the penalty (rows without the check, before session 58, left out)."""
    rows = [{"recording": "rope-squeeze-ring-17-viscosity", "verdict": "none", "clock_change": 0.115},
            {"recording": "dough-push-slide-15-viscosity", "verdict": "none", "clock_change": -0.006},
            {"recording": "dough-press-release-10-none", "verdict": "none", "clock_change": 0.006},
            {"recording": "rope-drag-12-none", "verdict": "none", "clock_change": None},
            {"recording": "rope-drag-13-none", "verdict": "none"}]
    bench._clock_damping(rows)
    out = capsys.readouterr().out
    assert "3 recordings, median change of its held-out loss +0.6 %; beyond the 4 % penalty on 1" in out
    assert "rope-squeeze-ring-17-viscosity" in out and "+11.5 %" in out and "dough-push-slide" not in out
    bench._clock_damping(rows[3:])
    assert capsys.readouterr().out == ""
    row = bench._row({"effect": "none", "clock": {"change": 0.115}}, "viscosity", "r", "squeeze-ring", None, 1.0)
    assert row["clock_change"] == 0.115


def test_floors_take_only_the_given_objects_problems_each_with_its_own_material(bench, tmp_path):
    """``--floor``, ``--oracle`` and ``--grid-offsets`` simulate each effect problem's true material, which is its
    object's (E, nu, density, the effect's defaults): a folder holding dough and rope problems yields, for
    ``--object dough``, the dough's alone (by the problem's ``object``, or for problems made before it, by the name
    ``--make`` gives them), and a problem that says neither is refused by name."""
    import pickle

    from empm_gym.perception.synth import effect_material

    def put(name, **prob):
        with open(tmp_path / f"{name}.pkl", "wb") as f:
            pickle.dump({"truth": "viscosity", "truth_params": {}, "base_params": {}, **prob}, f)

    put("v_dough-push-slide-21-viscosity")                      # old problem: its object from its name
    put("rope-squeeze-lift-3-viscosity")
    put("renamed-by-a-user", object="dough")                     # new problem: its object from itself
    put("dough-drag-3-none", truth="none")
    got = {p.stem: mat for p, _, mat in bench._effect_problems(tmp_path, "dough")}
    assert sorted(got) == ["renamed-by-a-user", "v_dough-push-slide-21-viscosity"]
    assert got["renamed-by-a-user"] == effect_material("dough", "viscosity")[0]
    assert effect_material("rope", "viscosity")[0] != got["renamed-by-a-user"]  # the mix-up this guards against
    assert [p.stem for p, _, _ in bench._effect_problems(tmp_path, "rope")] == ["rope-squeeze-lift-3-viscosity"]
    with_none = {p.stem: mat for p, _, mat in bench._effect_problems(tmp_path, "dough", with_none=True)}
    assert sorted(with_none) == ["dough-drag-3-none", "renamed-by-a-user", "v_dough-push-slide-21-viscosity"]
    assert with_none["dough-drag-3-none"] == effect_material("dough", "none")[0]  # the base model, no effect
    put("mystery", truth="fracture")
    with pytest.raises(SystemExit, match="mystery.pkl does not say which object"):
        list(bench._effect_problems(tmp_path, "dough"))


def test_rescore_calls_a_verdict_first_on_no_more_than_half_of_the_discretisations_none(bench, tmp_path):
    """A dump whose verdict came first on 1 of 5 discretisations (seed 23's dough lifted by one end without an
    effect, session 71: gripper slip, a stiffness field that fails on one grid first on the others) rescores as
    none under session 72's split rule; the same dump with the slip first on 3 of 5 keeps it."""
    labels = ["grid (1)", "grid (2)", "without camera 0", "without camera 1"]

    def test(gain):
        return {"gain": gain, "lower": gain - 0.1, "upper": gain + 0.1, "threshold": 0.04, "significant": True}

    def tests(gains):
        return {"tests": [{"variant": v, "gain": g, "threshold": 0.04,
                           "kind": "discretisation" if v.startswith("grid") else "body"} for v, g in zip(labels, gains)]}

    def res(name, field_gains):
        return {"recording": name, "script": "lift-end", "truth": "none", "effect": "gripper_slip",
                "confidence": 0.05, "wall_s": 1.0,
                "base": {"heldout": {"chamfer_m": 2e-3, "loss": 6.1e-3}, "params": {"E": 1.5e4}},
                "candidates": [{"effect": "heterogeneous_stiffness", "heldout": {"chamfer_m": 1.6e-3, "loss": 3.5e-3},
                                "gain": test(0.434), "toward_absence": []},
                               {"effect": "gripper_slip", "heldout": {"chamfer_m": 1.7e-3, "loss": 4.2e-3},
                                "gain": test(0.319), "toward_absence": []}],
                "variants": {"variants": labels, "base_E": 1.5e4, "base": [], "candidates": {
                    "heterogeneous_stiffness": tests(field_gains),
                    "gripper_slip": tests([0.065, 0.139, 0.443, 0.365])}}}

    rows = [res("split", [-0.01, 0.175, 0.470, 0.421]), res("most", [-0.01, 0.100, 0.400, 0.421])]
    (tmp_path / "dump.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    got = {r["recording"]: r["verdict"] for r in bench.rescore([tmp_path / "dump.jsonl"])}
    assert got == {"split": "none", "most": "gripper_slip"}


def test_make_with_two_effects_records_both_and_scores_against_both(bench, tmp_path):
    """``--make --effects plasticity+table_friction``: one recording per natural script of either effect, made
    with both effects (the ground truth names both), its problem's truth naming both; no single-effect
    signature is computed for it."""
    import pickle

    rc = bench.main(["--object", "block", "--make", str(tmp_path / "rec"), "--problems", str(tmp_path / "prob"),
                     "--effects", "plasticity+table_friction", "--effect-params", "friction=0.1", "--seeds", "1",
                     "--frames", "4", "--cameras", "2", "--width", "160", "--height", "120", "--only-make"])
    assert rc == 0
    names = sorted(p.stem for p in (tmp_path / "prob").glob("*.pkl"))
    assert names == ["block-press-release-0-plasticity+table_friction-friction0.1",
                     "block-push-slide-0-plasticity+table_friction-friction0.1"]
    with open(tmp_path / "prob" / f"{names[0]}.pkl", "rb") as f:
        prob = pickle.load(f)
    assert prob["truth"] == "plasticity+table_friction" and prob["signature_m"] is None
    # what each shows on top of the other, for the rounds' tally (a second round can only see that much)
    assert set(prob["signatures"]) == {"plasticity", "table_friction"}
    assert all(v >= 0.0 and v == v for v in prob["signatures"].values())
    gt = json.loads((tmp_path / "rec" / names[0] / "ground_truth.json").read_text())
    assert [e["name"] for e in gt["effects"]] == ["plasticity", "table_friction"]
    assert gt["effects"][1]["params"] == {"friction": 0.1}


@pytest.mark.parametrize("effects, said", [("plasticity+plasticity", "two different effects"),
                                           ("plasticity+viscosty", "two different effects"),
                                           ("none+plasticity", "two different effects"),
                                           ("plasticity+viscosity+fracture", "two different effects")])
def test_bad_pairs_of_effects_are_refused_before_anything_is_made(bench, tmp_path, effects, said):
    with pytest.raises(SystemExit, match=said):
        bench.main(["--object", "block", "--make", str(tmp_path / "rec"), "--problems", str(tmp_path / "prob"),
                    "--effects", effects, "--only-make"])
    with pytest.raises(SystemExit, match="without --vary-physics"):
        bench.main(["--object", "block", "--make", str(tmp_path / "rec"), "--problems", str(tmp_path / "prob"),
                    "--effects", "plasticity+viscosity", "--vary-physics", "--only-make"])
    assert not (tmp_path / "rec").exists() and not (tmp_path / "prob").exists()


def test_diagnoses_in_rounds_are_tallied_against_every_effect_of_the_recording(bench, capsys):
    """The rounds' table: a two-effect recording counts when both are named (in either order), a first verdict
    among them, an effect named that it lacks; on a one-effect recording whose first verdict is right, a further
    effect named by a later round is an invented one."""
    def row(name, truth, effects, final):
        verdicts = [(e, 1.0) for e in effects] + ([("none", 1.0)] if len(effects) < 2 else [])
        return {"recording": name, "truth": truth, "effects": effects, "round_verdicts": verdicts,
                "base_chamfer_m": 0.004, "final_chamfer_m": final}

    bench.summarise_rounds([{**row("a", "plasticity+table_friction", ["table_friction", "plasticity"], 0.001),
                             "signatures": {"plasticity": 0.0013, "table_friction": 0.05}},
                            {**row("b", "gripper_slip+plasticity", ["gripper_slip"], 0.002),
                             "signatures": {"plasticity": 0.0004, "gripper_slip": 0.01}},
                            row("c", "gripper_slip+fracture", ["viscosity"], 0.003),
                            row("d", "plasticity", ["plasticity"], 0.002),
                            row("e", "table_friction", ["table_friction", "viscosity"], 0.001),
                            row("f", "none", [], 0.004),
                            row("g", "fracture", ["gripper_slip"], 0.003)])
    out = capsys.readouterr().out
    assert "two effects: both named 1 of 3; the first verdict one of them 2; an effect named that the recording " \
           "lacks 1; median held-out Chamfer reduction of the last model named 50.0 %" in out
    assert "the other effect, where it shows by 1 mm or more held out on top of the first: named 1 of 1; where it " \
           "shows less: named 0 of 1" in out
    assert "one effect or none: the first verdict right on 3 of 4; of those, a further effect named by a later round " \
           "on 1 (e)" in out


def test_the_pair_screen_measures_what_pair_signatures_measures(bench, capsys):
    """``--screen-pairs``: from one simulation per effect set, each effect alone and each of a pair on top of the
    other, equal to what ``effect_signature`` and ``pair_signatures`` measure for the same material (a screen
    that added the effects in another way would choose recordings that do not show what it said); the table
    marks a pair where both show by EXPRESSED_M."""
    from empm_gym.perception.synth import effect_signature

    kw = dict(frames=4, dx=0.02)
    eparams = {"friction": 0.1, "yield_stress": 100.0}
    got = bench.screen_pairs("block", "push-slide", ["plasticity", "table_friction"], eparams, {}, **kw)
    pair = bench.pair_signatures("block", "push-slide", ["plasticity", "table_friction"], eparams, {}, **kw)
    assert got["pairs"][("plasticity", "table_friction")] == pair
    assert got["single"]["table_friction"] == effect_signature("block", "push-slide", "table_friction",
                                                               effect_params={"friction": 0.1}, **kw)
    assert got["single"]["table_friction"] > 1e-3  # a slippery table moves the pushed block: not a test of zeros
    bench.print_screen("block", "push-slide", {"single": {"a": 0.002, "b": 0.0}, "pairs": {("a", "b"): {"a": 0.0015,
                                                                                                   "b": 0.0012}}})
    out = capsys.readouterr().out
    assert "a+b" in out and "a    1.50, b    1.20  both" in out
    with pytest.raises(SystemExit):
        bench.main(["--screen-pairs", "push-slide", "--effects", "plasticity"])  # a pair needs two
    with pytest.raises(SystemExit):
        bench.main(["--screen-pairs", "push-sliide", "--effects", "plasticity,viscosity"])


def test_floors_with_the_true_part_in_the_grippers_swap_only_what_the_closed_grippers_hold(bench, slide_problems,
                                                                                           tmp_path):
    """``--floor --true-held`` scores the true and the elastic material again on the doctor's body with what the
    closed grippers hold at frame 0 replaced by the synthesiser's own particles there. A block held in two clamps:
    the prior fills each clamp to its middle, past the block's ends (more than the true part), and the true part is
    what the synthesiser's body has inside them. A block pushed by an open pusher holds nothing: its floors are the
    same either way, to the bit."""
    import pickle

    import numpy as np

    rc = bench.main(["--object", "block", "--make", str(tmp_path / "rec"), "--problems", str(tmp_path / "prob"),
                     "--effects", "gripper_slip", "--only-scripts", "squeeze-lift", "--scripts", "1", "--seeds", "1",
                     "--dx", "0.02", "--synth-dx", "0.02", "--frames", "8", "--cameras", "3", "--width", "320",
                     "--height", "240", "--only-make"])
    assert rc == 0
    args = bench.parse_args(["--object", "block", "--true-held"])
    (held,) = bench.floors(tmp_path / "prob", args)
    (pkl,) = (tmp_path / "prob").glob("*.pkl")
    with open(pkl, "rb") as f:
        prob = pickle.load(f)
    from empm_gym.perception.fusion import inside_end_effectors
    from empm_gym.perception.synth import simulate

    sc = prob["scene"]
    own = simulate("block", sc.material, script="squeeze-lift", frames=2, dx=0.02, seed=prob["seed"])
    inside = inside_end_effectors(own["particles"][0], sc.ee_configs, sc.ee_positions[0], select=sc.ee_grip[0] == 1)
    assert held["true_held_volume_m3"] == pytest.approx(float(np.sum(np.asarray(own["volumes"])[inside])))
    assert held["held_volume_m3"] > held["true_held_volume_m3"] > 0.0
    assert all(np.isfinite(held[k]) for k in ("elastic_chamfer_m", "true_held_floor_chamfer_m",
                                              "true_held_elastic_chamfer_m"))
    (pushed,) = bench.floors(slide_problems, args)
    assert pushed["held_volume_m3"] == pushed["true_held_volume_m3"] == 0.0
    assert pushed["true_held_floor_chamfer_m"] == pushed["floor_chamfer_m"]


def test_the_chosen_models_intervals_are_checked_against_the_truth_at_the_doctors_density(bench, tmp_path, capsys):
    """A plastic dough (the synthesiser's E 20 kPa and yield stress 1 kPa at 1200 kg/m^3) named plasticity: E and
    the yield stress are compared at the doctor's 1000 kg/m^3 (16.7 kPa, 833 Pa); an interval that holds the truth
    covers it, one that misses it while saying the value is determined is a confident wrong value and is listed.
    A wrong verdict, two effects or no intervals are not checked."""
    unc = {"E": {"interval": [1.2e4, 2.0e4], "determined": True, "level": 0.95},
           "yield_stress": {"interval": [900.0, 1100.0], "determined": True, "level": 0.95}}
    res = {"effect": "plasticity", "uncertainty": unc, "base": {"params": {"E": 3e4}},
           "candidates": [{"effect": "plasticity", "params": {"E": 1.6e4, "yield_stress": 1000.0}}]}
    prob = {"truth": "plasticity", "truth_params": {"yield_stress": 1000.0}, "base_params": {}}
    checks = bench.interval_check(res, prob, "dough")
    assert [(c["param"], round(c["truth"], 1), c["covered"]) for c in checks] == [
        ("E", round(20e3 / 1.2, 1), True), ("yield_stress", round(1000.0 / 1.2, 1), False)]
    # the combination the doctor reports for two correlated values: yield_stress/E is the same at any density
    combo = {"value": 0.06, "interval": [0.055, 0.065], "level": 0.95, "determined": True, "of": ["E", "yield_stress"],
             "exponent": -1.0, "unit": "-"}
    both = {**res, "identifiability": {"combinations": {"yield_stress/E": combo,
                                                        "E/density": {"value": 16.0, "unit": "m^2/s^2"}}}}
    assert [(c["param"], round(c["truth"], 4), c["covered"]) for c in bench.interval_check(both, prob, "dough")][2:] \
        == [("yield_stress/E", 0.05, False)]
    assert bench.interval_check({**res, "effect": "gripper_slip"}, prob, "dough") == []
    assert bench.interval_check(res, {**prob, "truth": "plasticity+viscosity"}, "dough") == []
    assert bench.interval_check({**res, "uncertainty": None}, prob, "dough") == []
    # a none recording: the base model's E against the object's own
    none = {"effect": "none", "uncertainty": {"E": {"interval": [0.0, None], "determined": False, "level": 0.95}},
            "base": {"params": {"E": 3e4}}, "candidates": []}
    [c] = bench.interval_check(none, {"truth": "none", "base_params": {}}, "dough")
    assert c["covered"] and not c["determined"]  # an interval open above holds every stiffer value
    rows = [{**_row("dough-press-release-3-plasticity", "plasticity", "plasticity", "press-release", 0.01),
             "intervals": checks},
            {**_row("dough-press-release-3-none", "none", "none", "press-release", 0.01), "intervals": [c]}]
    out = _summarise(bench, tmp_path, capsys, rows)
    assert ("3 values; determined 2, of them covered 1; not determined 1, of them covered 1" in out
            and "determined but missed: dough-press-release-3-plasticity yield_stress = 1000" in out), out
