"""The discrepancy doctor on hidden-effect recordings: confusion matrix, naming accuracy, false effects on
``none``, held-out Chamfer reduction and wall time per recording.

Two stages, so that recordings can be made and loaded on a machine with Open3D (the CPU) and diagnosed on
another (the GPU):

    python benchmarks/bench_doctor.py --make /tmp/docbench --problems .whl/docproblems   # synth + load (CPU)
    python benchmarks/bench_doctor.py --problems .whl/docproblems --device cuda:0         # diagnose, table

``--make`` synthesises every effect of the catalogue and ``none`` on ``--scripts`` (natural script of the
effect first, then the others listed) with ``--seeds`` seeds, loads each recording with
:func:`empm_gym.identification.doctor.load_for_doctor` (on the grid `empm doctor` would choose, unless ``--dx``
gives one) and pickles what the doctor reads (the scene and the
observations) plus, for scoring only, the effect named in ``ground_truth.json``. The doctor never sees
that label. Without ``--problems`` it diagnoses in the same process.

Two effects at once: ``--effects plasticity+table_friction`` makes each pair on the natural script of either effect
(``--every-effect-on`` for others) and stores how much each shows held out on top of the other; ``--rounds 2``
diagnoses in rounds (``DoctorConfig.rounds``) and tallies the effects named against both (:func:`summarise_rounds`).
"""

from __future__ import annotations

import argparse
import json
import pickle
import re
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

NATURAL = {"none": "press-release", "plasticity": "press-release", "viscosity": "squeeze-ring",
           "table_friction": "push-slide", "gripper_slip": "squeeze-lift", "heterogeneous_stiffness": "pull-apart",
           "fracture": "pull-apart"}
#: The second script of each effect: one besides the natural script where the effect changes the held-out frames
#: by well over the depth noise (docs/EFFECTS.md, "every script"; drag and lift-end were written for the two
#: effects that no other script showed).
OTHER = {"none": "squeeze-lift", "plasticity": "squeeze-ring", "viscosity": "push-slide",
         "table_friction": "drag", "gripper_slip": "pull-apart", "heterogeneous_stiffness": "squeeze-ring",
         "fracture": "lift-end"}
#: Where an object's second script differs from OTHER's, chosen by the same rule on that object: the rope pushed
#: across the table shows its viscosity by 0.92 mm, under EXPRESSED_M (the dough's by more; OTHER was chosen on the
#: dough), the rope squeezed and lifted by 5.2 mm (docs/EFFECTS.md, the rope's signature on every script; session 55).
OTHER_ON = {("rope", "viscosity"): "squeeze-lift"}
#: The second scripts of the first runs (2026-11-23); four of them do not express their effect (EXPRESSED_M):
#: viscosity, table friction, the stiffness field and fracture. ``--scripts 3`` adds them as a third script.
FIRST_OTHER = {"none": "squeeze-lift", "plasticity": "squeeze-ring", "viscosity": "press-release",
               "table_friction": "press-release", "gripper_slip": "pull-apart",
               "heterogeneous_stiffness": "squeeze-lift", "fracture": "squeeze-lift"}

#: Held-out signature [m] below which a recording does not show its effect: the mean Chamfer, over the held-out
#: frames, between the true object simulated with and without the effect (about the depth noise; every
#: effect-script pair of the dough lies below 0.7 mm or above 1.5 mm, docs/EFFECTS.md).
EXPRESSED_M = 1.0e-3


def second_script(obj: str, effect: str) -> str:
    """The benchmark's second script for ``effect`` on the object ``obj`` ("dough", "rope", ...)."""
    return OTHER_ON.get((obj, effect), OTHER[effect])


#: What ``--make --vary-physics`` draws per seed: log-uniform factors on the value each parameter would have (the
#: object's default or ``--base-params``; the effect's default or ``--effect-params``), the grid's offset (uniform
#: in [0, 1) cells along x and y; none along z, which would move the table's node layer: docs/EFFECTS.md) and the
#: body's particles jittered by up to +-VARY_JITTER/2 of their spacing. The
#: stiffness slope stays within the doctor's cap (1.2 at the default 1.0) and the fracture strain at or above
#: 0.15 (the pull-apart stretches to 80 %).
VARY_FACTORS = {"E": (0.5, 2.0), "yield_stress": (0.5, 2.0), "viscosity": (0.5, 2.0), "friction": (0.5, 2.0),
                "grip_friction": (0.5, 2.0), "stiffness_slope_1": (0.6, 1.2), "fracture_strain": (0.75, 1.5)}
VARY_JITTER = 0.5


def varied_physics(seed: int, obj: str, effect: str, base: dict, eparams: dict):
    """``(base params, effect params, simulate kwargs)`` of seed ``seed`` under ``--vary-physics``: E, the
    effect's parameters of :data:`VARY_FACTORS`, the grid offset and the particle jitter drawn from the seed alone
    (the same E, offset and jitter for every effect and script of a seed: its ``none`` is the effect's recording
    without the effect). Without it every seed of one object, script and effect is one simulation, seen through
    other noise (benchmarks/RESULTS.md, session 56)."""
    from empm_gym.perception.synth import OBJECT_DEFAULTS, effect_material
    from empm_gym.sim.effects import EFFECTS

    def factor(rng, name):  # log-uniform within VARY_FACTORS[name]
        lo, hi = VARY_FACTORS[name]
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))

    rng = np.random.default_rng([int(seed), 56])
    E = float(base.get("E", OBJECT_DEFAULTS[obj]["E"])) * factor(rng, "E")
    # along x and y only: the table acts on the highest node layer not above it, and the synthesiser's grid has
    # one on the table (as the doctor's, on the table it measures); moved down, the body would rest in the table
    offset = [float(v) for v in rng.uniform(0.0, 1.0, 2)] + [0.0]
    out_base = {**base, "E": E}
    out_eff = {}
    if effect != "none":
        erng = np.random.default_rng([int(seed), 56, 1])
        values = effect_material(obj, effect, eparams or None, **out_base)[1][0]["params"]  # defaults at this E
        for name in EFFECTS[effect].param_names:
            if name in VARY_FACTORS:
                out_eff[name] = float(values[name]) * factor(erng, name)
            elif name in eparams:
                out_eff[name] = float(eparams[name])
    return out_base, out_eff, {"grid_offset": offset, "jitter": VARY_JITTER}


def object_of(recording: str) -> str:
    """The object of a benchmark recording's name: "rope-drag-10-none" -> "rope"; a set's own prefix
    ("d5_dough-...", "sm_rope-...") left out."""
    return recording.split("-")[0].split("_")[-1]


def _name_values(text, flag, known, unknown_msg):
    """``flag``'s NAME=VALUE pairs (comma-separated) as {name: float}; a bare item, a name not in ``known``
    (``unknown_msg(name)`` says why) or a value that is no number stops the run with a message naming it."""
    out = {}
    for item in (text.split(",") if text else []):
        k, eq, v = (x.strip() for x in item.partition("="))
        if not eq:
            raise SystemExit(f"{flag} takes NAME=VALUE pairs separated by commas, got {item!r}")
        if k not in known:
            raise SystemExit(f"{flag}: {unknown_msg(k)}")
        try:
            out[k] = float(v)
        except ValueError:
            raise SystemExit(f"{flag}: {k} must be a number, got {v!r}") from None
    return out


def _effect_params(text, effects):
    """``--effect-params`` as {name: value}; each name must be a parameter of one of ``effects`` (a misspelt one
    would otherwise leave the defaults in place without a word)."""
    from empm_gym.sim.effects import EFFECTS

    known = {p for e in effects if e != "none" for part in e.split("+") for p in EFFECTS[part].param_names}
    return _name_values(text, "--effect-params", known,
                        lambda k: f"{k!r} is no parameter of the effects made ({', '.join(effects)}); "
                                  f"theirs: {', '.join(sorted(known)) or 'none'}")


def _base_params(text):
    """``--base-params`` as {name: value} for E, nu and density (the object's base material)."""
    return _name_values(text, "--base-params", ("E", "nu", "density"),
                        lambda k: f"{k!r} is not one of E, nu or density")


def _dx_arg(text: str):
    """``--dx``: a cell in metres, or "auto" (None: the doctor's own choice)."""
    if text == "auto":
        return None
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not v > 0.0:
        raise argparse.ArgumentTypeError(f"--dx must be a positive cell size in m or 'auto', got {text!r}")
    return v


