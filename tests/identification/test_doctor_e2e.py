"""The doctor end to end on the CPU, continued (see test_doctor.py, HIDDEN_2: a file of its own so that the CI's
two workers share these runs)."""

import pytest

from .test_doctor import HIDDEN_2, doctor_names_the_hidden_effect


@pytest.mark.slow
@pytest.mark.parametrize("case", HIDDEN_2, ids=["-".join(c[:2]) + ("-" + c[2] if len(c) > 2 else "") for c in HIDDEN_2])
def test_doctor_names_the_hidden_effect_too(tmp_path, case):
    doctor_names_the_hidden_effect(tmp_path, *case)


@pytest.mark.slow
def test_a_rig_whose_cameras_and_depth_are_off_is_corrected_and_its_effect_named(tmp_path):
    """Every camera 3 mm and 0.3 deg off its recorded pose and its depth 1 % off (a real rig's errors; the recording
    says nothing of them): uncorrected, the plastic dough pressed was fitted at E = 500 kPa, the search box's bound
    (35.6 kPa for the calibrated rig without an effect), and plasticity named at 0.50 (session 83). The loader
    shifts the cameras onto one surface and the rig onto the controls in memory, says so in the notes, and the
    doctor names plasticity with the base model's E inside its box."""
    import dataclasses
    import json

    from empm_gym.identification.doctor import diagnose_recording
    from empm_gym.perception.recording import Recording
    from empm_gym.perception.synth import synthesize

    from .test_doctor import _CPU

    rec = synthesize(tmp_path / "rec", "dough", script="press-release", effect="plasticity", frames=24, cameras=3,
                     width=320, height=180, seed=3, progress=False, calibration_error=(0.003, 0.3), depth_bias=0.01)
    (rec / "ground_truth.json").unlink()
    recorded = Recording(rec).c2w.copy()
    res = diagnose_recording(rec, out_dir=tmp_path / "doctor", config=dataclasses.replace(_CPU), dx=0.0125,
                             particles_per_cell=4, progress=False)
    note = [n for n in res["notes"] if "shifted onto one surface" in n]
    assert note and "whole rig was shifted" in note[0] and "files are unchanged" in note[0], res["notes"]
    assert res["effect"] == "plasticity", res["reason"]
    assert not res["base"]["at_search_bound"], res["base"]
    assert res["base"]["params"]["E"] < 0.5 * _CPU.E_bounds[1]
    assert (Recording(rec).c2w == recorded).all()  # the user's files are untouched
    written = json.loads((tmp_path / "doctor" / "doctor.json").read_text())
    assert any("shifted onto one surface" in n for n in written["notes"])
    cal = written["calibration"]
    assert cal["applied"] and cal["rig_shift_m"] is not None and len(cal["camera_shifts_m"]) == 3
    before, after = cal["cameras_disagree_m"]
    assert before > cal["tolerance_m"] > after


