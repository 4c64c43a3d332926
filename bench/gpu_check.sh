#!/usr/bin/env bash
# The GPU measurements of the `cuda` build, in two parts that each fit one short visit to a
# GPU machine (the numbers in docs/performance.md and docs/time-to-quality.md come from
# here). Build first with scripts/build-cuda.sh, strip, and put the binary at $OSRT_BIN.
#
#   bench/gpu_check.sh train   # check-device, then time to quality (clevr-lite-gpu) beside
#                              # 1,000 steps of clevr-lite-cpu in f32 and in bf16
#   bench/gpu_check.sh bench   # train-step time against PyTorch eager, same cases, f32 and bf16
#   bench/gpu_check.sh memory  # check-device (ops and steps), then the paper preset's peak
#                              # device memory and step time beside PyTorch, and the small model
#   bench/gpu_check.sh profile # the time of each op kind, forward and backward, beside the
#                              # PyTorch profiler's table: paper preset and clevr-lite-cpu b256
#   bench/gpu_check.sh workers # two workers sharing the GPU (`osrt train --workers 2`),
#                              # paper preset: each step's gradients and all-reduce time
#                              # (the gradient staged through page-locked memory), beside
#                              # one worker's step and its staged round trip (≤ 560 s of
#                              # timeouts; WORKERS_PRECISIONS=bf16 for one precision)
#   bench/gpu_check.sh visit   # one call of a short visit, most important first: the
#                              # plumbing, ops and steps against the CPU, the paper preset's
#                              # four step cases (1 view 8,192 rays and 5 views 2,304, f32
#                              # and bf16: time, peak memory), keeping and recomputing the
#                              # activations (--recompute), beside PyTorch, and the 1-view
#                              # bf16 step's memory at each phase (560 s of timeouts;
#                              # the paper preset at batch 32 on an H200, 16 on a card under
#                              # 100 GiB: ask for nvidia-h200 to compare with the earlier
#                              # H200 figures)
#   bench/gpu_check.sh lite    # both sides' profiles of the paper preset's 1-view bf16 step,
#                              # the small model's four step cases beside PyTorch: a second
#                              # short call after `visit` (290 s of timeouts)
#   bench/gpu_check.sh kernels # each GPU kernel's time in the paper preset's 1-view step
#                              # at batch 32 under Nsight Compute (`ncu`), summed by name
#                              # (bench/ncu_kernels.py; ≤ 400 s of timeouts, untried: the
#                              # first call tells whether ncu works on the machine)
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

# Where PyTorch is installed, without importing it (seconds on a fresh machine).
SITE="$(python3 -c 'import importlib.util as u, os; print(os.path.dirname(os.path.dirname(u.find_spec("torch").origin)))')"
LIBS="$(ls -d "$SITE"/nvidia/*/lib 2>/dev/null | tr '\n' ':')"
export LD_LIBRARY_PATH="${LIBS}${LD_LIBRARY_PATH:-}"
export RUST_LOG="${RUST_LOG:-warn}"
echo "== $(date -u +%FT%TZ) ${1:-} on $(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader)"
if [ ! -x "$BIN" ]; then
    echo "no osrt binary at $BIN (OSRT_BIN): stop"
    exit 1
fi
if ldd "$BIN" | grep "not found"; then
    echo "missing libraries: stop"
    exit 1
fi

# The plumbing, ops and steps of `check-device` against the CPU within $1 seconds. Plain
# text, printed as each check ends: a timeout or a failing step keeps what came before.
check_device() {
    timeout "$1" "$BIN" check-device --presets tiny,clevr-lite-cpu 2>&1 | tee "$OUT/check.txt"
    echo "check-device rc ${PIPESTATUS[0]}"
}

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
memory)
    # The paper's model at batch 32: the ops one by one and the whole step against the CPU
    # first, then peak device memory and step time beside PyTorch eager, same cases.
    check_device 240
    paper=(--device cuda --steps 5 --step-only --presets paper --image-size 128 --batch-size 32)
    for vr in "1 8192" "5 2304"; do
        set -- $vr
        for prec in f32 bf16; do
            echo "== osrt paper ${1}x$2 $prec fused"
            timeout 150 "$BIN" bench model "${paper[@]}" --input-views "$1" --rays-per-scene "$2" \
                --precision "$prec" --kernels fused --out "$OUT/osrt-paper$1-$prec.json" 2>&1 | tail -n 6
        done
    done
    timeout 200 python3 bench/torch_step.py --device cuda --presets paper --batch-size 32 --image-size 128 \
        --cases 1x8192,5x2304 --dtypes f32,bf16 --steps 5 --no-render --out "$OUT/torch-paper.json" 2>&1 | tail -n 8
    echo "== osrt paper 1x8192 f32 composed (candle's graph, for the one-node ops' share)"
    timeout 120 "$BIN" bench model "${paper[@]}" --input-views 1 --rays-per-scene 8192 --precision f32 \
        --kernels composed --out "$OUT/osrt-paper1-f32-composed.json" 2>&1 | tail -n 6
    lite=(--device cuda --steps 10 --step-only --presets clevr-lite-cpu --kernels fused)
    for prec in f32 bf16; do
        for b in 16 256; do
            echo "== osrt clevr-lite-cpu b$b $prec"
            timeout 60 "$BIN" bench model "${lite[@]}" --precision "$prec" --batch-size "$b" \
                --out "$OUT/osrt-lite$b-$prec.json" 2>&1 | tail -n 4
        done
    done
    timeout 120 python3 bench/torch_step.py --device cuda --presets clevr-lite-cpu --batch-size 16,256 \
        --dtypes f32,bf16 --no-render --out "$OUT/torch-lite.json" 2>&1 | tail -n 8
    ;;