def make(args):
    from empm_gym.identification.data import trimmed_body, view_jackknife_bodies
    from empm_gym.identification.doctor import DEFAULT_DX, load_for_doctor
    from empm_gym.perception.scripts import SCRIPTS
    from empm_gym.perception.synth import SPRINGMASS_EFFECTS, effect_material, effect_signature, synthesize
    from empm_gym.sim.effects import EFFECTS

    sm = args.simulator == "springmass"
    effects = (["none", *(SPRINGMASS_EFFECTS if sm else EFFECTS)] if args.effects == "all" else
               args.effects.split(","))
    for effect in effects:  # two effects at once: "plasticity+table_friction"
        parts = effect.split("+")
        bad = [e for e in parts if e not in EFFECTS and not (e == "none" and len(parts) == 1)]
        if bad or len(parts) > 2 or len(set(parts)) < len(parts):
            raise SystemExit(f"--effects: {effect!r} is not none, an effect or two different effects joined by '+' "
                             f"(effects: {', '.join(EFFECTS)})")
        if len(parts) == 2 and (args.vary_physics or sm):
            raise SystemExit(f"--effects {effect}: two effects at once are made without --vary-physics, by the MPM")
    refused = sorted(set(effects) - {"none", *SPRINGMASS_EFFECTS}) if sm else []
    if refused:
        raise SystemExit(f"--simulator springmass makes only none, {', '.join(SPRINGMASS_EFFECTS)}; got "
                         f"{', '.join(refused)}")
    sim_kw = {"simulator": "springmass"} if sm else {}
    params = _effect_params(args.effect_params, effects)
    base = _base_params(args.base_params)
    out = Path(args.problems) if args.problems else Path(args.make) / "problems"
    out.mkdir(parents=True, exist_ok=True)
    only = set(args.only_scripts.split(",")) if args.only_scripts else None
    # the synthesiser's grid: the doctor's (--dx) unless --synth-dx gives another, as another simulator's would be
    synth_dx = (args.dx or DEFAULT_DX) if args.synth_dx is None else args.synth_dx
    every_on = args.every_effect_on.split(",") if args.every_effect_on else None
    unknown = sorted((only or set()) - set(SCRIPTS)) or sorted(set(every_on or ()) - set(SCRIPTS))
    if unknown:
        raise SystemExit(f"--only-scripts / --every-effect-on: unknown script(s) {unknown}; known: {', '.join(SCRIPTS)}")
    # a rig with a real one's calibration and depth errors (the recording only; the signatures are the physics')
    # and a 2D tracker's and a segmenter's errors
    sensor_kw = dict(calibration_error=tuple(args.calibration_error), depth_bias=args.depth_bias,
                     track_error=tuple(args.track_error), mask_error_px=args.mask_error)
    sensor_suffix = ("" if not (any(args.calibration_error) or args.depth_bias) else
                     f"-cal{1e3 * args.calibration_error[0]:g}mm{args.calibration_error[1]:g}deg"
                     f"-bias{100 * args.depth_bias:g}pc")
    if any(args.track_error) or args.mask_error:
        sensor_suffix += (f"-trk{args.track_error[0]:g}px{args.track_error[1]:g}-{100 * args.track_error[2]:g}pc"
                          f"-mask{args.mask_error}")
    for effect in effects:
        parts = effect.split("+")
        scripts = (list(dict.fromkeys([NATURAL[effect], second_script(args.object, effect), FIRST_OTHER[effect]]))
                   if len(parts) == 1 else list(dict.fromkeys(NATURAL[e] for e in parts)))  # each one's natural
        scripts = scripts[: args.scripts]
        if effect == "none":
            scripts = list(SCRIPTS)  # an invented effect may hide on any script: none runs on all of them
        if only:
            scripts = [s for s in scripts if s in only]
        if every_on:
            scripts = every_on
        for script in scripts:
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                eparams = {k: v for k, v in params.items()
                           if effect != "none" and any(k in EFFECTS[e].param_names for e in parts)}
                name = (("sm_" if sm else "") + ("v_" if args.vary_physics else "")
                        + f"{args.object}-{script}-{seed}-{effect}"
                        + "".join(f"-{k}{v:g}" for k, v in {**base, **eparams}.items())
                        + sensor_suffix)
                seed_base, seed_kw = base, sim_kw
                if args.vary_physics:  # this seed's material and discretisation (its name keeps the flags' values)
                    seed_base, eparams, drawn_kw = varied_physics(seed, args.object, effect, base, eparams)
                    seed_kw = {**sim_kw, **drawn_kw}
                rec = Path(args.make) / name
                t0 = time.perf_counter()
                if (out / f"{name}.pkl").exists() and args.keep_existing:
                    with open(out / f"{name}.pkl", "rb") as f:
                        prob = pickle.load(f)
                    changed = False
                    if args.reload and rec.exists():
                        # the loader changed: the scene and observations rebuilt from the recording as made
                        scene, obs, _, _, notes = load_for_doctor(rec, dx=args.dx, particles_per_cell=args.ppc,
                                                                  progress=False, trim_to_surface=args.trim_bodies)
                        prob.update(scene=scene, obs=_subsample(obs, seed, args.max_points), body_notes=notes,
                                    trim_to_surface=args.trim_bodies)
                        if "view_bodies" in prob or args.view_bodies:
                            prob["view_bodies"] = view_jackknife_bodies(rec, scene, particles_per_cell=args.ppc,
                                                                        trim_to_surface=args.trim_bodies)
                        if "trimmed_body" in prob or args.trimmed_body:
                            prob["trimmed_body"] = trimmed_body(rec, scene, particles_per_cell=args.ppc)
                        changed = True
                    if "signature_m" not in prob:
                        prob["signature_m"] = effect_signature(args.object, script, effect, frames=args.frames, seed=seed,
                                                               effect_params=eparams or None, base_params=seed_base,
                                                               dx=synth_dx, **seed_kw)
                        changed = True
                    if args.trimmed_body and "trimmed_body" not in prob and rec.exists():
                        prob["trimmed_body"] = trimmed_body(rec, prob["scene"], particles_per_cell=args.ppc)
                        changed = True
                    if args.view_bodies and "view_bodies" not in prob and rec.exists():
                        prob["view_bodies"] = view_jackknife_bodies(rec, prob["scene"], particles_per_cell=args.ppc)
                        changed = True
                    if changed:
                        _write_problem(out / f"{name}.pkl", prob)
                    print(f"{name}: kept, held-out signature {1e3 * prob['signature_m']:.2f} mm", flush=True)
                    continue
                if len(parts) == 2:  # the first effect in the material, the second added by the synthesiser
                    first = effect_material(args.object, parts[0], _params_of(parts[0], eparams), **seed_base)[0]
                    kw = dict(effect=parts[1], material=first, effect_params=_params_of(parts[1], eparams))
                else:
                    kw = dict(effect=effect, effect_params=eparams or None, **seed_base)
                synthesize(rec, args.object, script=script, **kw, frames=args.frames, cameras=args.cameras,
                           dx=synth_dx, width=args.width, height=args.height, seed=seed, overwrite=True,
                           progress=False, tangent_splats=args.tangent_splats, **seed_kw, **sensor_kw)
                gt = json.loads((rec / "ground_truth.json").read_text())
                truth = [e["name"] for e in gt["effects"]]
                try:
                    scene, obs, _, _, notes = load_for_doctor(rec, dx=args.dx, particles_per_cell=args.ppc,
                                                              progress=False, trim_to_surface=args.trim_bodies)
                except ValueError as e:  # e.g. squeeze-ring's plate hides a rope from every camera
                    print(f"{name}: skipped, the recording cannot be loaded: {e}", flush=True)
                    continue
                obs = _subsample(obs, seed, args.max_points)
                prob = {"scene": scene, "obs": obs, "truth": "+".join(truth) or "none", "script": script,
                        "object": args.object, "seed": seed, "truth_params": eparams, "body_notes": notes,
                        "base_params": seed_base,
                        "synth_dx": synth_dx, "trim_to_surface": args.trim_bodies, "simulator": args.simulator,
                        "parted": gt.get("parted"),
                        "synth_kw": {k: v for k, v in seed_kw.items() if k in ("grid_offset", "jitter")},
                        "sensor_errors": gt.get("sensor_errors") if sensor_suffix else None,
                        **({"view_bodies": view_jackknife_bodies(rec, scene, particles_per_cell=args.ppc,
                                                                 trim_to_surface=args.trim_bodies)}
                           if args.view_bodies else {}),
                        **({"trimmed_body": trimmed_body(rec, scene, particles_per_cell=args.ppc)}
                           if args.trimmed_body else {}),
                        "signature_m": None if len(parts) == 2 else effect_signature(
                            args.object, script, effect, frames=args.frames, seed=seed, effect_params=eparams or None,
                            base_params=seed_base, dx=synth_dx, **seed_kw),
                        # two effects: how much each shows on top of the other (what a second round can see)
                        **({"signatures": pair_signatures(args.object, script, parts, eparams, seed_base,
                                                          frames=args.frames, seed=seed, dx=synth_dx, **seed_kw)}
                           if len(parts) == 2 else {})}
                _write_problem(out / f"{name}.pkl", prob)
                print(f"{name}: {len(scene.particles)} particles, {obs.num_frames} frames "
                      f"({time.perf_counter() - t0:.1f} s)", flush=True)
    return out


def pair_signatures(obj: str, script: str, parts, eparams: dict, base: dict, **kwargs) -> dict:
    """``{effect: signature [m]}`` of each of two effects on top of the other (:func:`effect_signature` with the
    other effect in the base material): what a recording with both shows of the one a first round did not name."""
    from empm_gym.perception.synth import effect_material, effect_signature

    return {e: effect_signature(obj, script, e, effect_params=_params_of(e, eparams), material=effect_material(
                obj, other, _params_of(other, eparams), **base)[0], **kwargs)
            for e, other in (parts, parts[::-1])}


def screen_pairs(obj: str, script: str, effects, eparams: dict, base: dict, **kwargs) -> dict:
    """What every effect of ``effects`` and every pair of them shows held out on ``obj`` run through ``script``,
    to choose two-effect recordings where both show before making them (``--screen-pairs``): ``{"single":
    {effect: signature [m]}, "pairs": {(a, b): {a: a's signature on top of b, b: b's on top of a}}}``, each as
    :func:`pair_signatures` measures it (:func:`~empm_gym.perception.synth.heldout_difference` between the
    object's simulations), from one simulation per effect set: 1 + n + n (n - 1) / 2 of them."""
    from itertools import combinations

    from empm_gym.perception.synth import effect_material, heldout_difference, simulate

    def run(parts):
        mat = None
        for e in parts or ("none",):  # each effect added on top of the ones before it, as --make's pairs are
            mat = effect_material(obj, e, _params_of(e, eparams) if e != "none" else None, base=mat, **base)[0]
        return simulate(obj, mat, script=script, **kwargs)["particles"]

    sims = {(): run(())}
    for e in effects:
        sims[(e,)] = run((e,))
    for a, b in combinations(effects, 2):
        sims[(a, b)] = run((a, b))
    return {"single": {e: heldout_difference(sims[()], sims[(e,)]) for e in effects},
            "pairs": {(a, b): {a: heldout_difference(sims[(b,)], sims[(a, b)]),
                               b: heldout_difference(sims[(a,)], sims[(a, b)])}
                      for a, b in combinations(effects, 2)}}


def screen(args, p) -> None:
    """``--screen-pairs SCRIPTS``: :func:`screen_pairs`' table for each script (``p``: the parser, for errors)."""
    from empm_gym.identification.doctor import DEFAULT_DX
    from empm_gym.perception.scripts import SCRIPTS
    from empm_gym.sim.effects import EFFECTS

    effects = list(EFFECTS) if args.effects == "all" else [e for e in args.effects.split(",") if e != "none"]
    if any(e not in EFFECTS for e in effects) or len(effects) < 2:
        p.error(f"--screen-pairs pairs two or more effects of {', '.join(EFFECTS)} (--effects, comma-separated); "
                f"got {args.effects!r}")
    scripts = args.screen_pairs.split(",")
    unknown = sorted(set(scripts) - set(SCRIPTS))
    if unknown:
        p.error(f"--screen-pairs: unknown script(s) {unknown}; known: {', '.join(SCRIPTS)}")
    eparams, base = _effect_params(args.effect_params, effects), _base_params(args.base_params)
    dx = (args.dx or DEFAULT_DX) if args.synth_dx is None else args.synth_dx
    for script in scripts:
        print_screen(args.object, script, screen_pairs(args.object, script, effects, eparams, base,
                                                       frames=args.frames, dx=dx))


