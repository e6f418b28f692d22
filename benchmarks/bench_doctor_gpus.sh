#!/usr/bin/env bash
# usage (from the repository's root, on a machine with GPUs): OUT=DIR bash benchmarks/bench_doctor_gpus.sh BUDGET_S PER_GPU PROBLEMS...
# Diagnoses every PROBLEMS/*.pkl.gz (bench_doctor.py --make's problems, gzipped), largest first, from one queue:
# PER_GPU processes on each GPU, each taking the next recording when it is done; nothing is started with under
# 100 s of BUDGET_S left, and every process is stopped at its end. Rows in $OUT/rows.jsonl, slim dumps (what
# `bench_doctor.py --rescore` reads) in $OUT/slim.jsonl, each process's wall time in $OUT/times.txt.
# SITE: a folder of installed packages to put first on PYTHONPATH (default /tmp/site); DOCTOR_ARGS: more flags of
# bench_doctor.py (e.g. --trimmed-body).
# Session 37 ran it on 4 H200s: `bash benchmarks/bench_doctor_gpus.sh 540 5 .dd11` (benchmarks/RESULTS.md).
export PYTHONPATH=${SITE:-/tmp/site}:$PWD PYTHONUNBUFFERED=1
if [ $# -lt 3 ] || ! [[ "$1" =~ ^[0-9]+$ && "$2" =~ ^[1-9][0-9]*$ ]] || [ -z "$OUT" ]; then
  echo "usage: OUT=DIR bash benchmarks/bench_doctor_gpus.sh BUDGET_S PER_GPU PROBLEMS... (BUDGET_S, PER_GPU: whole" \
       "numbers, PER_GPU at least 1; got '$1' '$2'; OUT='$OUT')" >&2
  exit 2
fi
B=$1; K=$2; shift 2
END=$(($(date +%s) + B))
export W=$(mktemp -d)  # this run's own working folder: nothing outside it and $OUT is written
mkdir -p $W/res $W/logs $W/one $W/dump "$OUT"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader > $OUT/gpu.txt
for d in "$@"; do ls $d/*.pkl.gz; done | xargs ls -S > $W/q
touch $W/notrun
NG=$(nvidia-smi -L | wc -l)
worker () {  # gpu
  while true; do
    f=$(flock $W/q.lock bash -c 'f=$(head -n 1 $W/q); [ -n "$f" ] && sed -i 1d $W/q; echo "$f"')
    [ -z "$f" ] && return
    left=$((END - $(date +%s)))
    if [ $left -lt 100 ]; then echo "$f" >> $W/notrun; continue; fi
    n=$(basename $f .pkl.gz); mkdir -p $W/one/$n; gunzip -c $f > $W/one/$n/$n.pkl
    s=$(date +%s)
    timeout $left python3 benchmarks/bench_doctor.py --problems $W/one/$n --device cuda:$1 --iters 6 --popsize 8 \
      --view-bodies $DOCTOR_ARGS --dump $W/dump --jsonl $W/res/$n.jsonl > $W/logs/$n.log 2>&1
    echo "$n gpu $1 rc $? process $(( $(date +%s) - s )) s" >> $W/times.txt
  done
}
for g in $(seq 0 $((NG - 1))); do for k in $(seq 1 $K); do worker $g & done; done
wait
python3 - <<'PY'
import json, glob, os
keys = ["base", "base_bound_check", "candidates", "clock", "confidence", "effect", "effect_before_variants", "first_elsewhere", "first_on", "grid",
        "implausible", "indistinguishable_from", "noise_sigma_m", "not_ruled_out", "notes", "parted", "reason", "recording", "schema",
        "split",
        "viscosity_box_raised",
        "script", "signature_m",
        "stage_wall_s",
        "truth", "uncertainty", "identifiability", "variants", "wall_s"]
with open(os.environ["OUT"] + "/slim.jsonl", "w") as f:
    for p in sorted(glob.glob(os.environ["W"] + "/dump/*.json")):
        r = json.load(open(p))
        s = {k: r.get(k) for k in keys}
        s["signature_check"] = (r.get("evidence") or {}).get("signature_check")
        # the base model's and the verdict's summary features (pieces, slip, ...) and the controls' lag
        s["features"] = (r.get("evidence") or {}).get("features")
        s["features_with_effect"] = (r.get("evidence") or {}).get("features_with_effect")
        s["control_lag"] = r.get("control_lag")
        s["heldout_per_frame"] = r.get("heldout_per_frame")  # per-frame losses: a later rule's bootstrap can rescore
        if "rounds" in r:  # --rounds: the later rounds' summaries (each one's whole result is in the dump)
            s["effects"], s["signatures"] = r["effects"], r.get("signatures")
            s["rounds"] = [{k: v for k, v in x.items() if k != "result"} for x in r["rounds"]]
        f.write(json.dumps(s) + "\n")
PY
cat $W/res/*.jsonl > $OUT/rows.jsonl 2>/dev/null
cp $W/times.txt $OUT/times.txt 2>/dev/null
echo "not run: $(wc -l < $W/notrun)"; cat $W/notrun
for l in $W/logs/*.log; do grep -q "held-out Chamfer reduction" $l || { echo "== $l"; grep -v "^Warp\|Module\|^$" $l | tail -n 3; }; done
grep -h "held-out Chamfer reduction" $W/logs/*.log | cut -c1-160