profile)
    # Where each side's step goes, op by op (the tables that choose the next kernel):
    # osrt's op calls timed alone (`--profile`), PyTorch's ops under its profiler.
    for prec in f32 bf16; do
        echo "== osrt profile paper 1x8192 b32 $prec"
        timeout 150 "$BIN" bench model --device cuda --profile --steps 3 --presets paper \
            --image-size 128 --batch-size 32 --input-views 1 --rays-per-scene 8192 \
            --precision "$prec" --out "$OUT/profile-paper1-$prec.json" 2>&1 | tail -n 24
        echo "== osrt profile clevr-lite-cpu b256 $prec"
        timeout 60 "$BIN" bench model --device cuda --profile --steps 5 --presets clevr-lite-cpu \
            --batch-size 256 --precision "$prec" --out "$OUT/profile-lite256-$prec.json" 2>&1 | tail -n 24
    done
    timeout 150 python3 bench/torch_step.py --device cuda --profile --presets paper --batch-size 32 \
        --image-size 128 --cases 1x8192 --dtypes f32,bf16 --steps 3 --no-render \
        --out "$OUT/torch-profile-paper.json" 2>&1 | tail -n 72
    timeout 90 python3 bench/torch_step.py --device cuda --profile --presets clevr-lite-cpu \
        --batch-size 256 --dtypes f32,bf16 --steps 5 --no-render \
        --out "$OUT/torch-profile-lite.json" 2>&1 | tail -n 72
    ;;
workers)
    # A 128 px dataset for the paper preset (seconds on the host's cores).
    if [ ! -f data128/manifest.json ]; then
        timeout 60 "$BIN" data generate --preset clevr-lite --image-size 128 --train 64 --val 4 \
            --test 4 --out data128 >/dev/null
    fi
    # Global batch 8: two processes' steps fit an H100's memory as well as an H200's.
    # WORKERS_PRECISIONS="bf16" halves the call (about 280 s a precision at most).
    for prec in ${WORKERS_PRECISIONS:-bf16 f32}; do
        echo "== osrt train paper, 2 workers on one GPU, batch 8 (4 each), 1 view, 8192 rays, $prec"
        rm -rf "runs/workers-$prec"
        # -k: `osrt train` waits up to 30 s for its coordinator after a SIGTERM.
        RUST_LOG=osrt_worker=debug,warn timeout -k 10 150 "$BIN" train --preset paper --data data128 \
            --device cuda --workers 2 --precision "$prec" --batch-size 8 --rays-per-scene 8192 \
            --max-steps 8 --eval-every-s 100000 --eval-scenes 2 --skip-memory-check \
            --run "runs/workers-$prec" \
            >"$OUT/workers-$prec.txt" 2>&1
        echo "train rc $?"
        python3 bench/worker_steps.py "$OUT/workers-$prec.txt"
        echo "== osrt paper, one worker's step at batch 4 and the staged round trip, $prec"
        timeout 60 "$BIN" bench model --device cuda --step-only --presets paper --image-size 128 \
            --batch-size 4 --input-views 1 --rays-per-scene 8192 --steps 5 --precision "$prec" \
            --out "$OUT/osrt-paper1-b4-$prec.json" 2>&1 | tail -n 6
    done
    ;;