def print_screen(obj: str, script: str, screen: dict) -> None:
    """:func:`screen_pairs`' table: each effect alone, then each pair with what each shows on top of the other,
    the pairs where both reach EXPRESSED_M marked."""
    mm = lambda v: f"{1e3 * v:7.2f}"  # noqa: E731
    print(f"\n=== {obj} {script}: held-out signature [mm] (both: each shows {1e3 * EXPRESSED_M:g} mm or more on top of "
          f"the other)")
    for e, v in screen["single"].items():
        print(f"  {e:48s} alone {mm(v)}")
    for (a, b), v in screen["pairs"].items():
        both = min(v.values()) >= EXPRESSED_M
        print(f"  {a + '+' + b:48s} {a} {mm(v[a])}, {b} {mm(v[b])}" + ("  both" if both else ""))


def _params_of(effect: str, eparams: dict) -> Optional[dict]:
    """The entries of ``eparams`` that are ``effect``'s parameters (None: none of them)."""
    from empm_gym.sim.effects import EFFECTS

    return {k: v for k, v in eparams.items() if k in EFFECTS[effect].param_names} or None


def _subsample(obs, seed: int, max_points: int):
    """``obs`` with at most ``max_points`` observed points per frame (a random choice seeded by ``seed``): what the
    doctor's loss uses anyway."""
    rng = np.random.default_rng(seed)
    obs.points = [p if len(p) <= max_points else p[rng.choice(len(p), max_points, replace=False)] for p in obs.points]
    return obs


def diagnose_all(problems: Path, args):
    import dataclasses

    from empm_gym.identification.doctor import DoctorConfig, diagnose

    cfg = DoctorConfig(base_iters=args.iters, candidate_iters=args.iters, popsize=args.popsize, variants=args.variants,
                       robust_verdict=not args.no_robust, deterministic=args.deterministic, rounds=args.rounds)
    rows = []
    k, n = (int(v) for v in args.shard.split("/"))
    paths = sorted(Path(problems).glob("*.pkl"))[k::n]
    for path in paths:
        if args.dump and (Path(args.dump) / f"{path.stem}.json").exists():
            continue  # diagnosed by an earlier (interrupted) run
        with open(path, "rb") as f:
            prob = pickle.load(f)
        scene = dataclasses.replace(prob["scene"], device=args.device)
        t0 = time.perf_counter()
        others = [(label, None if sc is None else dataclasses.replace(sc, device=args.device))
                  for label, sc in prob.get("view_bodies", ())] if args.view_bodies else []
        if args.trimmed_body:
            if "trimmed_body" not in prob:
                raise SystemExit(f"{path}: --trimmed-body, but the problem holds no trimmed body (make it with "
                                 f"--make ... --keep-existing --trimmed-body while the recording is there)")
            label, sc = prob["trimmed_body"]
            others.append((label, None if sc is None else dataclasses.replace(sc, device=args.device), "trimmed"))
        res = diagnose(scene, prob["obs"], None, config=cfg, progress=False, other_bodies=others,
                       body_notes=prob.get("body_notes", ()))
        wall = time.perf_counter() - t0
        if args.dump:
            from empm_gym.identification.doctor.core import _jsonable

            Path(args.dump).mkdir(parents=True, exist_ok=True)
            (Path(args.dump) / f"{path.stem}.json").write_text(json.dumps(_jsonable(
                {**res, "recording": path.stem, "truth": prob["truth"], "script": prob["script"],
                 "signature_m": prob.get("signature_m"), "parted": prob.get("parted"),
                 **({"signatures": prob["signatures"]} if "signatures" in prob else {}),
                 "wall_s": wall})))
        truth, verdict = prob["truth"], res["effect"]
        row = _row(res, truth, path.stem, prob["script"], prob.get("signature_m"), wall, prob.get("parted"))
        row["intervals"] = interval_check(res, prob, problem_object(path, prob))
        if "signatures" in prob:
            row["signatures"] = prob["signatures"]
        red = row["reduction"]
        rows.append(row)
        if args.jsonl:
            with open(args.jsonl, "a") as f:
                f.write(json.dumps(row) + "\n")
        sig = float("nan") if row["signature_m"] is None else 1e3 * row["signature_m"]
        print(f"{path.stem:48s} truth {truth:24s} (signature {sig:5.2f} mm) verdict {verdict:24s} "
              f"conf {row['confidence']:.2f} held-out Chamfer reduction (true effect) {100 * red:6.1f} %  "
              f"{wall:6.1f} s" + (f"  effects named in {args.rounds} rounds: {' + '.join(row['effects']) or 'none'}"
                                  if args.rounds > 1 else ""), flush=True)
    summarise(rows)


#: The density the doctor assumes (its base material's): from motion alone it determines E, a yield stress and a
#: viscosity only as ratios to the density, so the truth is compared at this density (:func:`interval_check`).
DOCTOR_DENSITY = 1000.0


def interval_check(res: dict, prob: dict, obj: Optional[str]) -> list:
    """The chosen model's intervals (``doctor.json``'s ``uncertainty``, :attr:`DoctorConfig.intervals`) against the
    truth, which the benchmark alone reads (the problem's object, effect and parameters): one entry per parameter,
    ``{param, fit, interval, determined, truth, covered}`` (and one per combination of two correlated values that
    the doctor reports, ``yield_stress/E`` say), where the verdict is the true model (the named effect
    is the recording's, or both are ``none``); [] elsewhere, for two effects, without intervals and where the
    object ``obj`` (:func:`problem_object`) is unknown. E, a yield
    stress and a viscosity are compared at the doctor's density (:data:`DOCTOR_DENSITY`); a stiffness field's
    slope is not compared (its axis is the reconstructed body's, not the truth's). A confident wrong value is
    ``determined`` and not ``covered``."""
    from empm_gym.identification.doctor.core import named_candidate
    from empm_gym.identification.uncertainty import DENSITY_SCALED
    from empm_gym.perception.synth import effect_material

    unc, truth = res.get("uncertainty") or {}, prob["truth"]
    if not unc or "+" in truth or res.get("effect") != truth or obj is None:
        return []
    mat = effect_material(obj, truth, prob.get("truth_params") or None, **(prob.get("base_params") or {}))[0]
    fit = (named_candidate(res) or res["base"])["params"]

    def true(k):
        if k.startswith("stiffness_slope"):
            return None
        t = float(mat.E if k == "E" else mat.get(k))
        return t * DOCTOR_DENSITY / float(mat.density) if k in DENSITY_SCALED else t

    combos = [(name, c) for name, c in ((res.get("identifiability") or {}).get("combinations") or {}).items()
              if "exponent" in c]  # two correlated values' combination (uncertainty.pair_combination)
    out = []
    for k, u, f, t in ([(k, u, fit.get(k), true(k)) for k, u in unc.items()]
                       + [(name, c, c["value"], None if None in (true(c["of"][0]), true(c["of"][1]))
                           else true(c["of"][1]) * true(c["of"][0]) ** c["exponent"]) for name, c in combos]):
        lo, hi = (float("inf") if v is None else float(v) for v in u["interval"])
        lo = 0.0 if u["interval"][0] is None else lo
        out.append({"param": k, "fit": f, "interval": u["interval"], "determined": u["determined"],
                    "truth": t, "covered": None if t is None else bool(lo <= t <= hi)})
    return out


def _intervals_summary(rows) -> None:
    """How the chosen model's intervals (:func:`interval_check`) fare against the truth: the values the recordings
    determine that the interval covers, those it misses (a confident wrong value), and those said not determined."""
    checks = [c for r in rows for c in r.get("intervals") or () if c["truth"] is not None]
    if not checks:
        return
    det = [c for c in checks if c["determined"]]
    missed = [(r["recording"], c) for r in rows for c in r.get("intervals") or ()
              if c["truth"] is not None and c["determined"] and not c["covered"]]
    print(f"\nthe chosen model's 95 % intervals against the truth (where the verdict is the true model): {len(checks)} "
          f"values; determined {len(det)}, of them covered {sum(c['covered'] for c in det)}; not determined "
          f"{len(checks) - len(det)}, of them covered {sum(c['covered'] for c in checks if not c['determined'])}")
    for name, c in missed:
        print(f"  determined but missed: {name} {c['param']} = {c['fit']:.4g}, interval {c['interval']}, truth "
              f"{c['truth']:.4g}")


def _row(res: dict, truth: str, name: str, script: str, signature_m, wall_s: float, parted=None) -> dict:
    """One result row of a doctor result (``diagnose``'s return value or a ``--dump`` line); ``parted``: where the
    synthesiser's body came apart (ground_truth.json's ``parted``), None where it stayed whole or is unknown."""
    from empm_gym.identification.doctor.core import not_ruled_out, select_verdict

    red = c_true = c_base = l_base = float("nan")
    variants = res.get("variants") or {}
    before_trim = res["effect"]
    trim_checked = any("trimmed" in rec for rec in variants.get("candidates", {}).values())
    if trim_checked:
        # the verdict without the check on the body trimmed to the measured surface (the other rules as they are)
        untrimmed = {**variants, "candidates": {n: {k: v for k, v in rec.items() if k != "trimmed"}
                                                for n, rec in variants["candidates"].items()}}
        before_trim = select_verdict(res["candidates"], untrimmed)[0] or "none"
    if res.get("candidates"):
        c_base, l_base = res["base"]["heldout"]["chamfer_m"], res["base"]["heldout"]["loss"]
    if truth != "none" and "+" not in truth and res.get("candidates"):
        c_true = next(c for c in res["candidates"] if c["effect"] == truth)["heldout"]["chamfer_m"]
        red = 1.0 - c_true / c_base
    # the named effect's check against its own signature (doctor.json's evidence; a slim --dump line keeps it at
    # the top level); None where the verdict is none or the result predates the check (session 31)
    sig = (res.get("evidence") or {}).get("signature_check", res.get("signature_check")) or {}
    return {"recording": name, "script": script, "truth": truth, "verdict": res["effect"],
            "confidence": res.get("confidence", 0.0), "reduction": red, "base_chamfer_m": c_base,
            "true_effect_chamfer_m": c_true, "base_loss": l_base,
            "before_variants": res.get("effect_before_variants", res["effect"]), "signature_m": signature_m,
            "signature_doubted": sig.get("doubted"), "wall_s": wall_s, "stage_wall_s": res.get("stage_wall_s"),
            "not_ruled_out": [e["effect"] for e in not_ruled_out(res.get("candidates") or [], res["effect"])],
            "parted": parted, "clock_change": (res.get("clock") or {}).get("change"), "before_trim": before_trim,
            "trim_checked": trim_checked, **_rounds_columns(res, c_base),
            **({"signatures": res["signatures"]} if res.get("signatures") else {})}


