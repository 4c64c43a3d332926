#!/usr/bin/env bash
# The GPU measurements of the `cuda` build, in two parts that each fit one short visit to a
# GPU machine (the numbers in docs/performance.md and docs/time-to-quality.md come from
# here). Build first with scripts/build-cuda.sh, strip, and put the binary at $OSRT_BIN.
#
#   bench/gpu_check.sh train   # check-device, then time to quality (clevr-lite-gpu) beside
#                              # 1,000 steps of clevr-lite-cpu in f32 and in bf16
#   bench/gpu_check.sh bench   # train-step time against PyTorch eager, same cases, f32 and bf16
#
# Results go to $OUT (default target/gpu-check). The CUDA 13 libraries are taken from the
# machine's PyTorch (site-packages/nvidia/*/lib); the driver's libcuda.so.1 from the system.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${OUT:-target/gpu-check}"
BIN="${OSRT_BIN:-target/release/osrt}"
TTQ_MINUTES="${TTQ_MINUTES:-10}"
mkdir -p "$OUT"
LOG="$OUT/log-${1:-none}.txt"
exec > >(tee -a "$LOG") 2>&1

SITE="$(python3 -c 'import os, torch; print(os.path.dirname(os.path.dirname(torch.__file__)))')"
LIBS="$(ls -d "$SITE"/nvidia/*/lib 2>/dev/null | tr '\n' ':')"
export LD_LIBRARY_PATH="${LIBS}${LD_LIBRARY_PATH:-}"
export RUST_LOG="${RUST_LOG:-warn}"
echo "== $(date -u +%FT%TZ) $1 on $(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader)"
if ldd "$BIN" | grep "not found"; then
    echo "missing libraries: stop"
    exit 1
fi

case "${1:-}" in
train)
    # 1. The default dataset (20,000 scenes at 32 px, what `osrt train` generates into
    #    ./data), on the CPU while the GPU is checked.
    if [ ! -f data/manifest.json ]; then
        "$BIN" data generate --preset clevr-lite --image-size 32 --train 20000 --val 100 \
            --test 100 --out data >/dev/null &
        gen=$!
    fi
    # 2. Correctness first: a device path that fails outright ends the visit early.
    timeout 180 "$BIN" check-device --json >"$OUT/check.json"
    echo "check-device rc $?"
    cat "$OUT/check.json"
    if ! grep -q '"pass"' "$OUT/check.json"; then
        echo "check-device gave no result: stop"
        exit 1
    fi
    # Waits name their processes: a bare `wait` also waits for the `tee` above, forever.
    [ -n "${gen:-}" ] && wait "$gen"
    # 3. Time to quality, and beside it (sharing the GPU for their first minute or two)
    #    1,000 steps of the CPU preset in f32 and in bf16 for the loss curves.
    limit=$(python3 -c "print(int($TTQ_MINUTES * 60 + 90))")
    timeout "$limit" "$BIN" train --preset clevr-lite-gpu --max-minutes "$TTQ_MINUTES" \
        --eval-every-s 60 --run runs/gpu-ttq >"$OUT/ttq.txt" 2>&1 &
    pids=($!)
    for p in f32 bf16; do
        timeout "$limit" "$BIN" train --preset clevr-lite-cpu --device cuda --precision "$p" --workers 1 \
            --threads 2 --max-steps 1000 --eval-every-s 100000 --run "runs/gpu-1000-$p" \
            >"$OUT/steps-$p.txt" 2>&1 &
        pids+=($!)
    done
    wait "${pids[@]}"
    # The curves first: they must come back even if the evaluation below runs out of time.
    tar czf "$OUT/runs.tgz" runs/*/metrics.jsonl runs/*/config.toml runs/*/run.json
    "$BIN" eval --run runs/gpu-ttq --split test --device cuda --json >"$OUT/ttq-test.json"
    cat "$OUT/ttq.txt" "$OUT/ttq-test.json"
    ;;
bench)
    # Side by side, same cases, one after the other on the same GPU.
    common=(--device cuda --steps 10 --step-only)
    for prec in f32 bf16; do
        "$BIN" bench model "${common[@]}" --precision "$prec" --presets clevr-lite-cpu \
            --batch-size 16 --out "$OUT/osrt-lite16-$prec.json"
        "$BIN" bench model "${common[@]}" --precision "$prec" --presets clevr-lite-cpu \
            --batch-size 256 --out "$OUT/osrt-lite256-$prec.json"
        "$BIN" bench model "${common[@]}" --precision "$prec" --presets paper --image-size 128 \
            --batch-size 32 --input-views 1 --rays-per-scene 8192 --out "$OUT/osrt-paper1-$prec.json"
        "$BIN" bench model "${common[@]}" --precision "$prec" --presets paper --image-size 128 \
            --batch-size 32 --input-views 5 --rays-per-scene 2304 --out "$OUT/osrt-paper5-$prec.json"
    done
    python3 bench/torch_step.py --device cuda --presets clevr-lite-cpu --batch-size 16,256 \
        --dtypes f32,bf16 --no-render --out "$OUT/torch-lite.json"
    python3 bench/torch_step.py --device cuda --presets paper --batch-size 32 --image-size 128 \
        --cases 1x8192,5x2304 --dtypes f32,bf16 --no-render --out "$OUT/torch-paper.json"
    tar czf "$OUT/osrt-bench.tgz" "$OUT"/osrt-*.json && rm -f "$OUT"/osrt-*.json
    ;;
*)
    echo "usage: bench/gpu_check.sh train|bench"
    exit 2
    ;;
esac