visit)
    check_device 90
    # The paper preset's step at batch 32 peaked at 71–90 GiB (docs/gpu.md, older build):
    # on a card under 100 GiB (an H100) both sides run at batch 16 instead.
    mib="$(nvidia-smi --query-gpu=memory.total --format=csv,noheader,nounits | head -n 1)"
    pb=32
    [ "${mib:-0}" -lt 100000 ] && pb=16
    echo "== paper preset at batch $pb (${mib} MiB card)"
    paper=(--device cuda --step-only --presets paper --image-size 128 --batch-size "$pb")
    # The four step cases of docs/gpu.md's memory table, osrt then PyTorch, time and peak memory; then
    # the same with the activations made again in the backward pass (`--recompute`).
    for rc in "" --recompute; do
        for vr in "1 8192" "5 2304"; do
            set -- $vr
            for prec in f32 bf16; do
                echo "== osrt paper ${1}x$2 $prec $rc"
                timeout 40 "$BIN" bench model "${paper[@]}" --input-views "$1" --rays-per-scene "$2" \
                    --steps 5 --precision "$prec" $rc --out "$OUT/osrt-paper$1-$prec$rc.json" 2>&1 |
                    tail -n 6
            done
        done
    done
    # Which phase holds the peak: each step's memory at its phases (debug log; GiB).
    echo "== osrt paper 1x8192 bf16, memory by phase"
    RUST_LOG=osrt_trainer=debug timeout 50 "$BIN" bench model "${paper[@]}" --input-views 1 \
        --rays-per-scene 8192 --steps 2 --precision bf16 --out "$OUT/osrt-phases-bf16.json" 2>&1 |
        grep -E "train step gradients|apply and drop" | tail -n 4
    timeout 100 python3 bench/torch_step.py --device cuda --presets paper --batch-size "$pb" \
        --image-size 128 --cases 1x8192,5x2304 --dtypes f32,bf16 --steps 5 --no-render \
        --out "$OUT/torch-paper.json" 2>&1 | tail -n 8
    ;;
lite)
    # Where osrt's bf16 step goes, beside PyTorch's profiler on the same case (the paper
    # preset at batch 32), then the small model's four cases beside PyTorch: a second,
    # short call after `visit`.
    echo "== osrt profile paper 1x8192 bf16"
    paper=(--device cuda --step-only --presets paper --image-size 128 --batch-size 32)
    timeout 60 "$BIN" bench model "${paper[@]}" --input-views 1 --rays-per-scene 8192 --profile \
        --steps 2 --precision bf16 --out "$OUT/profile-paper1-bf16.json" 2>&1 | tail -n 30
    timeout 50 python3 bench/torch_step.py --device cuda --profile --presets paper --batch-size 32 \
        --image-size 128 --cases 1x8192 --dtypes bf16 --steps 2 --no-render \
        --out "$OUT/torch-profile-paper.json" 2>&1 | tail -n 36
    lite=(--device cuda --steps 10 --step-only --presets clevr-lite-cpu)
    for prec in f32 bf16; do
        for b in 16 256; do
            echo "== osrt clevr-lite-cpu b$b $prec"
            timeout 30 "$BIN" bench model "${lite[@]}" --precision "$prec" --batch-size "$b" \
                --out "$OUT/osrt-lite$b-$prec.json" 2>&1 | tail -n 4
        done
    done
    timeout 60 python3 bench/torch_step.py --device cuda --presets clevr-lite-cpu --batch-size 16,256 \
        --dtypes f32,bf16 --no-render --out "$OUT/torch-lite.json" 2>&1 | tail -n 8
    ;;
kernels)
    # Each kernel's GPU time in the paper preset's 1-view bf16 step at batch 32 (Nsight
    # Compute, one metric, launches serialised: 3 steps, the 2 warm-up ones included),
    # summed by kernel name: what inside the MLP and attention nodes takes the time.
    NCU="$(command -v ncu || ls /opt/nvidia/nsight-compute/*/ncu 2>/dev/null | head -n 1)"
    for prec in ${KERNELS_PRECISIONS:-bf16 f32}; do
        echo "== ncu osrt paper 1x8192 $prec"
        timeout 200 "$NCU" --clock-control none --cache-control none --metrics gpu__time_duration.sum \
            --csv --page details --log-file "$OUT/ncu-paper1-$prec.csv" \
            "$BIN" bench model --device cuda --step-only --presets paper --image-size 128 \
            --batch-size 32 --input-views 1 --rays-per-scene 8192 --steps 1 --precision "$prec" \
            --out "$OUT/osrt-ncu-$prec.json" 2>&1 | tail -n 4
        python3 bench/ncu_kernels.py "$OUT/ncu-paper1-$prec.csv" --steps 3 --top 40
        gzip -f "$OUT/ncu-paper1-$prec.csv"
    done
    ;;
*)
    echo "usage: bench/gpu_check.sh train|bench|memory|profile|workers|visit|lite|kernels"
    exit 2
    ;;
esac