def _rounds_columns(res: dict, c_base: float) -> dict:
    """A diagnosis in rounds (``res["rounds"]``, :attr:`DoctorConfig.rounds`): the effects named, each round's
    verdict and confidence, and the held-out Chamfer of the last model named (round 1's base model where none was);
    {} for one round."""
    from empm_gym.identification.doctor.core import named_candidate

    if "rounds" not in res:
        return {}
    named = named_candidate(res)
    final = c_base if named is None else named["heldout"]["chamfer_m"]
    for r in res["rounds"]:
        if r["effect"] != "none" and r.get("effect_heldout_chamfer_m") is not None:
            final = r["effect_heldout_chamfer_m"]
    return {"effects": list(res.get("effects") or []),
            "round_verdicts": [(res["effect"], res.get("confidence"))] + [(r["effect"], r["confidence"])
                                                                           for r in res["rounds"]],
            "final_chamfer_m": final}


def summarise_rounds(rows) -> None:
    """The table of diagnoses in rounds: per recording its effects and those named round by round; for the
    recordings with two effects how often both were named, for the others how often a further effect was named on
    top of the right first verdict (an effect invented by a later round)."""
    rows = [r for r in rows if "effects" in r]
    if not rows:
        return
    print(f"\n=== diagnoses in rounds ({len(rows)} recordings)")
    for r in rows:
        truth = [] if r["truth"] == "none" else r["truth"].split("+")
        verdicts = ", ".join(f"{e} {c:.2f}" if c is not None else f"{e} (rescored)" for e, c in r["round_verdicts"])
        print(f"  {r['recording']:48s} truth {' + '.join(truth) or 'none':38s} rounds: {verdicts:48s} held-out "
              f"Chamfer {1e3 * r['base_chamfer_m']:.2f} -> {1e3 * r['final_chamfer_m']:.2f} mm")
    two = [r for r in rows if "+" in r["truth"]]
    if two:
        both = sum(set(r["effects"]) == set(r["truth"].split("+")) for r in two)
        first = sum(bool(r["effects"]) and r["effects"][0] in r["truth"].split("+") for r in two)
        wrong = sum(any(e not in r["truth"].split("+") for e in r["effects"]) for r in two)
        red = [1.0 - r["final_chamfer_m"] / r["base_chamfer_m"] for r in two]
        print(f"two effects: both named {both} of {len(two)}; the first verdict one of them {first}; an effect named "
              f"that the recording lacks {wrong}; median held-out Chamfer reduction of the last model named "
              f"{_median_pct(red)}")
        # the effect the first round did not name, and how much it shows on top of the one it named
        rest = [(r, next(e for e in r["truth"].split("+") if e != r["effects"][0])) for r in two
                if r.get("signatures") and r["effects"] and r["effects"][0] in r["truth"].split("+")]
        shown = [(r, e) for r, e in rest if r["signatures"][e] >= EXPRESSED_M]
        if rest:
            print(f"  the other effect, where it shows by {1e3 * EXPRESSED_M:g} mm or more held out on top of the first: "
                  f"named {sum(e in r['effects'] for r, e in shown)} of {len(shown)}; where it shows less: named "
                  f"{sum(e in r['effects'] for r, e in rest if (r, e) not in shown)} of {len(rest) - len(shown)}")
    one = [r for r in rows if "+" not in r["truth"]]
    if one:
        right = [r for r in one if (r["effects"][:1] or ["none"])[0] == r["truth"]]
        extra = [r["recording"] for r in right if len(r["effects"]) > (r["truth"] != "none")]
        print(f"one effect or none: the first verdict right on {len(right)} of {len(one)}; of those, a further effect "
              f"named by a later round on {len(extra)}" + (f" ({', '.join(extra)})" if extra else ""))


def _write_problem(path: Path, prob: dict) -> None:
    """Pickle ``prob`` to ``path`` whole or not at all (a run stopped while writing leaves no truncated problem
    that ``--keep-existing`` would then fail to read)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        pickle.dump(prob, f)
    tmp.replace(path)


def rescore(paths):
    """Rows of ``--dump`` files with the verdict taken again by the doctor's rule
    (:func:`empm_gym.identification.doctor.core.select_verdict`) from the fits and variant tests they hold: a
    dump written by an earlier version of the rule (or with ``--no-robust``) scores as the current doctor would
    on the same fits. A recording found in several files is scored from the last of them (a run of a few
    recordings again, given after the run it completes)."""
    from empm_gym.identification.doctor import DoctorConfig
    from empm_gym.identification.doctor.core import (SIGNATURE_FEATURES, _friction_equivalent, first_places,
                                                     select_verdict, signature_contradicts, split_verdict,
                                                     toward_absence)
    from empm_gym.sim.effects import PARAMETERS

    factor = DoctorConfig().friction_equivalence

    def vanishing(t, box=None):
        """A fit or variant test with its flag taken again by the current rule (:func:`toward_absence`) from its
        fitted values and its candidate's search box (``box``; dumps older than session 53 hold none: the
        registry's, where the side an effect vanishes on is never capped)."""
        ps = t.get("params", {})
        box = {k: tuple(v) for k, v in (box or t.get("search_box") or {}).items()}
        return {**t, "toward_absence": toward_absence(
            ps, {k: box.get(k, PARAMETERS[k].search) for k in ps if k in PARAMETERS})}

    rows = {}
    for path in paths:
        for line in Path(path).read_text().splitlines():
            if not line.strip():
                continue
            res = json.loads(line)
            if res.get("candidates"):
                # dumps older than the friction rule (session 25) lack its flag: it is taken from the fitted values
                base_mu = res["base"].get("table_friction", 0.5)
                cands = [c if "equivalent_to_base" in c else
                         {**c, "equivalent_to_base": _friction_equivalent(c.get("params", {}).get("friction"), base_mu,
                                                                         factor)} for c in res["candidates"]]
                # the fits that end where their effect vanishes, by the current rule (dumps older than session 53
                # lack the flag)
                cands = [vanishing(c) for c in cands]
                # dumps older than the signature veto (session 44) hold the check for their verdict alone: that
                # candidate is marked as the doctor now marks every significant one (older than session 40, the
                # check's "unsupported", a discrepancy under the depth noise, is taken from the values it holds)
                sc = (res.get("evidence") or {}).get("signature_check", res.get("signature_check")) or {}
                if sc and not any("contradicted_by_signature" in c for c in cands):
                    d0, noise = sc.get("discrepancy_base"), res.get("noise_sigma_m")
                    unsupported = sc.get("unsupported", sc.get("unit") == "m" and d0 is not None
                                         and noise is not None and d0 < noise)
                    trusted = sc.get("trusted", SIGNATURE_FEATURES.get(res.get("effect"), (0, 0, False))[2])
                    contra = bool(trusted and sc.get("explained") is False and not unsupported)
                    cands = [{**c, "contradicted_by_signature": contra and c["effect"] == res.get("effect")}
                             for c in cands]
                # since then every significant candidate holds its own check: its veto is taken again by the
                # current rule (session 61: an overshoot within the noise is none)
                cands = [{**c, "contradicted_by_signature": signature_contradicts(c["signature_check"])}
                         if c.get("signature_check") and "contradicted_by_signature" in c else c for c in cands]
                variants = res.get("variants")
                if variants and "base_E" not in variants:  # dumps older than session 28: the base fit's E
                    variants = {**variants, "base_E": res["base"]["params"]["E"]}
                if variants and variants.get("candidates"):  # and the variants' refits that end where it vanishes
                    boxes = {c["effect"]: c.get("search_box") for c in cands}
                    variants = {**variants, "candidates": {
                        name: {**rec, "tests": [vanishing(t, boxes.get(name)) for t in rec.get("tests", [])],
                               **({"trimmed": vanishing(rec["trimmed"], boxes.get(name))} if rec.get("trimmed")
                                  else {})}
                        for name, rec in variants["candidates"].items()}}
                win, first, _ = select_verdict(cands, variants)
                share, _, n_disc, _ = first_places(cands, variants, win)
                if split_verdict(share, n_disc):
                    win = None  # no majority of the discretisations puts it first (session 72's rule)
                # a verdict that differs from the run's own has no confidence of its own: the run's was for another
                # verdict (the bootstrap, variant and first-place shares are the doctor's, taken on its fits)
                kept = (win or "none") == res.get("effect")
                res = {**res, "candidates": cands, "effect": win or "none", "effect_before_variants": first or "none",
                       "confidence": res.get("confidence", 0.0) if kept else None}
            rows.pop(res["recording"], None)
            rows[res["recording"]] = _row(res, res["truth"], res["recording"], res["script"], res.get("signature_m"),
                                          res["wall_s"], res.get("parted"))
    return list(rows.values())


def problem_object(path: Path, prob: dict) -> Optional[str]:
    """The object a problem was made of: its ``"object"`` (problems made since session 59), else the one its name
    begins with (``--make`` names them ``[v_]<object>-<script>-<seed>-<effect>``), else None."""
    if prob.get("object"):
        return prob["object"]
    from empm_gym.perception.synth import OBJECT_DEFAULTS

    m = re.match(rf"(?:v_)?({'|'.join(OBJECT_DEFAULTS)})-", Path(path).stem)
    return m.group(1) if m else None


def _effect_problems(problems: Path, obj: str, with_none: bool = False):
    """``(path, problem, true material)`` of every effect problem (``none`` left out unless ``with_none``) of
    object ``obj`` in ``problems``: the true material from the problem's ground-truth effect and parameters (the
    benchmark's own use of it). Problems of another object are passed over: the true material is the object's (its
    E, nu, density and effect defaults), and a dough problem given the rope's scored 1.54 mm held out where its own
    scores 2.30 (session 58's seed-20 floors, made with both objects' problems in one folder)."""
    from empm_gym.perception.synth import OBJECT_DEFAULTS, effect_material

    for path in sorted(Path(problems).glob("*.pkl")):
        with open(path, "rb") as f:
            prob = pickle.load(f)
        if prob["truth"] == "none" and not with_none:
            continue
        made_of = problem_object(path, prob)
        if made_of is None:
            raise SystemExit(f"{path.name} does not say which object it was made of (no 'object' in it, and its name "
                             f"does not begin with an object's name: {', '.join(f'{o}-' for o in OBJECT_DEFAULTS)})")
        if made_of != obj:
            continue
        mat, _ = effect_material(obj, prob["truth"], prob.get("truth_params") or None, **prob.get("base_params", {}))
        yield path, prob, mat


