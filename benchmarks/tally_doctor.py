"""The doctor benchmark's standing from the stored rows: every recording of seeds FIRST..LAST (default 10-18) in
the benchmark's set (each effect on its natural and its second script, ``none`` on every script), scored from the
last stored run of it, then bench_doctor.py's tables over them, with every stored floor and oracle (what each
recording lets a fit show).

Rows come from ``benchmarks/data/doctor_s*.jsonl`` in session order: slim ``--dump`` lines are rescored with the
doctor's current rule (``bench_doctor.rescore``), older result rows are taken as they are. Files of experiments that
ran the doctor other than as shipped (a changed rule, a probe) are left out of the verdicts by name (EXCLUDED), and
so are the floors' and oracles' files, which ``stored_floors`` reads.

usage: python benchmarks/tally_doctor.py [--seeds 10-18] [--misses] [--varied] [--would-raise]
"""

import argparse
import functools
import json
import re
import sys
from collections import Counter
from pathlib import Path
from typing import Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_doctor as B  # noqa: E402

DATA = Path(__file__).resolve().parent / "data"
#: Parts of the names of stored runs that are not the doctor as shipped at their time: signature and floor
#: measurements, oracles and probes, a rule's before/after comparisons, runs with a setting changed to compare, and
#: recordings made again with another rig under the benchmark's names (four cameras, session 79).
EXCLUDED = ("signatures", "oracle", "floors", "probe", "s52_yield", "s52_rope_lift_end_14", "code_742e6fc",
            "world_axes", "before_change", "before_rule", "before_scan", "retry_reverted", "variants_side", "old_new",
            "alone", "repeat", "contenders", "unscaled_start_only", "trimmed_bodies", "grid_offsets", "discretisations",
            "four_cameras")
NAME = re.compile(r"(v_)?(dough|rope)-([a-z-]+)-(\d+)-([a-z_]+)$")  # v_: made with --vary-physics


def _session(path: Path) -> int:
    m = re.search(r"_s(\d+)_", path.name)  # doctor_s36_floors_..., doctor_floors_s29_...; undated by session: 0
    return int(m.group(1)) if m else 0


def _stored(data: Path, pattern: str, excluded=EXCLUDED):
    """The files of ``data`` matching ``pattern``, in session order, less those whose names hold a part of
    ``excluded``."""
    return sorted((p for p in data.glob(pattern) if not any(x in p.name for x in excluded)),
                  key=lambda p: (_session(p), p.name))  # within a session, by name: the same order on any machine


def stored_rows(first: int, last: int, data: Path = DATA, varied: bool = False):
    """The benchmark's rows of seeds ``first``..``last``, each from the last stored run of its recording, with the
    file it came from under ``"source"``; ``varied``: those of the recordings made with ``--vary-physics``
    (``v_...``, each seed its own material and discretisation) instead of the fixed set's."""
    rows = {}
    for path in _stored(data, "doctor_s*.jsonl"):
        lines = [json.loads(t) for t in path.read_text().splitlines() if t.strip()]
        dumps = any(r.get("candidates") and "effect" in r and "wall_s" in r for r in lines)
        scored = {r["recording"]: r for r in B.rescore([path])} if dumps else {}
        for line in lines:
            m = NAME.match(line.get("recording", ""))
            if not m or bool(m.group(1)) != varied or not first <= int(m.group(4)) <= last:
                continue
            row = scored.get(line["recording"]) or (line if "verdict" in line else None)
            if row is None:
                continue
            obj, script, truth = m.group(2), m.group(3), row.get("truth") or m.group(5)
            if truth != "none" and script not in (B.NATURAL[truth], B.second_script(obj, truth)):
                continue
            rows.pop(line["recording"], None)
            rows[line["recording"]] = {**row, "truth": truth, "script": script, "source": path.name}
    return list(rows.values())


def stored_floors(data: Path = DATA):
    """The stored ``--floor`` and ``--oracle`` rows (the true material on the doctor's body; the recording's own
    simulation), the last of each kind per recording: what each recording lets any fit show (bench_doctor.floors).
    A floor was measured on the doctor's body of its session; a later change to the body is not in it."""
    rows = {}
    for pattern in ("doctor_*floors*.jsonl", "doctor_*oracle*.jsonl"):
        for path in _stored(data, pattern, excluded=("trimmed_bodies",)):  # a body changed to compare: left out
            for t in path.read_text().splitlines():
                if t.strip():
                    r = json.loads(t)
                    kind = "floor" if "floor_chamfer_m" in r else "oracle" if "oracle_chamfer_m" in r else None
                    if kind and "recording" in r:
                        rows[(kind, r["recording"])] = r
    return list(rows.values())


