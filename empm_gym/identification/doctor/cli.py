"""``empm doctor REC_DIR --out DIR [--base material.json] [--device cuda:0]``."""

from __future__ import annotations

import argparse
import sys

__all__ = ["register"]


def _doctor(args) -> int:
    from . import DoctorConfig, DoctorError, diagnose_recording
    from .core import fitted_text, interval_rows, interval_text
    from .report import gap_summary

    effects = [e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else None
    try:
        cfg = DoctorConfig(train_fraction=args.train_fraction, base_iters=args.iters, candidate_iters=args.iters,
                           popsize=args.popsize, variants=args.variants, variant_iters=args.variant_iters,
                           viscosity_raise=args.viscosity_raise, deterministic=args.deterministic,
                           rounds=args.rounds, intervals=not args.no_intervals)
        res = diagnose_recording(args.rec_dir, out_dir=args.out, base=args.base, config=cfg, dx=args.dx,
                                 particles_per_cell=args.particles_per_cell, device=args.device,
                                 progress=not args.quiet, effects=effects, view_bodies=not args.no_view_bodies,
                                 trimmed_body=not args.no_trimmed_body, control_delay=args.control_delay,
                                 refine_calibration=not args.keep_calibration)
    except (DoctorError, ValueError, OSError) as exc:
        print(f"empm doctor: error: {exc}", file=sys.stderr)
        return 2
    print(f"verdict: {res['effect']}  (confidence {res['confidence']:.2f})")
    print(f"  {res['reason']}")
    if res.get("decidable", True) and "candidates" in res:
        b = res["base"]["heldout"]
        print(f"  base model: {fitted_text(res['base'])} [Pa], held-out Chamfer {1e3 * b['chamfer_m']:.2f} mm")
        if gap_summary(res.get("gap")):
            print(f"  {gap_summary(res['gap'])}")
        undecided = [e["effect"] for e in res.get("not_ruled_out") or []]
        for c in res["candidates"]:
            g = c["gain"] or {}
            word = ("(significant)" if g.get("significant") else "(not ruled out)" if c["effect"] in undecided else "")
            test = "" if not interval_text(g) else (
                f" (95 % interval {interval_text(g)} %"
                + (f", penalty {100 * g['threshold']:.0f} %" if g.get("threshold") is not None else "") + ")")
            print(f"  {c['effect']:24s} held-out Chamfer {1e3 * c['heldout']['chamfer_m']:.2f} mm, loss gain "
                  f"{100 * g.get('gain', float('nan')):+.1f} %{test} {word}; fitted {fitted_text(c)}")
    for r in interval_rows(res):
        print(f"  {res['effect'] if res['effect'] != 'none' else 'base model'} {r['parameter']} = {r['value']} "
              f"({r['interval']})" + ("" if r["determined"] == "yes" else f": not determined ({r['why not']})"))
    for n in res.get("notes", []):
        print(f"  note: {n}")
    for r in res.get("rounds", ()):
        b, e = r["base_heldout_chamfer_m"], r["effect_heldout_chamfer_m"]
        print(f"round {r['round']} (the base model with {', '.join(r['base_effects'])}): {r['effect']}  (confidence "
              f"{r['confidence']:.2f})")
        print(f"  {r['reason']}")
        if b is not None:
            print(f"  held-out Chamfer {1e3 * b:.2f} mm" + (f" -> {1e3 * e:.2f} mm with {r['effect']}" if e else ""))
        for n in r.get("notes", ()):
            print(f"  note: {n}")
        if r.get("dir"):
            print(f"  its report: {r['dir']}/report.md")
    if "effects" in res:
        last = next((r["dir"] for r in reversed(res["rounds"]) if r["effect"] != "none" and r.get("dir")), None)
        where = f"{last}/material.json" if last else res.get("files", {}).get("material")
        print(f"effects named: {', '.join(res['effects']) or 'none'}" + (f"; the material with all of them: {where}"
                                                                        if res["effects"] and where else ""))
    if args.rounds == 1 and res.get("effect", "none") != "none":
        print(f"to look for a second missing effect on top of {res['effect']}: the same command with --rounds 2")
    print(f"wrote {', '.join(res.get('files', {}).values())}")
    return 0


def _effects(args) -> int:
    from empm_gym.sim.effects import describe

    print(describe())
    return 0


def register(subparsers) -> None:
    """Add ``empm doctor`` and ``empm effects``."""
    e = subparsers.add_parser("effects", help="list the catalogue of effects the doctor can name")
    e.set_defaults(func=_effects)
    p = subparsers.add_parser(
        "doctor", help="find which physical effect a model misses on a recording",
        description="Fit the base model (elastic, table friction 0.5, rigid grippers) on the first frames, find "
                    "where it disagrees with the recording, refit with each effect of the catalogue and name the one "
                    "that predicts the held-out frames better than noise explains, on other discretisations of the "
                    "body and on the body rebuilt without each camera too (or 'none').",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("rec_dir", help="recording directory")
    p.add_argument("--out", required=True, help="output directory (doctor.json, material.json, report.md, figures)")
    p.add_argument("--base", default=None, help="material file of the base model (default: elastic, E fitted)")
    p.add_argument("--effects", default=None, help="comma-separated candidate effects (default: the whole catalogue)")
    p.add_argument("--train-fraction", type=float, default=0.7, help="leading fraction of frames fitted (0.7)")
    p.add_argument("--iters", type=int, default=8, help="CMA-ES generations per fit (default 8)")
    p.add_argument("--popsize", type=int, default=8, help="CMA-ES population = simulated worlds (default 8)")
    p.add_argument("--dx", type=float, default=None,
                   help="simulation grid cell in m (default: 0.01, halved at most twice while the body is fewer than "
                        "4 cells across its thin parts, measured on each finer fill)")
    p.add_argument("--particles-per-cell", type=float, default=8, help="particles per cell of the body (8)")
    p.add_argument("--device", default=None, help="Warp device (cpu, cuda:0)")
    p.add_argument("--variants", type=int, default=2,
                   help="other discretisations of the body (grid shifted, particles resampled) a named effect must "
                        "hold its gain on (default 2; 0: no such check)")
    p.add_argument("--variant-iters", type=int, default=4, help="CMA-ES generations of a refit on a variant (4)")
    p.add_argument("--no-view-bodies", action="store_true",
                   help="do not check a named effect on the body rebuilt without each camera (faster; the check on "
                        "other discretisations stays)")
    p.add_argument("--no-trimmed-body", action="store_true",
                   help="do not check a named effect on the body trimmed to the measured surface (the rebuilt body "
                        "fills the scan's outer envelope and is larger than the object: by default a named effect "
                        "must hold on the trimmed one as well)")
    p.add_argument("--control-delay", type=float, default=0.0, metavar="FRAMES",
                   help="delay the recorded controls by this many frames (fractional) before fitting: for a "
                        "recording whose images trail its controls, as doctor.json's control_lag and its note say "
                        "(default 0)")
    p.add_argument("--viscosity-raise", type=float, default=1.0, metavar="FACTOR",
                   help="when the viscosity's fit ends at the top of the box the explicit step allows and gains held "
                        "out, fit every candidate again with that box FACTOR times higher, on about FACTOR times the "
                        "substeps (default 1: never; for a material far more viscous than the box)")
    p.add_argument("--deterministic", action="store_true",
                   help="the same result to the bit on every run, on a GPU too (64-bit integer sums in P2G, "
                        "at some speed cost; CPU runs are deterministic either way)")
    p.add_argument("--rounds", type=int, default=1,
                   help="diagnoses in a row: where one names an effect, the next fits the base model with it and "
                        "tries the catalogue's other effects on top, for a recording that lacks more than one "
                        "(default 1; each round costs about one diagnosis more, its outputs in OUT/round2, ...)")
    p.add_argument("--no-intervals", action="store_true",
                   help="skip the 95 %% intervals of the chosen model's parameters (probe simulations around its "
                        "fit, as `empm identify` gives them)")
    p.add_argument("--keep-calibration", action="store_true",
                   help="use the recorded camera poses as they are, even where the cameras disagree (by default "
                        "cameras whose frame-0 points disagree beyond 1.5 mm are shifted onto one surface, in "
                        "memory, and the notes say by how much; the recording is not changed)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_doctor)