def _emit(row: dict, text: str, rows: list, jsonl):
    """Keep ``row``, print ``text`` beside its recording's name and append it to ``jsonl`` (if given)."""
    rows.append(row)
    print(f"{row['recording']:48s} {text}", flush=True)
    if jsonl:
        with open(jsonl, "a") as f:
            f.write(json.dumps(row) + "\n")


def floors(problems: Path, args):
    """The held-out Chamfer of the true material (``ground_truth``'s, read by the benchmark only) simulated on the
    doctor's own body and grid, scored as the doctor scores: what a perfect fit of the right model could reach.
    The reduction it gives over the base model bounds what the doctor's named effect can show: the rest of the
    gap is depth noise, the reconstructed body and the discretisation, which no effect removes."""
    import dataclasses

    from empm_gym.identification.doctor import DoctorConfig

    cfg = DoctorConfig()
    rows = []
    for path, prob, mat in _effect_problems(problems, args.object):
        sc = dataclasses.replace(prob["scene"], device=args.device, motion_margin=cfg.motion_margin)
        per, F, _ = _true_material_on(sc, prob["obs"], mat, cfg)
        row = {"recording": path.stem, "truth": prob["truth"], "floor_chamfer_m": float(np.mean(per["chamfer"][F:])),
               "floor_loss": float(np.mean(per["loss"][F:]))}
        text = f"true material's held-out Chamfer {1e3 * row['floor_chamfer_m']:.3f} mm"
        if getattr(args, "true_held", False):
            row.update(_true_held_floors(path, prob, mat, sc, cfg, args))
            text += (f", elastic {1e3 * row['elastic_chamfer_m']:.3f}; with the true part in the grippers "
                     f"({1e6 * row['held_volume_m3']:.1f} -> {1e6 * row['true_held_volume_m3']:.1f} cm^3) "
                     f"{1e3 * row['true_held_floor_chamfer_m']:.3f}, elastic {1e3 * row['true_held_elastic_chamfer_m']:.3f}")
        _emit(row, text, rows, args.jsonl)
    return rows


def _true_held_floors(path: Path, prob: dict, mat, scene, cfg, args) -> dict:
    """``--floor --true-held``: the elastic material at the true E (no effect) on the doctor's body, and the true
    and the elastic material on that body with what its closed grippers hold at frame 0 replaced by the
    synthesiser's own frame-0 particles there (:func:`_own_simulation`; the benchmark's use of ground truth). Where
    the two bodies' floors differ much, the recording turns on the prior that fills the grippers, which no camera
    sees into (:func:`empm_gym.perception.fusion.complete_occluded`)."""
    import dataclasses

    from empm_gym.perception.fusion import inside_end_effectors
    from empm_gym.perception.synth import effect_material

    own = _own_simulation(path, prob, mat, args, frames=2)  # frame 0 is all it takes
    X0, V0 = own["particles"][0], np.asarray(own["volumes"], np.float64) * np.ones(len(own["particles"][0]))
    x = np.asarray(scene.particles, np.float64)
    v = np.asarray(scene.volumes, np.float64) * np.ones(len(x))
    if len(scene.ee_configs):
        closed = np.asarray(scene.ee_grip[0]) == 1
        q = None if scene.ee_orientations is None else scene.ee_orientations[0]
        held = inside_end_effectors(x, scene.ee_configs, scene.ee_positions[0], q, select=closed)
        held_true = inside_end_effectors(X0, scene.ee_configs, scene.ee_positions[0], q, select=closed)
    else:
        held, held_true = np.zeros(len(x), bool), np.zeros(len(X0), bool)
    swapped = dataclasses.replace(scene, particles=np.concatenate([x[~held], X0[held_true]]),
                                  volumes=np.concatenate([v[~held], V0[held_true]]))
    elastic, _ = effect_material(args.object, "none", None, **prob.get("base_params", {}))
    out = {"held_volume_m3": float(v[held].sum()), "true_held_volume_m3": float(V0[held_true].sum())}
    for key, body, m in (("elastic_chamfer_m", scene, elastic), ("true_held_floor_chamfer_m", swapped, mat),
                         ("true_held_elastic_chamfer_m", swapped, elastic)):
        per, F, _ = _true_material_on(body, prob["obs"], m, cfg)
        out[key] = float(np.mean(per["chamfer"][F:]))
    return out


def _true_material_on(scene, obs, mat, cfg):
    """The true material ``mat`` simulated on ``scene`` (a body of the doctor's, its own clock) and scored as the
    doctor scores (``cfg``): ``(per-frame losses, first held-out frame, positions [T, N, 3])``."""
    from empm_gym.identification.doctor.core import _per_frame_losses, heldout_objective
    from empm_gym.identification.problem import _ForwardSim

    mu = mat.get("friction")
    sc = scene.with_material(mat, table_friction=mu)
    T = obs.num_frames if sc.num_frames is None else min(obs.num_frames, sc.num_frames)
    X, _, _ = _ForwardSim(sc, [mat], [mu]).run(T)
    return _per_frame_losses(heldout_objective(sc, obs, T, cfg), X[:, 0]), int(round(cfg.train_fraction * T)), X[:, 0]


def discretisations(problems: Path, args):
    """How much the discretisation alone moves what the true material scores on the doctor's body: every problem's
    true material (``none`` included; the benchmark's own use of ground truth) simulated on the doctor's body and on
    its first ``args.discretisations`` discretisation variants (the grid shifted by part of a cell and the particles
    moved to another lattice, :func:`~empm_gym.identification.doctor.core._variant_scene`, as the doctor's variants
    check makes them), each on the material's own clock, scored as the doctor scores. Where the held-out loss
    differs much between these equally valid discretisations of one body and one material, the held-out frames turn
    on how the model is discretised, and a candidate's gain on the doctor's body may be that body's draw."""
    import dataclasses

    from empm_gym.identification.doctor import DoctorConfig
    from empm_gym.identification.doctor.core import _variant_scene

    cfg = DoctorConfig()
    rows = []
    for path, prob, mat in _effect_problems(problems, args.object, with_none=True):
        body = dataclasses.replace(prob["scene"], device=args.device, motion_margin=cfg.motion_margin)
        losses, chamfers = [], []
        for k in range(-1, args.discretisations):
            per, F, X = _true_material_on(body if k < 0 else _variant_scene(body, k), prob["obs"], mat, cfg)
            if not np.all(np.isfinite(X)):
                raise SystemExit(f"{path.name}: the true material's simulation on discretisation {k + 1} is not "
                                 f"finite")
            losses.append(float(np.mean(per["loss"][F:])))
            chamfers.append(float(np.mean(per["chamfer"][F:])))
        row = {"recording": path.stem, "truth": prob["truth"], "heldout_loss": losses, "heldout_chamfer_m": chamfers,
               "spread": max(losses) / min(losses)}
        _emit(row, f"held-out loss on the doctor's body {losses[0]:.5f}, on its variants "
              + ", ".join(f"{v:.5f}" for v in losses[1:]) + f" ({row['spread']:.2f}x)", rows, args.jsonl)
    return rows


def _own_simulation(path: Path, prob: dict, mat, args, frames: Optional[int] = None) -> dict:
    """The synthesiser run again for the effect problem ``prob`` (read from ``path``): ``ground_truth``'s material
    ``mat``, the problem's script and seed, on the grid the recording was made on (the problem's ``synth_dx``, or
    ``args.synth_dx`` for problems made before session 38; its grid offset and particle jitter, ``--vary-physics``);
    :func:`~empm_gym.perception.synth.simulate`'s result,
    its particles in float64. Refused by name where the grid is unknown or disagrees, or where the run's frame-0
    body does not lie where the recording's frame-0 points were seen (another object or script)."""
    from scipy.spatial import cKDTree

    from empm_gym.perception.synth import simulate

    synth_dx = prob.get("synth_dx")
    if synth_dx is None and args.synth_dx is None:
        raise SystemExit(f"{path.name} does not say which grid its recording was made on (problems made before "
                         f"session 38): give it as --synth-dx")
    if synth_dx is not None and args.synth_dx is not None and abs(synth_dx - args.synth_dx) > 1e-12:
        raise SystemExit(f"{path.name} was made on a {synth_dx:g} m grid, not --synth-dx {args.synth_dx:g}")
    synth_dx = args.synth_dx if synth_dx is None else synth_dx
    obs = prob["obs"]
    out = simulate(args.object, mat, script=prob["script"], frames=frames or obs.num_frames, dx=synth_dx,
                   seed=prob["seed"], device=args.device, **prob.get("synth_kw", {}))
    out["particles"] = out["particles"].astype(np.float64)
    d0 = float(np.median(cKDTree(out["particles"][0]).query(obs.points[0])[0]))
    if d0 > synth_dx:
        raise SystemExit(f"{path.name}: the synthesiser's frame-0 body lies {1e3 * d0:.1f} mm (median) from the "
                         f"recording's frame-0 points: not the recording's simulation (--object {args.object}, "
                         f"--synth-dx {synth_dx:g}?)")
    return out


def oracles(problems: Path, args):
    """The held-out Chamfer of each effect recording's own simulation: the synthesiser run again (``ground_truth``'s
    material, the script and the seed, on the grid the recording was made on; :func:`_own_simulation`), its
    particles carrying the doctor's frame-0 observed points as the doctor's fits carry them, scored as the doctor
    scores. A perfect body and a perfect model: what is left is the depth noise of the frames compared and surface
    the cameras no longer see (and, with ``DoctorConfig.unseen_surface`` off, the surface seen later that frame 0
    did not see), which no model removes. The reduction it gives over the base model bounds what any model, on any
    body, can show on the recording (:func:`floors` bounds what the doctor's own body allows)."""
    import dataclasses

    from empm_gym.identification.doctor import DoctorConfig
    from empm_gym.identification.doctor.core import _per_frame_losses, heldout_objective

    cfg = DoctorConfig()
    rows = []
    for path, prob, mat in _effect_problems(problems, args.object):
        try:
            X = _own_simulation(path, prob, mat, args)["particles"]
        except SystemExit as e:
            raise SystemExit(f"--oracle: {e}") from None
        obs = prob["obs"]
        T = obs.num_frames
        sc = dataclasses.replace(prob["scene"], particles=X[0], volumes=float(np.mean(prob["scene"].volumes)))
        F = int(round(cfg.train_fraction * T))
        objective = heldout_objective(sc, obs, T, cfg)
        per = _per_frame_losses(objective, X)
        # the Chamfer's two halves: observed points far from the simulation are depth noise (and, with the doctor's
        # unseen_surface off, surface seen later but not at frame 0); carried points far from the observed ones,
        # surface hidden later
        P, U = objective.predicted_points(X), objective.unseen_points(X)
        row = {"recording": path.stem, "truth": prob["truth"], "unseen_surface": cfg.unseen_surface,
               "oracle_chamfer_m": float(np.mean(per["chamfer"][F:])),
               "oracle_loss": float(np.mean(per["loss"][F:])),
               **{f"oracle_{d}_m": float(np.mean(objective.chamfer(P, direction=d, unseen=U)[F:]))
                  for d in ("obs_to_pred", "pred_to_obs")}}
        _emit(row, f"its own simulation's held-out Chamfer {1e3 * row['oracle_chamfer_m']:.3f} mm", rows, args.jsonl)
    return rows


