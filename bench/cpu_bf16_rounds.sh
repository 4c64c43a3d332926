#!/usr/bin/env bash
# Side by side on one CPU host, alternating, ROUNDS rounds: osrt's train step in f32 and
# bf16 (`osrt bench model --step-only --precision P`) and PyTorch's mirror in f32 and bf16
# autocast (`bench/torch_step.py --dtypes f32,bf16`), at 1 and 2 threads. Prints one line
# per run and case; the JSON of every run stays in OUT (default target/bench/rounds).
#
#   bench/cpu_bf16_rounds.sh [ROUNDS] [extra `osrt bench model` / torch_step.py args…]
#   OSRT=path/to/osrt PYTHON=path/to/python bench/cpu_bf16_rounds.sh 4
#
# Extra arguments go to both sides (the shape flags both take: --presets, --batch-size,
# --image-size, --rays-per-scene, --steps).
set -euo pipefail
cd "$(dirname "$0")/.."
ROUNDS=${1:-4}
shift || true
OSRT=${OSRT:-target/release/osrt}
PYTHON=${PYTHON:-python3}
OUT=${OUT:-target/bench/rounds}
mkdir -p "$OUT"
lscpu | grep "Model name"
for f in amx_bf16 avx512_bf16; do
    if grep -qw "$f" /proc/cpuinfo; then echo "$f: yes"; else echo "$f: no"; fi
done
for r in $(seq 1 "$ROUNDS"); do
    for p in f32 bf16; do
        "$OSRT" bench model --step-only --threads 1,2 --precision "$p" --out "$OUT/osrt-$p-$r.json" "$@" >/dev/null
        "$PYTHON" - "$OUT/osrt-$p-$r.json" "$r" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
for t, v in sorted(d.items()):
    for s in v["steps"] if "steps" in v else [v]:
        print(f"round {sys.argv[2]} osrt  {s.get('precision', '?'):>4} {t}t {s['median_step_s'] * 1e3:8.1f} ms")
PY
    done
    "$PYTHON" bench/torch_step.py --threads 1,2 --dtypes f32,bf16 --no-render \
        --out "$OUT/torch-$r.json" "$@" >/dev/null
    "$PYTHON" - "$OUT/torch-$r.json" "$r" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
for k, v in d.items():
    if isinstance(v, dict) and "median_step_s" in v:
        print(f"round {sys.argv[2]} torch {v['dtype']:>4} {k}: {v['median_step_s'] * 1e3:8.1f} ms")
PY
done