@pytest.mark.slow
def test_a_trackers_and_a_segmenters_errors_leave_the_fit_and_the_verdict_as_on_clean_data(tmp_path):
    """Tracks with a tracker's errors (2 px of jitter a frame, a drift of 0.3 px a frame, 5 % of them jumping 4-20
    px; at 320 x 180 a pixel is 3.8 mm at the object) and object masks grown by 3 px onto the pusher and the table
    (a segmenter's). Before session 84 the dough pressed without an effect was fitted there at E = 12.0 kPa with
    `none` at confidence 0.11 and a stiffness field 6 % better held out (35.6 kPa on the clean recording), at the
    search box's bound with the tracks' errors alone and at 13.9 kPa with the masks' alone. The tracks now weigh what
    their scatter against the depth's own leaves them, the pusher's pixels are given back to it, the table's rim
    and the tracked points that strayed onto it are left out: `none` at full confidence. E is either within a
    quarter of the clean recording's fit or said to lie at its search's bound: on this recording the elastic
    model's Chamfer over the fitting frames is lowest near 4 kPa at 0.2 times the truth (20 kPa) and within 5 % of
    it up to 1.5 times, with those tracks or without them (benchmarks/loss_sweep.py), and the fit chose 30.2 kPa
    with them and 3.7 kPa, at its bound, without (session 86). Neither is a measurement, and since session 87 the
    doctor says so: the clean fit's E (35.6 kPa) gets a 95 % interval that reaches below its search window and
    covers the truth, the noisy one's (3.7 kPa) lies at its bound, both marked not determined, in doctor.json,
    material.json, the notes and report.md."""
    import dataclasses
    import json

    from empm_gym.identification.doctor import diagnose_recording
    from empm_gym.perception.synth import synthesize

    from .test_doctor import _CPU

    res = {}
    for name, errors in (("clean", {}), ("noisy", dict(track_error=(2.0, 0.3, 0.05), mask_error_px=3))):
        rec = synthesize(tmp_path / name, "dough", script="press-release", effect="none", frames=24, cameras=3,
                         width=320, height=180, seed=3, progress=False, **errors)
        (rec / "ground_truth.json").unlink()
        res[name] = diagnose_recording(rec, out_dir=tmp_path / f"doctor-{name}", config=dataclasses.replace(_CPU),
                                       dx=0.0125, particles_per_cell=4, progress=False)
    clean, noisy = res["clean"], res["noisy"]
    assert clean["effect"] == "none" and clean["track_weight"] == 1.0
    assert noisy["effect"] == "none" and noisy["confidence"] > 0.9, (noisy["confidence"], noisy["reason"])
    assert noisy["track_weight"] < 0.1 and any("2D tracker" in n for n in noisy["notes"]), noisy["notes"]
    assert any("lay on the table" in n for n in noisy["notes"]), noisy["notes"]
    assert not clean["base"]["at_search_bound"]
    assert (noisy["base"]["params"]["E"] == pytest.approx(clean["base"]["params"]["E"], rel=0.25)
            or noisy["base"]["at_search_bound"] == ["E"]), noisy["base"]
    # how firmly the frames fix E: on this flat landscape, not at all, and every output says so; the clean fit's
    # interval covers the truth, the noisy fit's lies at its bound (what the errors do to the body and the tracks
    # is no noise that an interval holds: it says that the data ask for a value outside its box)
    u, truth = clean["uncertainty"]["E"], 20e3 * 1000.0 / 1200.0  # the doctor's density is 1000, the dough's 1200
    assert not u["determined"] and u["interval"][0] <= truth <= u["interval"][1], u
    assert not noisy["uncertainty"]["E"]["determined"] and any(
        w.startswith("E: ") and "outside the box searched" in w for w in noisy["identifiability"]["warnings"])
    for r in res.values():
        assert any("the base model's fitted E = " in n and "not determined by these frames" in n
                   for n in r["notes"]), r["notes"]
    fit = json.loads((tmp_path / "doctor-clean" / "material.json").read_text())["fit"]
    assert fit["uncertainty"] == json.loads(json.dumps(clean["uncertainty"]))
    report = (tmp_path / "doctor-clean" / "report.md").read_text()
    assert "## How firmly the fitting frames fix the base model's values (material.json)" in report
    assert f"- base E [Pa]: {clean['base']['params']['E']:.4g} (95 %: at most " in report
    assert "; not determined by these frames)" in report


def test_a_mask_that_takes_in_the_table_around_the_ringed_dough_leaves_it_none(tmp_path):
    """The dough squeezed in the ring without an effect, its masks grown by 3 pixels (11 mm at the object at
    320 x 180): the table's points around its base made a wider body than the object's, and before session 85 the
    doctor said `none` at confidence 0.02, a gripper slip 6.3 % better held out (clean: `none` at 1.00). The table's
    rim is now left out (fusion.drop_table_rim) and a note says so: `none` at 0.98."""
    import dataclasses

    from empm_gym.identification.doctor import diagnose_recording
    from empm_gym.perception.synth import synthesize

    from .test_doctor import _CPU

    rec = synthesize(tmp_path / "rec", "dough", script="squeeze-ring", effect="none", frames=24, cameras=3,
                     width=320, height=180, seed=3, progress=False, mask_error_px=3)
    (rec / "ground_truth.json").unlink()
    res = diagnose_recording(rec, out_dir=tmp_path / "doctor", config=dataclasses.replace(_CPU), dx=0.0125,
                             particles_per_cell=4, progress=False)
    assert res["effect"] == "none" and res["confidence"] > 0.5, (res["confidence"], res["reason"])
    assert any("reach onto the table" in n for n in res["notes"]), res["notes"]