#: Offsets of the recording's grid that :func:`grid_offsets` tries by default, in cells along x, y, z.
GRID_OFFSETS = ((0.0, 0.0, 0.0), (0.2, 0.0, 0.0), (0.4, 0.0, 0.0), (0.6, 0.0, 0.0), (0.8, 0.0, 0.0),
                (0.0, 0.0, 0.4), (0.0, 0.0, 0.8), (0.5, 0.5, 0.5))


def _grid_offsets_arg(text: str):
    """``--grid-offsets`` entries ``X,Y,Z`` (cells, each in [0, 1)), separated by ``;``."""
    out = []
    for item in text.split(";"):
        parts = item.split(",")
        try:
            off = tuple(float(v) for v in parts)
        except ValueError:
            off = ()
        if len(off) != 3 or not all(0.0 <= v < 1.0 for v in off):
            raise argparse.ArgumentTypeError(f"--grid-offsets wants X,Y,Z in cells, each in [0, 1), entries "
                                             f"separated by ';'; got {item!r}")
        out.append(off)
    return tuple(out)


def grid_offsets(problems: Path, args):
    """How much of each effect recording is its grid's: the recording's own body and true material
    (:func:`_own_simulation`, the benchmark's own use of ground truth) simulated by the doctor's simulator on the
    recording's grid shifted by fractions of a cell (``args.grid_offsets``, :meth:`GridConfig.shifted`), scored as
    the doctor scores. Per offset: the held-out loss and Chamfer, the distance of the particles from the recording's
    own simulation (the median at the last frame, and the largest over all frames), and the pieces the body is in
    (:func:`~empm_gym.identification.doctor.features.count_pieces`): the first frame in more than one, and at the
    last frame. At offset 0 the doctor's simulator is the synthesiser's, particle for particle; an effect whose
    outcome changes with the offset (a tear that opens on one grid and not on another) is as much the
    discretisation's as the material's, and no fit on the doctor's own grid can be expected to reproduce it."""
    import dataclasses

    from empm_gym.identification.doctor import DoctorConfig
    from empm_gym.identification.doctor.core import _per_frame_losses, heldout_objective
    from empm_gym.identification.doctor.features import count_pieces
    from empm_gym.identification.problem import _ForwardSim

    cfg = DoctorConfig()
    rows = []
    for path, prob, mat in _effect_problems(problems, args.object):
        own = _own_simulation(path, prob, mat, args)
        X0, grid = own["particles"], own["grid"]
        obs = prob["obs"]
        T = obs.num_frames
        F = int(round(cfg.train_fraction * T))
        mu = mat.get("friction")
        own_pieces = [count_pieces(X0[t]) for t in range(T)]

        def parts_from(counts):  # the first frame in more than one piece (None: whole throughout)
            return next((t for t, n in enumerate(counts) if n > 1), None)

        for off in args.grid_offsets:
            sc = dataclasses.replace(prob["scene"], particles=X0[0], volumes=np.asarray(own["volumes"], np.float64),
                                     grid=grid.shifted(off), device=args.device).with_material(mat, table_friction=mu)
            X, _, _ = _ForwardSim(sc, [mat], [mu]).run(T)
            X = X[:, 0].astype(np.float64)
            if not np.all(np.isfinite(X)):
                raise SystemExit(f"{path.name}: the simulation on the grid offset by {off} cells is not finite")
            per = _per_frame_losses(heldout_objective(sc, obs, T, cfg), X)
            pieces = [count_pieces(X[t]) for t in range(T)]
            row = {"recording": path.stem, "truth": prob["truth"], "grid_offset_cells": list(off),
                   "heldout_loss": float(np.mean(per["loss"][F:])),
                   "heldout_chamfer_m": float(np.mean(per["chamfer"][F:])),
                   "max_from_own_m": float(np.max(np.linalg.norm(X - X0, axis=-1))),
                   "median_from_own_last_m": float(np.median(np.linalg.norm(X[-1] - X0[-1], axis=-1))),
                   "parts_from_frame": parts_from(pieces), "last_pieces": pieces[-1],
                   "own_parts_from_frame": parts_from(own_pieces), "own_last_pieces": own_pieces[-1]}
            parts = ("whole" if row["parts_from_frame"] is None else
                     f"parts from frame {row['parts_from_frame']}, {row['last_pieces']} piece(s) at the last")
            _emit(row, f"grid offset {off} cells: held-out loss {1e3 * row['heldout_loss']:.3f} mm; from its own "
                       f"simulation {1e3 * row['median_from_own_last_m']:.1f} mm (median, last frame), "
                       f"{1e3 * row['max_from_own_m']:.1f} mm at most; {parts}", rows, args.jsonl)
        mine = [r for r in rows if r["recording"] == path.stem]
        parted = sum(r["parts_from_frame"] is not None for r in mine)
        own_text = ("whole" if mine[0]["own_parts_from_frame"] is None
                    else f"parted from frame {mine[0]['own_parts_from_frame']}")
        print(f"{path.stem:48s} its own simulation {own_text}; parts on {parted} of {len(mine)} grid offsets; "
              f"held-out loss {1e3 * min(r['heldout_loss'] for r in mine):.3f} to "
              f"{1e3 * max(r['heldout_loss'] for r in mine):.3f} mm", flush=True)
    return rows


def _clock_damping(rows, penalty: Optional[float] = None) -> None:
    """How much the diagnoses' shared clock damped their base models (doctor.json's ``clock``, from session 58):
    the base model's held-out loss on its own clock against the shared one's, and the recordings where that
    exceeds ``penalty`` (what a candidate must gain, ``DoctorConfig.penalty_per_param`` by default; the doctor
    then notes it)."""
    from empm_gym.identification.doctor import DoctorConfig

    penalty = DoctorConfig().penalty_per_param if penalty is None else penalty
    rs = [r for r in rows if r.get("clock_change") is not None and np.isfinite(r["clock_change"])]
    if not rs:
        return
    big = [r for r in rs if abs(r["clock_change"]) > penalty]
    print(f"\nthe shared clock's damping (the base model on its own clock against the diagnosis's): {len(rs)} "
          f"recordings, median change of its held-out loss {100 * np.median([r['clock_change'] for r in rs]):+.1f} %; "
          f"beyond the {100 * penalty:.0f} % penalty on {len(big)}"
          + "".join(f"\n  {r['recording']:45s} {100 * r['clock_change']:+6.1f} %  verdict {r['verdict']}" for r in big))


def summarise(rows, floor_rows=()):
    """The tables of result rows: the benchmark's set (each effect on its natural and second script) first,
    then any other recordings (the first runs' second scripts) on their own. With ``floor_rows``
    (:func:`floors`), the reduction each effect recording could show at most, beside the one it shows. Rows of
    diagnoses in rounds (``--rounds``) are tallied once more in their own table (:func:`summarise_rounds`), the
    recordings with two effects only there."""
    in_rounds, rows = rows, [r for r in rows if "+" not in r["truth"]]
    if rows:
        _summarise_one(rows, floor_rows)
    summarise_rounds(in_rounds)


def _summarise_one(rows, floor_rows=()):
    bench = [r for r in rows if r["truth"] == "none" or r.get("script") in
             (NATURAL[r["truth"]], second_script(object_of(r["recording"]), r["truth"]))]
    rest = [r for r in rows if r not in bench]
    print(f"\n=== the benchmark: each effect on its natural and its second script, none on every script "
          f"({len(bench)} recordings)")
    _table(bench)
    floor = {r["recording"]: r["floor_chamfer_m"] for r in floor_rows if "floor_chamfer_m" in r}
    both = [r for r in bench if r["recording"] in floor and np.isfinite(r.get("base_chamfer_m", np.nan))]
    if both:
        print("\nheld-out Chamfer reduction with the true effect's fit, against the true material on the doctor's body "
              "(the most any fit on that body can show)")
        for eff in dict.fromkeys(r["truth"] for r in both):
            rs = [r for r in both if r["truth"] == eff]
            can = [1.0 - floor[r["recording"]] / r["base_chamfer_m"] for r in rs]
            print(f"  {eff:24s} {len(rs)} recordings: shown {100 * np.median([r['reduction'] for r in rs]):6.1f} %, "
                  f"possible {100 * np.median(can):6.1f} % (medians)")
        can = [1.0 - floor[r["recording"]] / r["base_chamfer_m"] for r in both]
        print(f"  all {len(both)}: shown {100 * np.median([r['reduction'] for r in both]):.1f} %, possible "
              f"{100 * np.median(can):.1f} %")
    _against_the_recordings_own_simulation(bench, floor_rows)
    _shown_on_the_body(bench, floor_rows)
    _clock_damping(bench)
    _intervals_summary(rows)
    if rest:
        print(f"\n=== other recordings: scripts besides each effect's two (the first runs' second scripts, the rope's "
              f"push-slide with viscosity; {len(rest)} recordings)")
        _table(rest)