def would_raise(row: dict, factor: float = 3.0) -> str:
    """Why the current doctor with ``DoctorConfig.viscosity_raise`` at ``factor`` (off by default) would fit
    ``row``'s candidates again with the viscosity's box raised
    (:func:`~empm_gym.identification.doctor.core.viscosity_raise_reason`, from its stored viscosity candidate),
    or '' where it would not, or the run raised it already (``viscosity_box_raised``). A row stored before
    candidates kept their search box (session 58) has it recomputed from its E window and material at the
    recording's cell: the first pass's box."""
    from empm_gym.identification.doctor.core import DoctorConfig, _Fit, _search_box, viscosity_raise_reason
    from empm_gym.sim import MaterialConfig

    if row.get("viscosity_box_raised"):
        return ""
    dx = (row.get("grid") or {}).get("dx_m")
    for c in row.get("candidates") or []:
        if c.get("effect") != "viscosity" or not c.get("gain") or "viscosity" not in c.get("params", {}):
            continue
        box = (c.get("search_box") or {}).get("viscosity")
        if box is None:
            if not dx or not c.get("E_window"):
                continue
            m = c.get("material") or {}
            stiffest = MaterialConfig(E=c["E_window"][1], nu=m.get("nu", 0.3), density=m.get("density", 1000.0))
            box = _search_box("viscosity", stiffest, dx)
        f = _Fit("viscosity", dict(c["params"]), MaterialConfig(E=c["params"]["E"], nu=0.3, density=1000.0), 0.5,
                 c.get("fit_loss", 0.0), 0.0, added=1, bounds={"viscosity": tuple(box)})
        f.test = c["gain"]
        return viscosity_raise_reason([f], DoctorConfig(viscosity_raise=factor)) or ""
    return ""


def by_session(rows) -> str:
    """How many of ``rows`` (:func:`stored_rows`) come from the runs of each session: "s35 22, s37 42, ..."."""
    n = Counter(_session(Path(r["source"])) for r in rows)
    return ", ".join(f"s{k} {v}" for k, v in sorted(n.items()))


def by_simulation(rows) -> dict:
    """``rows`` (:func:`stored_rows`) grouped by the simulation they render: ``{(object, script, truth): (named
    right, recordings)}``. The synthesiser samples every seed's body on one lattice with the same material and
    controls, so the seeds of one object, script and effect are one simulation seen through different depth noise
    (benchmarks/RESULTS.md, session 56): the benchmark's independent physical cases are these, not its
    recordings."""
    out = {}
    for r in rows:
        m = NAME.match(r["recording"])
        key = (m.group(2), r["script"], r["truth"])
        right, n = out.get(key, (0, 0))
        out[key] = (right + (r["verdict"] == r["truth"]), n + 1)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", default="10-18", help="FIRST-LAST, inclusive (default 10-18)")
    p.add_argument("--misses", action="store_true", help="list the wrong verdicts and the file each came from")
    p.add_argument("--varied", action="store_true",
                   help="the recordings made with --vary-physics (v_..., each seed its own material and grid)")
    p.add_argument("--would-raise", action="store_true",
                   help="list the recordings whose stored run the doctor would fit again with the viscosity's box "
                        "raised (DoctorConfig.viscosity_raise=3, off by default) and the file each came from")
    args = p.parse_args(argv)
    try:
        first, last = (int(x) for x in args.seeds.split("-"))
    except ValueError:
        raise SystemExit(f"--seeds: FIRST-LAST, two whole numbers, e.g. 10-18; got {args.seeds!r}")
    if first > last:
        raise SystemExit(f"--seeds: FIRST must not exceed LAST; got {args.seeds!r}")
    rows = stored_rows(first, last, varied=args.varied)
    if not rows:
        raise SystemExit(f"no stored benchmark rows for {'varied ' if args.varied else ''}seeds {first}-{last} "
                         f"in {DATA}")
    ok = sum(r["truth"] == r["verdict"] for r in rows)
    print(f"seeds {first}-{last}: {len(rows)} recordings, {ok} named right ({100 * ok / len(rows):.1f} %)")
    # the code each verdict's run was made with: an old run's fits are not the current doctor's
    print(f"  runs by session: {by_session(rows)}")
    sims = by_simulation(rows)
    if not args.varied:  # varied recordings are each a simulation of their own
        every = sum(right == n for right, n in sims.values())
        most = sum(2 * right > n for right, n in sims.values())
        print(f"  {len(sims)} simulations (object, script, truth: its seeds render one simulation): named right "
              f"on every seed {every}, on most seeds {most}")
    B.summarise(rows, stored_floors())
    if args.misses:
        print("\n" + ("objects, scripts and effects" if args.varied else "simulations")
              + " not named right on every seed (named right / recordings)")
        for (obj, script, truth), (right, n) in sorted(sims.items()):
            if right < n:
                print(f"  {obj:6s} {script:14s} {truth:24s} {right} / {n}")
        print("\nwrong verdicts (recording, verdict, stored in)")
        for r in sorted(rows, key=lambda r: r["recording"]):
            if r["truth"] != r["verdict"]:
                print(f"  {r['recording']:45s} {r['verdict']:24s} {r['source']}")
    if args.would_raise:
        print("\nrecordings the doctor with viscosity_raise=3 would fit again with the viscosity's box raised "
              "(verdict, stored in)")
        for r in sorted(rows, key=lambda r: r["recording"]):
            line = _line_of(r)
            why = would_raise(line) if line else ""
            if why:
                print(f"  {r['recording']:45s} {r['verdict']:24s} {r['source']}\n    {why}")
    return 0


def _line_of(row: dict, data: Path = DATA) -> Optional[dict]:
    """The stored line (slim dump or result row) that ``row`` (:func:`stored_rows`) was scored from."""
    return _lines(data / row["source"]).get(row["recording"])


@functools.lru_cache(maxsize=None)
def _lines(path: Path) -> dict:
    """A stored file's lines by recording (the last of each), read once."""
    return {line.get("recording"): line for line in map(json.loads, filter(str.strip, path.read_text().splitlines()))}


if __name__ == "__main__":
    sys.exit(main())
