"""``empm identify`` and ``empm evaluate``.

    empm identify REC_DIR --out material.json [--method adam|cmaes] [--params E,nu,...] [--iters N] [--resume]
    empm identify REC_DIR --out material.json --online
    empm evaluate REC_DIR --material material.json [--out-dir DIR]
    empm identify REC_DIR --model spring-mass --out sm.json [--params stiffness,damping]

``--model spring-mass`` fits the PhysTwin-style spring-mass model family instead of the MPM
(:mod:`empm_gym.identification.springmass`: stiffness [Pa] and damping [Pa s], Adam through ``wp.Tape``) and
writes a ``"model": "spring-mass"`` material file; ``evaluate`` reads the family from the file.

``identify`` fits the first ``--train-fraction`` of the frames (default 0.7) and writes ``material.json``,
``<stem>_fit.png`` (loss and parameter curves) and ``<stem>.rrd`` (simulation over the measured points)
next to it; with ``--online`` it replays the recording through the streaming identifier instead and also
writes ``<stem>_online.json`` / ``<stem>_online.png`` with the losses with and without updates.
``evaluate`` reports Chamfer, tracking error, mask IoU, PSNR and SSIM on the held-out frames.

After an offline fit, ``identify`` says how far to trust it (:func:`.uncertainty.assess_fit`): a 95 %
interval per parameter in ``fit.uncertainty.<param>`` (``interval``, ``level``, ``determined``), the
combinations that motion alone determines (E / density when the density is assumed), and warnings in
``fit.identifiability`` for a parameter at its search bound, flat within noise, strongly correlated with
another, or a grid too coarse for the body; ``--strict`` then exits with 3. The interval includes the
share of the frame-0 body's reconstructed shape: the body is rebuilt with each camera left out in turn
and the probes rerun on each (a one-camera recording cannot do this, and a warning says so).

Interrupting ``identify`` (Ctrl-C or SIGTERM) stops the fit after its current iteration, writes the best
parameters so far to ``--out`` with ``fit.complete: false`` and the state to continue from, and exits with
130 (SIGINT) or 143 (SIGTERM); a second Ctrl-C stops at once without writing. The file is replaced
atomically, never truncated; interrupted before the first iteration finished, it is left as it was. Run the
same command with ``--resume`` to continue up to ``--iters`` iterations in all (default: the interrupted
run's) with the same result as an uninterrupted fit; ``--resume`` refuses (exit 2) a file that holds no
interrupted fit or one made with other options or data.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["register"]


def _parse_params(text: str):
    from .problem import PARAM_NAMES

    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [n for n in names if n not in PARAM_NAMES]
    if not names or bad:
        raise ValueError(f"--params must be a comma-separated subset of {','.join(PARAM_NAMES)}, got {text!r}")
    return tuple(names)


def _parse_init(text):
    from .problem import PARAM_NAMES

    out = {}
    if not text:
        return out
    for item in text.split(","):
        if "=" not in item:
            raise ValueError(f"--init takes NAME=VALUE pairs separated by commas (e.g. E=1e5,nu=0.3), got {item!r}")
        k, v = item.split("=", 1)
        k = k.strip()
        if k not in PARAM_NAMES:
            raise ValueError(f"--init: unknown parameter {k!r}; allowed: {', '.join(PARAM_NAMES)}")
        try:
            out[k] = float(v)
        except ValueError:
            raise ValueError(f"--init: {k} must be a number, got {v!r}") from None
    return out


def _base_material(init, params):
    """The material a recording is replayed with: E, nu, density and the effect parameters given in ``init``
    (yield_stress 1 kPa when fitted without a start; the table friction is the scene's)."""
    from empm_gym.sim import MaterialConfig
    from empm_gym.sim.effects import PARAMETERS

    ys = init.get("yield_stress", 1.0e3 if "yield_stress" in params else None)
    m = MaterialConfig(E=init.get("E", 1.0e5), nu=init.get("nu", 0.3), density=init.get("density", 1000.0),
                       yield_stress=ys)
    try:
        return m.replace(**{k: v for k, v in init.items() if k in PARAMETERS and k not in ("yield_stress", "friction")})
    except ValueError as exc:
        raise ValueError(f"--init: {exc}") from None


def _identify(args) -> int:
    # which options the user set (a time budget never changes those), then their defaults
    args.user_set = {"particles_per_cell": args.particles_per_cell is not None, "iters": args.iters is not None,
                     "lr": bool(args.lr), "frames": args.train_fraction is not None}
    args.train_fraction = 0.7 if args.train_fraction is None else args.train_fraction
    args.particles_per_cell = 27.0 if args.particles_per_cell is None else args.particles_per_cell
    if getattr(args, "model", "mpm") == "spring-mass":
        return _identify_spring_mass(args)
    from empm_gym.sim import MaterialConfig  # noqa: F401  (import errors surface early)

    from .data import frame_ranges, load_recording, open_recording
    from .interrupt import stop_on_signals
    from .offline import ResumeError, identify, read_resume_state
    from .report import plot_fit, plot_online, save_rrd
    from empm_gym.sim import write_material

    out = Path(args.out)
    resume = None
    try:
        params = _parse_params(args.params or "E")
        init = _parse_init(args.init)
        if not (0.0 < args.train_fraction <= 1.0):
            raise ValueError(f"--train-fraction must lie in (0, 1], got {args.train_fraction}")
        if args.budget_min is not None and not args.budget_min >= 0.0:
            raise ValueError(f"--budget-min must be 0 (no budget) or a positive number of minutes, got "
                             f"{args.budget_min}")
        if args.resume:
            if args.online:
                raise ValueError("--resume continues an interrupted offline fit; it does not apply to --online")
            resume = read_resume_state(out)
        body_info = {}
        # opened once: the bodies rebuilt below see the same (corrected) cameras
        args.recording = open_recording(args.rec_dir, refine_calibration=not args.keep_calibration, info=body_info)
        scene, obs, views = load_recording(args.recording, dx=args.dx, particles_per_cell=args.particles_per_cell,
                                           material=_base_material(init, params),
                                           table_friction=init.get("friction", 0.5), frames=args.frames,
                                           device=args.device, progress=not args.quiet, info=body_info)
    except (ValueError, OSError) as exc:
        print(f"empm identify: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"empm identify: interrupted while loading the recording; {out} not written", file=sys.stderr)
        return 130
    stem = out.with_suffix("")
    T = obs.num_frames
    if args.online:
        from .online import OnlineFrame, replay

        frames = (OnlineFrame(obs.points[t], scene.ee_positions[t], scene.ee_grip[t],
                              views.masks[t] if views.masks is not None else None) for t in range(T))
        res = replay(scene, frames, params=params, init=init or None, cameras=views.cameras, H=args.horizon,
                     k=args.every, lr=args.lr or 0.1, progress=not args.quiet)
        mat, mu = _material_from(scene, res["params"])
        fit = {"method": "online", "params": list(params), "init": res["initial_params"],
               "summary": res["summary"], "frames_used": T, "fps": obs.fps, "dx": scene.dx,
               "particles_per_cell": args.particles_per_cell}
        write_material(out, mat.replace(friction=mu), fit)
        Path(f"{stem}_online.json").write_text(json.dumps(res, indent=2, default=float))
        plot_online(res, f"{stem}_online.png")
        s = res["summary"]
        print(f"online: {s['updates']} updates at {s['quasi_static_frames']} quasi-static frames of {s['frames']}")
        for k in ("chamfer", "mask_loss", "mask_iou"):
            if f"{k}_with_updates" in s:
                print(f"  {k:10s} with updates {s[f'{k}_with_updates']:.5f}   without {s[f'{k}_without_updates']:.5f}")
        print(f"  params: {', '.join(f'{k}={v:.5g}' for k, v in res['params'].items())}")
        print(f"wrote {out}")
        return 0
    F = max(2, int(round(args.train_fraction * T)))
    iters = args.iters if args.iters is not None else int(resume["iterations_requested"]) if resume else 30
    ppc = args.particles_per_cell
    try:
        cams = len(views.cameras)
        shape_bodies = (cams if cams > 1 else 0) + (2 if (body_info.get("symmetry") or {}).get("used") else 0)
        plan, scene = _plan(args, scene, obs, resume, F, iters, ppc, shape_bodies, len(params))
    except (ValueError, OSError) as exc:
        print(f"empm identify: error: {exc}", file=sys.stderr)
        return 2
    if plan is not None:
        F, iters, ppc = plan.fit_frames, (iters if resume else plan.iters), plan.particles_per_cell
    kw = dict(params=params, method=args.method, init=init or None, iters=iters, frames=F,
              progress=not args.quiet, popsize=args.popsize)
    if args.lr or (plan is not None and plan.lr):
        kw["lr"] = args.lr or plan.lr
    if plan is not None:
        kw["memory_budget_bytes"] = plan.memory_budget_bytes
    done0 = int(resume["iterations_done"]) if resume else 0
    what = f"iterations {done0 + 1}-{iters} of {iters}, resuming {out}" if resume else f"{iters} iterations"
    if not resume:
        _note_interrupted_fit(out)
    hidden = [t for t in body_info.get("hidden_frames", []) if t < F]
    print(f"empm identify: fitting {','.join(params)} ({args.method}) on frames 0-{F - 1} of {T} ({what}"
          + (f"; frames {frame_ranges(hidden)} not scored: no camera sees the object there" if hidden else "")
          + "); Ctrl-C stops after the current iteration and saves", file=sys.stderr)
    with stop_on_signals() as stop:
        try:
            res = identify(obs, scene, stop=stop, resume=resume, **kw)
        except ResumeError as exc:
            print(f"empm identify: error: cannot resume from {out}: {exc}", file=sys.stderr)
            return 2
        except ValueError as exc:
            print(f"empm identify: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"empm identify: stopped at once by a second signal; {out} not written", file=sys.stderr)
            return stop.exit_code
        res.extra["dx"] = scene.dx
        res.extra["particles_per_cell"] = ppc
        if plan is not None:
            res.extra["plan"] = plan.to_dict()
        res.extra["recording"] = str(Path(args.rec_dir).resolve())
        if hidden:
            res.extra["hidden_frames"] = hidden  # simulated but not scored (Observations.seen)
        if stop.is_set():  # save what there is, skip the plots
            return _save_interrupted(res, out, stop, done0)
    undetermined = []
    if not args.no_uncertainty:
        from .uncertainty import assess_fit

        if not args.quiet:
            print("empm identify: intervals and identifiability (probe simulations around the fit) ...",
                  file=sys.stderr)
        from .data import view_jackknife_bodies

        others = view_jackknife_bodies(args.recording, scene, particles_per_cell=ppc, symmetry=body_info.get("symmetry"))
        a = assess_fit(res, scene, obs, other_bodies=others, body_note=body_info.get("body_completion"),
                       resample_bodies=2 if plan is None else plan.resample_bodies,
                       # the grid's share (a finer or coarser grid) costs probe batches that a time budget's
                       # estimate leaves out
                       refine_grid=plan is None or plan.budget_s is None)
        if body_info.get("hidden_note"):  # the interval holds the rebuilt bodies, all on the same completion
            a["identifiability"]["warnings"].append(body_info["hidden_note"])
        if body_info.get("calibration_note"):  # every body and every frame carries the rig's disagreement
            a["identifiability"]["warnings"].append(body_info["calibration_note"])
        if body_info.get("track_note"):  # the tracks weigh less than the depth's noise alone would let them
            a["identifiability"]["warnings"].append(body_info["track_note"])
        if body_info.get("rim_note"):  # the masks took in the table's rim around the object: left out
            a["identifiability"]["warnings"].append(body_info["rim_note"])
        if body_info.get("table_track_note"):  # tracks that strayed onto the table through such masks: left out
            a["identifiability"]["warnings"].append(body_info["table_track_note"])
        res.extra.update(a)
        undetermined = [k for k, u in a["uncertainty"].items() if not u["determined"]]
    res.save(out)
    plot_fit(res, f"{stem}_fit.png")
    if not args.no_rrd:
        from .problem import simulate_frames

        X = simulate_frames(scene, [res.material], [res.friction], frames=T)[:, 0]
        save_rrd(f"{stem}.rrd", X, obs.points, obs.fps, ee_positions=scene.ee_positions,
                 ee_configs=scene.ee_configs, ee_orientations=scene.ee_orientations,
                 particle_radius=scene.particle_radius)
    print(f"{args.method}: {', '.join(f'{k}={v:.5g}' for k, v in res.params.items())}  loss {res.loss:.5g}  "
          f"({res.wall_time_s:.1f} s, {len(res.loss_history)} iterations"
          + (", converged" if res.extra.get("converged_at") is not None else "") + f", frames 0-{F - 1} of {T})")
    if "uncertainty" in res.extra:
        _print_uncertainty(res.extra)
    print(f"wrote {out}, {stem}_fit.png" + ("" if args.no_rrd else f", {stem}.rrd"))
    if undetermined and args.strict:
        print(f"empm identify: --strict: {', '.join(undetermined)} not determined by this recording (exit 3)",
              file=sys.stderr)
        return 3
    return 0


def _plan(args, scene, obs, resume, F: int, iters: int, ppc: float, shape_bodies: int, fitted: int):
    """``(FitPlan or None, scene)``: the Adam fit's settings for the time budget (:mod:`.budget`), said on stderr
    with the estimate; a resumed fit takes the plan recorded in the file it continues. ``shape_bodies``: how many
    rebuilt frame-0 bodies the intervals will probe (:func:`.data.view_jackknife_bodies`); ``fitted``: how many
    parameters are fitted (the intervals scan each across its box)."""
    import dataclasses

    from .budget import FitPlan, default_budget_s, plan_fit
    from .data import rebuilt_scene

    if args.method != "adam":
        return None, scene
    if resume is not None:
        rec = resume.get("plan")
        if not isinstance(rec, dict):
            return None, scene
        try:
            plan = FitPlan(**{k: v for k, v in rec.items() if k in {f.name for f in dataclasses.fields(FitPlan)}})
        except TypeError as exc:
            raise ValueError(f"cannot resume from {args.out}: its fit.plan is incomplete ({exc})") from None
        if plan.motion_margin is not None:
            scene = dataclasses.replace(scene, motion_margin=plan.motion_margin)
        if plan.particles_per_cell != ppc:
            scene = rebuilt_scene(args.recording, scene, particles_per_cell=plan.particles_per_cell,
                                  points=obs.points[0])
        return plan, scene
    budget = default_budget_s(args.device) if args.budget_min is None else 60.0 * args.budget_min
    plan, scene = plan_fit(scene, scene.material, fit_frames=F, iters=iters, particles_per_cell=ppc, budget_s=budget,
                           fixed=args.user_set, views=shape_bodies, lr=args.lr,
                           rebuild_body=lambda sc, q: rebuilt_scene(args.recording, sc, particles_per_cell=q,
                                                                    points=obs.points[0]),
                           uncertainty=not args.no_uncertainty, fitted=fitted)
    print(f"empm identify: {plan.describe()}", file=sys.stderr)
    return plan, scene


def _print_uncertainty(extra: dict) -> None:
    """Intervals, combinations and identifiability warnings of a fit (see :func:`.uncertainty.assess_fit`)."""
    from .uncertainty import uncertainty_bound

    idf = extra["identifiability"]
    for k, u in extra["uncertainty"].items():
        lo, hi = u["interval"]
        bound = uncertainty_bound(u)
        state = "" if u["determined"] else (f"   NOT DETERMINED: bounded {bound} (see warnings)" if bound
                                            else "   NOT DETERMINED (see warnings)")
        print(f"  {k:14s} {100 * u['level']:.0f} % interval [{lo:.4g}, {hi:.4g}]{state}")
    for name, c in idf["combinations"].items():
        iv = c.get("interval")
        iv = f" [{iv[0]:.4g}, {iv[1]:.4g}]" if iv else ""
        unit = "" if c["unit"] == "-" else f" {c['unit']}"
        print(f"  {name:14s} {c['value']:.4g}{iv}{unit}: {c['note']}")
    for w in idf["warnings"]:
        print(f"  warning: {w}")


def _note_interrupted_fit(out: Path) -> None:
    """Say so on stderr when a fresh fit is about to replace the interrupted fit held in ``out``."""
    from empm_gym.sim import read_material

    try:
        fit = read_material(out).fit if out.is_file() else None
    except (ValueError, OSError):
        return
    if isinstance(fit, dict) and fit.get("complete") is False and fit.get("resume"):
        print(f"empm identify: note: {out} holds an interrupted fit ({fit.get('iterations_done')} of "
              f"{fit.get('iterations_requested')} iterations); fitting anew replaces it (--resume continues it)",
              file=sys.stderr)


def _save_interrupted(res, out: Path, stop, done0: int) -> int:
    """Write an interrupted fit (if it did an iteration), say so in one line; the exit code of the signal."""
    if res.iterations_done <= done0:
        print(f"empm identify: interrupted before an iteration finished; {out} left as it was", file=sys.stderr)
        return stop.exit_code
    try:
        res.save(out)
    except KeyboardInterrupt:  # a second signal during the (atomic) write: the previous file stays
        print(f"empm identify: stopped at once by a second signal; {out} left as it was", file=sys.stderr)
        return stop.exit_code
    if res.complete:
        print(f"empm identify: interrupted in the last iteration; wrote {out} (fit.complete: true, "
              f"{res.iterations_done} iterations); skipped the plots", file=sys.stderr)
    else:
        print(f"empm identify: interrupted after {res.iterations_done} of {res.iterations_requested} iterations; "
              f"wrote {out} (fit.complete: false); continue with --resume", file=sys.stderr)
    return stop.exit_code


def _material_from(scene, values):
    """(MaterialConfig, table friction) of the scene's material with ``values`` substituted."""
    mat = scene.material.replace(**{k: v for k, v in values.items() if k != "friction"})
    return mat, float(values.get("friction", scene.table_friction))


def _evaluate(args) -> int:
    from .data import frame_ranges, load_recording
    from .evaluate import evaluate, held_out_frames
    from empm_gym.sim import read_material

    try:
        mf = read_material(args.material, models=("mpm", "spring-mass"))
        if args.model is not None and args.model != mf.model:
            raise ValueError(f"{args.material} holds a {mf.model} model, not --model {args.model}")
        mat, mu, fit = mf.material, mf.table_friction, mf.fit or {}
        dx = args.dx or float(fit.get("dx", 0.01))
        ppc = args.particles_per_cell or float(fit.get("particles_per_cell", 27))
        scene, obs, views = load_recording(args.rec_dir, dx=dx, particles_per_cell=ppc, material=mat,
                                           table_friction=0.5 if mu is None else mu, device=args.device,
                                           progress=not args.quiet)
        frames = held_out_frames(obs.num_frames, args.train_fraction)
    except (ValueError, OSError) as exc:
        print(f"empm evaluate: error: {exc}", file=sys.stderr)
        return 2
    out_dir = Path(args.out_dir) if args.out_dir else Path(args.material).resolve().parent
    if mf.model == "spring-mass":
        from .springmass import evaluate_spring_mass, read_spring_mass

        try:
            cfg, _ = read_spring_mass(args.material)
        except ValueError as exc:
            print(f"empm evaluate: error: {exc}", file=sys.stderr)
            return 2
        res = evaluate_spring_mass(scene, cfg, obs, views, eval_frames=frames, downsample=args.downsample,
                                   out_dir=out_dir, progress=not args.quiet)
    else:
        res = evaluate(scene, mat, mu, obs, views, eval_frames=frames, downsample=args.downsample, out_dir=out_dir,
                       progress=not args.quiet)
    hidden = res.get("unscored_frames") or []
    print(f"held-out frames {frames[0]}-{frames[-1]} of {obs.num_frames}"
          + (f" (frames {frame_ranges(hidden)} not scored: no camera sees the object there)" if hidden else "") + ":")
    units = {"chamfer": "m", "chamfer_obs": "m", "track": "m", "iou": "", "psnr": "dB", "ssim": ""}
    for k, v in res["summary"].items():
        print(f"  {k:12s} {v:.5g} {units.get(k, '')}")
    print(f"wrote {', '.join(res['files'])}")
    return 0


def register(subparsers) -> None:
    """Add ``identify`` and ``evaluate`` to the ``empm`` command."""
    p = subparsers.add_parser("identify", help="fit material parameters to a recording",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("rec_dir", help="recording directory")
    p.add_argument("--out", default="material.json", help="output material file (default material.json)")
    p.add_argument("--method", choices=("adam", "cmaes"), default="adam")
    p.add_argument("--model", choices=("mpm", "spring-mass"), default="mpm",
                   help="model family: the MPM (default) or the PhysTwin-style spring-mass model (adam only)")
    from .problem import PARAM_NAMES

    p.add_argument("--params", default=None, help=f"comma-separated subset of {','.join(PARAM_NAMES)} (the base "
                   f"parameters and every effect parameter of empm_gym.sim.effects; default E); with --model "
                   f"spring-mass of stiffness,damping (the default)")
    p.add_argument("--init", default="", help="starting values, e.g. E=1e5,yield_stress=2000,viscosity=5 (SI units; "
                   "default: E=1e5, nu=0.3, density=1000, friction=0.5, an effect's registry start value)")
    p.add_argument("--iters", type=int, default=None, help="Adam steps or CMA-ES generations in all (default 30; "
                   "with --resume the interrupted run's)")
    p.add_argument("--resume", action="store_true", help="continue the interrupted fit saved in --out (run with "
                   "the same recording and options)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate in log-parameter space (default 0.15)")
    p.add_argument("--popsize", type=int, default=6, help="CMA-ES population = simulated worlds (default 6)")
    p.add_argument("--train-fraction", type=float, default=None, help="leading fraction of frames fitted (0.7)")
    p.add_argument("--frames", type=int, default=None, help="use only the first N frames of the recording")
    p.add_argument("--dx", type=float, default=0.01, help="simulation grid cell in m (default 0.01)")
    p.add_argument("--particles-per-cell", type=float, default=None,
                   help="particles per grid cell filling the frame-0 body (default 27)")
    p.add_argument("--budget-min", type=float, default=None,
                   help="time budget of an Adam fit and its intervals, in minutes (default: 9 on the CPU, none on "
                        "a GPU; 0: none): the fit's cost is measured first and, when over, the options not given "
                        "are reduced (grid margin, particles per cell, iterations, fitted frames); said up front")
    p.add_argument("--online", action="store_true", help="stream the recording through the online identifier")
    p.add_argument("--horizon", type=int, default=10, help="online: look-ahead H in frames (default 10)")
    p.add_argument("--every", type=int, default=5, help="online: at most one update every k frames (default 5)")
    p.add_argument("--device", default=None, help="Warp device (cpu, cuda:0)")
    p.add_argument("--no-rrd", action="store_true", help="do not write the rerun recording")
    p.add_argument("--no-uncertainty", action="store_true",
                   help="skip the intervals and identifiability checks (probe simulations after the fit)")
    p.add_argument("--strict", action="store_true",
                   help="exit with status 3 when a fitted parameter is not determined by the recording")
    p.add_argument("--keep-calibration", action="store_true",
                   help="use the recorded camera poses as they are, even where the cameras disagree (by default "
                        "cameras whose frame-0 points disagree beyond 1.5 mm are shifted onto one surface, in "
                        "memory; the recording is not changed)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_identify)

    e = subparsers.add_parser("evaluate", help="evaluate a material file on a recording's held-out frames")
    e.add_argument("rec_dir", help="recording directory")
    e.add_argument("--material", required=True, help="material file (material.json written by empm identify)")
    e.add_argument("--out-dir", default=None, help="where to write the report (default: next to the material)")
    e.add_argument("--train-fraction", type=float, default=0.7, help="frames after this fraction are evaluated")
    e.add_argument("--dx", type=float, default=None, help="grid cell in m (default: the one used for fitting)")
    e.add_argument("--particles-per-cell", type=float, default=None,
                   help="particles per grid cell (default: the one used for fitting)")
    e.add_argument("--model", choices=("mpm", "spring-mass"), default=None,
                   help="model family expected in --material (default: whatever the file holds)")
    e.add_argument("--downsample", type=int, default=2, help="image downsampling for IoU / PSNR / SSIM (2)")
    e.add_argument("--device", default=None, help="Warp device (cpu, cuda:0)")
    e.add_argument("--quiet", action="store_true", help="no progress bars")
    e.set_defaults(func=_evaluate)


def _identify_spring_mass(args) -> int:
    """``empm identify --model spring-mass``: fit stiffness / damping of the spring-mass model family."""
    from empm_gym.sim import MaterialConfig

    from .data import load_recording
    from .interrupt import stop_on_signals
    from .report import plot_fit, save_rrd
    from .springmass import SPRING_MASS_PARAMS, identify_spring_mass, simulate_frames_spring_mass

    out = Path(args.out)
    allowed = tuple(SPRING_MASS_PARAMS) + ("density", "friction")
    try:
        if args.method != "adam" or args.online or args.resume:
            raise ValueError("--model spring-mass fits with --method adam only (no --online, no --resume)")
        params = tuple(s.strip() for s in (args.params or "stiffness,damping").split(",") if s.strip())
        bad = [n for n in params if n not in SPRING_MASS_PARAMS]
        if not params or bad:
            raise ValueError(f"--params for --model spring-mass must be a subset of {','.join(SPRING_MASS_PARAMS)}, "
                             f"got {args.params!r}")
        init = {}
        for item in filter(None, (s.strip() for s in (args.init or "").split(","))):
            k, sep, v = item.partition("=")
            if not sep or k.strip() not in allowed:
                raise ValueError(f"--init takes NAME=VALUE with NAME in {', '.join(allowed)} for --model spring-mass, "
                                 f"got {item!r}")
            try:
                init[k.strip()] = float(v)
            except ValueError:
                raise ValueError(f"--init: {k.strip()} must be a number, got {v!r}") from None
        if not (0.0 < args.train_fraction <= 1.0):
            raise ValueError(f"--train-fraction must lie in (0, 1], got {args.train_fraction}")
        scene, obs, views = load_recording(args.rec_dir, dx=args.dx, particles_per_cell=args.particles_per_cell,
                                           material=MaterialConfig(density=init.get("density", 1000.0)),
                                           table_friction=init.get("friction", 0.5), frames=args.frames,
                                           device=args.device, progress=not args.quiet)
    except (ValueError, OSError) as exc:
        print(f"empm identify: error: {exc}", file=sys.stderr)
        return 2
    T = obs.num_frames
    F = max(2, int(round(args.train_fraction * T)))
    iters = args.iters or 30
    print(f"empm identify: fitting {','.join(params)} of the spring-mass model on frames 0-{F - 1} of {T} "
          f"({iters} iterations); Ctrl-C stops after the current iteration and saves", file=sys.stderr)
    kw = {"lr": args.lr} if args.lr else {}
    with stop_on_signals() as stop:
        try:
            res = identify_spring_mass(obs, scene, params=params, init={k: v for k, v in init.items()
                                                                         if k in SPRING_MASS_PARAMS},
                                       iters=iters, frames=F, progress=not args.quiet, stop=stop, **kw)
        except ValueError as exc:
            print(f"empm identify: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"empm identify: stopped at once by a second signal; {out} not written", file=sys.stderr)
            return stop.exit_code
    res.extra.update(dx=scene.dx, particles_per_cell=args.particles_per_cell,
                     recording=str(Path(args.rec_dir).resolve()))
    res.save(out)
    stem = out.with_suffix("")
    if stop.is_set():
        print(f"empm identify: interrupted after {res.iterations_done} of {iters} iterations; wrote {out} "
              f"(fit.complete: false)", file=sys.stderr)
        return stop.exit_code
    plot_fit(res, f"{stem}_fit.png")
    if not args.no_rrd:
        X = simulate_frames_spring_mass(scene, res.config, frames=T)
        save_rrd(f"{stem}.rrd", X, obs.points, obs.fps, ee_positions=scene.ee_positions,
                 ee_configs=scene.ee_configs, ee_orientations=scene.ee_orientations,
                 particle_radius=0.5 * res.extra["spacing_m"])
    print(f"spring-mass: {', '.join(f'{k}={v:.5g}' for k, v in res.params.items())}  loss {res.loss:.5g}  "
          f"({res.wall_time_s:.1f} s, {len(res.loss_history)} iterations, {res.extra['particles']} particles, "
          f"{res.extra['springs']} springs, frames 0-{F - 1} of {T})")
    print(f"wrote {out}, {stem}_fit.png" + ("" if args.no_rrd else f", {stem}.rrd"))
    idf = res.extra["identifiability"]
    for w in idf["warnings"]:
        print(f"  warning: {w}")
    undetermined = [k for k, ok in idf["determined"].items() if not ok]
    if undetermined and args.strict:
        print(f"empm identify: --strict: {', '.join(undetermined)} not determined by this recording (exit 3)",
              file=sys.stderr)
        return 3
    return 0