def _against_the_recordings_own_simulation(rows, floor_rows):
    """The reductions beside what a perfect body and model could show (:func:`oracles`), and the share of the gap
    above that floor that the true effect's fit closes, (base - fit) / (base - own simulation): the held-out Chamfer
    never reaches zero, since the frames compared carry the depth noise; this says how much of what a model can
    remove the fit removed."""
    oracle = {r["recording"]: r["oracle_chamfer_m"] for r in floor_rows if "oracle_chamfer_m" in r}
    both = [r for r in rows if r["recording"] in oracle and np.isfinite(r.get("base_chamfer_m", np.nan))
            and np.isfinite(r.get("true_effect_chamfer_m", np.nan))]
    if not both:
        return
    print("\nagainst the recording's own simulation (the synthesiser's particles: a perfect body and model; what is "
          "left is the depth noise, the surface hidden later and, in rows scored without the unseen surface (before "
          "session 39), the surface frame 0 did not see): the most any model can show, and the share of the gap above "
          "it the fit closes")
    for eff in [*dict.fromkeys(r["truth"] for r in both), None]:
        rs = [r for r in both if eff is None or r["truth"] == eff]
        can = [1.0 - oracle[r["recording"]] / r["base_chamfer_m"] for r in rs]
        share = [(r["base_chamfer_m"] - r["true_effect_chamfer_m"]) / (r["base_chamfer_m"] - oracle[r["recording"]])
                 for r in rs if r["base_chamfer_m"] > oracle[r["recording"]]]
        shown = 100 * np.median([r["reduction"] for r in rs])
        base = 1e3 * np.median([r["base_chamfer_m"] for r in rs])
        print(f"  {eff or f'all {len(rs)}':24s} {len(rs)} recordings: shown {shown:6.1f} %, "
              f"possible {100 * np.median(can):6.1f} %, base model {base:.2f} mm "
              f"against its own simulation {1e3 * np.median([oracle[r['recording']] for r in rs]):.2f} mm; gap closed "
              f"{100 * np.median(share) if share else float('nan'):6.1f} % (medians)")
    halves = {r["recording"]: r for r in floor_rows if "oracle_obs_to_pred_m" in r}

    for obj in dict.fromkeys(object_of(r["recording"]) for r in both if r["recording"] in halves):
        hs = [halves[r["recording"]] for r in both if r["recording"] in halves and object_of(r["recording"]) == obj]
        unseen = sum(bool(h.get("unseen_surface")) for h in hs)
        to = ("the simulation (noise)" if unseen == len(hs) else "the carried ones (noise, and surface seen later but "
              f"not at frame 0{f'; {unseen} of them scored with the unseen surface' if unseen else ''})")
        print(f"  its two halves, {obj} ({len(hs)}): observed points to {to} "
              f"{1e3 * np.median([h['oracle_obs_to_pred_m'] for h in hs]):.2f} mm, carried to observed "
              f"{1e3 * np.median([h['oracle_pred_to_obs_m'] for h in hs]):.2f} mm "
              f"(noise, and surface hidden later) (medians)")


def _shown_on_the_body(rows, floor_rows):
    """Accuracy over the recordings whose effect the doctor's own body and grid can show: the true material
    (:func:`floors`: ground truth, the benchmark's own use of it), simulated on the doctor's body, scores a
    held-out loss below the base model's fit by more than the doctor's penalty for the effect's parameters.
    Where it does not, the recording shows its effect less than the body, the grid and the depth noise disturb it
    at this resolution: the true material (its E included) does no better than the elastic fit, and a candidate
    that refits E beside the effect can gain only by what the refit of E buys. ``none`` is then a defensible
    verdict; the table says which recordings those are, the accuracy over the others beside the full one."""
    from empm_gym.identification.doctor import DoctorConfig
    from empm_gym.identification.doctor.core import candidate_params

    loss = {r["recording"]: r["floor_loss"] for r in floor_rows if "floor_loss" in r}
    eff = [r for r in rows if r["truth"] != "none" and r["recording"] in loss and np.isfinite(r.get("base_loss", np.nan))]
    if not eff:
        return
    pen = DoctorConfig().penalty_per_param
    gain = {r["recording"]: 1.0 - loss[r["recording"]] / r["base_loss"] for r in eff}
    shows = [r for r in eff if gain[r["recording"]] > pen * len(candidate_params(r["truth"]))]
    none = [r for r in rows if r["truth"] == "none"]
    ok = [r["verdict"] == r["truth"] for r in shows + none]
    print(f"\nthe true material on the doctor's body against the base model's fit (held-out loss): {len(shows)} of "
          f"{len(eff)} effect recordings show their effect beyond the penalty; on them and the {len(none)} none: "
          f"accuracy {100 * np.mean(ok):.1f} % of {len(ok)}")
    for r in sorted(eff, key=lambda r: gain[r["recording"]]):
        if r not in shows:
            print(f"  does not show it: {r['recording']:40s} true material {100 * gain[r['recording']]:+6.1f} %, "
                  f"verdict {r['verdict']}")


CONFIDENCE_BINS = (0.0, 0.5, 0.9, 1.0)


def _by_confidence(rows, edges=CONFIDENCE_BINS):
    """``(low, high, [verdict right?, ...])`` for each confidence bin [low, high) (the last one closed): how far a
    user can trust the confidence the doctor reports, a bin at a time."""
    out = []
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        last = k == len(edges) - 2
        out.append((lo, hi, [r["verdict"] == r["truth"] for r in rows if r["confidence"] is not None
                             and (lo <= r["confidence"] < hi or (last and r["confidence"] == hi))]))
    return out


def _median_pct(values) -> str:
    """The median of ``values`` (fractions; NaNs left out) in per cent, or "n/a" when none is finite (a table of
    ``none`` recordings alone), without numpy's warning over an empty slice."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return f"{100 * np.median(v):.1f} %" if len(v) else "n/a"


def _table(rows):
    """Confusion matrix, accuracy, false effects on none, median reduction and wall time of result rows."""
    from empm_gym.sim.effects import EFFECTS

    if not rows:
        return

    names = ["none", *EFFECTS]
    full = rows
    conf = {t: {p: 0 for p in names} for t in names}
    for r in rows:
        conf[r["truth"]][r["verdict"]] += 1
    walls = [r["wall_s"] for r in rows]
    reductions = [r["reduction"] for r in rows if r["truth"] != "none"]
    natural = [r["truth"] == r["verdict"] for r in rows if r.get("script") == NATURAL[r["truth"]]]
    rows = [(r["recording"], r["truth"], r["verdict"]) for r in rows]
    n = len(rows)
    acc = np.mean([r[1] == r[2] for r in rows]) if n else float("nan")
    none_rows = [r for r in rows if r[1] == "none"]
    false_rate = np.mean([r[2] != "none" for r in none_rows]) if none_rows else float("nan")
    print("\nconfusion matrix (rows: truth, columns: verdict)")
    print(" " * 24 + "".join(f"{p[:10]:>11}" for p in names))
    for t in names:
        if sum(conf[t].values()):
            print(f"{t:24s}" + "".join(f"{conf[t][p]:>11d}" for p in names))
    print(f"\nrecordings {n}; naming accuracy {100 * acc:.1f} %; false effects on none {100 * false_rate:.1f} %; "
          f"median held-out Chamfer reduction with the true effect {_median_pct(reductions)}; "
          f"wall time per recording median {np.median(walls):.1f} s, max {np.max(walls):.1f} s")
    named = [r["reduction"] for r in full if r["truth"] != "none" and r["verdict"] == r["truth"]]
    if named:
        # what a user is shown when the doctor names the effect; a selection: the recordings that show their
        # effect are those named, so this is no stand-in for the median over every effect recording above
        print(f"where the true effect was named: median held-out Chamfer reduction {_median_pct(named)} of "
              f"{len(named)} (the recordings that show their effect; the benchmark's median is the one above)")
    if natural:
        print(f"on each effect's natural script only: accuracy {100 * np.mean(natural):.1f} % of {len(natural)}")
    unknown = sum(r["confidence"] is None for r in full)
    print("accuracy by the verdict's confidence: " + "; ".join(
        f"{lo:.1f}-{hi:.1f}: {sum(ok)} of {len(ok)} right" for lo, hi, ok in _by_confidence(full))
        + (f"; {unknown} rescored to another verdict than their run's, without a confidence" if unknown else ""))
    before = [(r["truth"], r["before_variants"]) for r in full if "before_variants" in r]
    if before:
        print(f"without the variants check: accuracy {100 * np.mean([t == v for t, v in before]):.1f} %, false effects "
              f"on none {sum(v != 'none' for t, v in before if t == 'none')} of {sum(t == 'none' for t, _ in before)}; "
              f"verdicts the check changed: {sum(r['before_variants'] != r['verdict'] for r in full if 'before_variants' in r)}")
    trimmed = [r for r in full if r.get("trim_checked")]
    if trimmed:
        print(f"checked on the body trimmed to the measured surface: {len(trimmed)} recordings; without that check: "
              f"accuracy {100 * np.mean([r['truth'] == r['before_trim'] for r in trimmed]):.1f} % (with it "
              f"{100 * np.mean([r['truth'] == r['verdict'] for r in trimmed]):.1f} %), false effects on none "
              f"{sum(r['before_trim'] != 'none' for r in trimmed if r['truth'] == 'none')} of "
              f"{sum(r['truth'] == 'none' for r in trimmed)}; verdicts it changed: "
              + (", ".join(f"{r['recording']} {r['before_trim']} -> {r['verdict']}" for r in trimmed
                           if r["before_trim"] != r["verdict"]) or "none"))
    checked = [r for r in full if r.get("signature_doubted") is not None]
    if checked:
        doubted = [r for r in checked if r["signature_doubted"]]
        print(f"checked against their signature: {len(checked)} named verdicts; doubted (the named effect's fit does "
              f"not bring its trusted feature closer): {len(doubted)}, of them right "
              f"{sum(r['verdict'] == r['truth'] for r in doubted)}; not doubted and wrong: "
              f"{sum(r['verdict'] != r['truth'] for r in checked if not r['signature_doubted'])}")
    # what a none could not exclude (doctor.json's not_ruled_out): on a missed effect, is the truth among them?
    nones = [r for r in full if r["verdict"] == "none" and r.get("not_ruled_out") is not None]
    if nones:
        missed = [r for r in nones if r["truth"] != "none"]
        right = [r for r in nones if r["truth"] == "none"]
        print(f"none verdicts and what they could not exclude: on {len(missed)} effect recordings called none, the "
              f"true effect is not ruled out on {sum(r['truth'] in r['not_ruled_out'] for r in missed)}; on "
              f"{len(right)} none recordings called none, some candidate is not ruled out on "
              f"{sum(bool(r['not_ruled_out']) for r in right)}")
    # against what each recording shows: an effect whose held-out signature is below EXPRESSED_M is not in the
    # data, and `none` is then a right verdict as well
    # and a body that the synthesiser tore without a fracture (ground_truth.json's parted) shows a fracture
    known = [r for r in full if r.get("signature_m") is not None]
    if known:
        shown = [r for r in known if r["truth"] == "none" or r["signature_m"] >= EXPRESSED_M]
        hidden = [r for r in known if r not in shown]
        ok = [r["verdict"] == r["truth"] or (r in hidden and r["verdict"] == "none")
              or (bool(r.get("parted")) and r["verdict"] == "fracture") for r in known]
        torn = [r for r in known if r.get("parted") and r["truth"] != "fracture"]
        print(f"against what the recordings show (an effect with a held-out signature under "
              f"{1e3 * EXPRESSED_M:g} mm may be called none; a body the synthesiser tore without a fracture, "
              f"fracture: {len(torn)} such, {sum(r['verdict'] == 'fracture' for r in torn)} called fracture): "
              f"accuracy {100 * np.mean(ok):.1f} % of {len(known)}; "
              f"recordings that show their effect: {100 * np.mean([r['verdict'] == r['truth'] for r in shown]):.1f} % "
              f"of {len(shown)}; median Chamfer reduction on them "
              f"{_median_pct([r['reduction'] for r in shown if r['truth'] != 'none'])}")


def _parser():
    from empm_gym.perception.synth import OBJECT_DEFAULTS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--make", default=None, help="synthesise and load the recordings into this folder first")
    p.add_argument("--problems", default=None, help="folder of pickled problems (written by --make, read otherwise)")
    p.add_argument("--object", default="dough", choices=sorted(OBJECT_DEFAULTS))
    p.add_argument("--effects", default="all", help="comma-separated effects (and none), default all")
    p.add_argument("--scripts", type=int, default=2, help="scripts per effect: its natural one, then another")
    p.add_argument("--only-scripts", default=None,
                   help="with --make: only these scripts (comma-separated) of those --scripts picks, e.g. the ones "
                        "whose grippers close, to rerun after a change to the grippers")
    p.add_argument("--every-effect-on", default=None,
                   help="with --make: every effect (none included) on these scripts (comma-separated) instead of "
                        "each effect's own two, e.g. a script none of the doctor's rules were chosen on")
    p.add_argument("--effect-params", default=None,
                   help="with --make: NAME=VALUE pairs (comma-separated) replacing effect defaults, e.g. viscosity=200 "
                        "(a detection limit); the recordings' names end with them")
    p.add_argument("--base-params", default=None,
                   help="with --make: E, nu, density as NAME=VALUE pairs (comma-separated) replacing the object's base "
                        "material, e.g. E=1e4,density=1100 (a material the doctor's rules were not chosen on); the "
                        "recordings' names end with them")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--calibration-error", type=float, nargs=2, default=(0.0, 0.0), metavar=("M", "DEG"),
                   help="--make: each camera's written pose off its true one by M metres and DEG degrees (random "
                        "directions; empm synth --calibration-error); the problems' names end in -cal...")
    p.add_argument("--depth-bias", type=float, default=0.0, metavar="FRAC",
                   help="--make: each camera's depth scaled by 1 +- FRAC (empm synth --depth-bias)")
    p.add_argument("--track-error", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=("JITTER", "DRIFT", "OUTLIERS"),
                   help="--make: the tracks get a tracker's errors (empm synth --track-error); names end in -trk...")
    p.add_argument("--mask-error", type=int, default=0, metavar="PX",
                   help="--make: the object masks grown by PX pixels (empm synth --mask-error); names end in -mask...")
    p.add_argument("--vary-physics", action="store_true",
                   help="with --make: each seed its own E, effect parameters, grid offset and particle jitter "
                        "(VARY_FACTORS; names start with v_); without it every seed is one simulation, other noise")
    p.add_argument("--first-seed", type=int, default=0, help="seeds --first-seed ... --first-seed + --seeds - 1")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--cameras", type=int, default=3)
    p.add_argument("--width", type=int, default=848)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--dx", type=_dx_arg, default=None,
                   help="the doctor's grid cell (m) for --make; default auto: as `empm doctor` chooses it "
                        "(doctor.load_for_doctor)")
    p.add_argument("--ppc", type=float, default=8)
    p.add_argument("--simulator", default="mpm", choices=("mpm", "springmass"),
                   help="--make's recordings moved by our MPM or by a spring-mass network (another simulator's "
                        "output: only none, table_friction and heterogeneous_stiffness; names start with sm_)")
    p.add_argument("--synth-dx", type=float, default=None,
                   help="the synthesiser's grid cell (m) for --make; default --dx, the doctor's (a finer one makes "
                        "recordings of physics the doctor's grid does not share, as another simulator's would)")
    p.add_argument("--max-points", type=int, default=1500)
    p.add_argument("--iters", type=int, default=8)
    p.add_argument("--popsize", type=int, default=8)
    p.add_argument("--device", default="cpu")
    p.add_argument("--variants", type=int, default=2, help="discretisation variants a named effect must hold on")
    p.add_argument("--no-robust", action="store_true", help="record the variants' gains, verdict without them")
    p.add_argument("--rounds", type=int, default=1,
                   help="diagnoses in a row (DoctorConfig.rounds): each named effect added to the base model and the "
                        "others tried on top; for recordings with two effects (--effects a+b)")
    p.add_argument("--deterministic", action="store_true",
                   help="every simulation the same to the bit on every run (DoctorConfig.deterministic)")
    p.add_argument("--view-bodies", action="store_true",
                   help="with --make: pickle the frame-0 body rebuilt without each camera; when diagnosing: use them "
                        "as variants too")
    p.add_argument("--trimmed-body", action="store_true",
                   help="with --make: pickle the frame-0 body trimmed to the measured surface (data.trimmed_body); "
                        "when diagnosing: a named effect must hold on it too, as `empm doctor` checks by default")
    p.add_argument("--dump", default=None, help="write each recording's full doctor result (JSON) into this folder")
    p.add_argument("--only-make", action="store_true", help="stop after --make")
    p.add_argument("--screen-pairs", default=None, metavar="SCRIPTS",
                   help="print what each of --effects (default all) and each pair of them shows held out on --object "
                        "run through these scripts (comma-separated), from the true materials' simulations: to "
                        "choose --effects a+b recordings where both show before making them (1 + n + n(n-1)/2 "
                        "simulations a script: 22 for the six, 8-23 minutes on a 2-core CPU at --synth-dx 0.005)")
    p.add_argument("--flat-splats", dest="tangent_splats", action="store_false", default=True,
                   help="with --make: record with the surface drawn as flat discs at their centres' depth (inclined "
                        "faces 0.3-0.8 mm too near), as seeds up to 14 were; by default in its tangent planes")
    p.add_argument("--tangent-splats", dest="tangent_splats", action="store_true", default=True,
                   help="with --make: the surface in its tangent planes (the default; seed 15 of session 41)")
    p.add_argument("--trim-bodies", action="store_true",
                   help="with --make: the frame-0 bodies trimmed to the measured surface (load_for_doctor's "
                        "trim_to_surface; off by default, benchmarks/RESULTS.md session 40)")
    p.add_argument("--reload", action="store_true",
                   help="with --make --keep-existing: rebuild each kept problem's scene and observations from its "
                        "recording (after a change to the loader), and its view and trimmed bodies where it has them, "
                        "keeping its signature")
    p.add_argument("--keep-existing", action="store_true",
                   help="with --make: keep problems already pickled (adding their signature), make the others")
    p.add_argument("--shard", default="0/1", help="K/N: diagnose every N-th recording from the K-th (split runs)")
    p.add_argument("--jsonl", default=None, help="append one JSON line per recording to this file")
    p.add_argument("--summarise", nargs="*", default=None, help="print the tables of these --jsonl files and stop")
    p.add_argument("--rescore", nargs="*", default=None,
                   help="print the tables of these --dump files (one JSON result per line), the verdict taken again "
                        "by the doctor's current rule, and stop (a recording in several files: from the last)")
    p.add_argument("--floor", action="store_true",
                   help="simulate each effect problem's true material on the doctor's body instead of diagnosing "
                        "(rows to --jsonl; the benchmark's own use of ground truth)")
    p.add_argument("--true-held", action="store_true",
                   help="with --floor: also the elastic material (the true E, no effect), and both again on the "
                        "doctor's body with what its closed grippers hold at frame 0 replaced by the synthesiser's "
                        "own particles there (how much of the floor is the clamp prior's)")
    p.add_argument("--oracle", action="store_true",
                   help="simulate each effect problem's recording again with the synthesiser (its ground truth, on "
                        "the grid it was made on; --synth-dx for problems that do not record it) and score its own "
                        "particles: what a perfect body and model reach, the rest depth noise (rows to --jsonl)")
    p.add_argument("--grid-offsets", type=_grid_offsets_arg, nargs="?", const=GRID_OFFSETS, default=None,
                   help="simulate each effect problem's recording again (as --oracle) with the doctor's simulator on "
                        "the recording's grid shifted by these offsets ('X,Y,Z;...' in cells, each in [0, 1); "
                        "without a value, 8 offsets along x, z and the diagonal): how much of what the recording "
                        "shows is its grid's (rows to --jsonl)")
    p.add_argument("--discretisations", type=int, default=None, metavar="K",
                   help="simulate every problem's true material (none included) on the doctor's body and on its "
                        "first K discretisation variants (grid shifted, particles on another lattice, as the "
                        "doctor's variants check makes them): how much the discretisation alone moves the held-out "
                        "loss (rows to --jsonl; the benchmark's own use of ground truth)")
    p.add_argument("--floors", nargs="*", default=[],
                   help="--floor and --oracle rows to print beside --summarise / --rescore")
    return p


def parse_args(argv=None):
    """The benchmark's options (:func:`main`'s) as a namespace."""
    return _parser().parse_args(argv)


def main(argv=None):
    p = _parser()
    args = p.parse_args(argv)
    floor_rows = [json.loads(line) for f in args.floors for line in Path(f).read_text().splitlines() if line]
    if args.rescore is not None:
        summarise(rescore(args.rescore), floor_rows)
        return 0
    if args.summarise is not None:
        summarise([json.loads(line) for f in args.summarise for line in Path(f).read_text().splitlines() if line],
                  floor_rows)
        return 0
    problems = Path(args.problems) if args.problems else None
    if args.true_held and not args.floor:
        p.error("--true-held is a part of --floor: give both")
    if args.reload and not (args.make and args.keep_existing):
        p.error("--reload rebuilds the problems kept by --make DIR --keep-existing: give both")
    if not args.tangent_splats and not args.make:
        p.error("--flat-splats says how --make records its recordings: give --make DIR")
    if args.vary_physics and not args.make:
        p.error("--vary-physics says what --make simulates for each seed: give --make DIR")
    if args.screen_pairs:
        screen(args, p)
        return 0
    if args.make:
        problems = make(args)
        if args.only_make:
            return 0
    if problems is None:
        p.error("give --make or --problems")
    if args.floor:
        floors(problems, args)
        return 0
    if args.oracle:
        oracles(problems, args)
        return 0
    if args.grid_offsets is not None:
        grid_offsets(problems, args)
        return 0
    if args.discretisations is not None:
        if args.discretisations < 1:
            p.error(f"--discretisations takes the number of variants, at least 1, got {args.discretisations}")
        discretisations(problems, args)
        return 0
    diagnose_all(problems, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
