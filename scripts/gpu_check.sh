#!/usr/bin/env bash
# The GPU checks of docs/performance.md ("On a GPU"), in one go, on a machine with an NVIDIA GPU
# (driver and OptiX) and undream's dependencies importable by $PYTHON (default python3):
#
#   scripts/gpu_check.sh [OUT_DIR]
#
# 1. which Mitsuba variant undream picks (cuda_ad_rgb expected);
# 2. the one-scene run (examples/runs/bin_orbit_pgd.yaml) with the victim on cuda (where torch sees a
#    GPU), then on the CPU:
#    benchmarks/bench_main_job.py's table of seconds per part;
# 3. the main job (examples/runs/bin_orbit_conditions.yaml, victim on cuda where it can): the same
#    table, whose "process" row is the whole command's time;
# 4. the tests of the gradient's path on that variant (transport against prb, batched frames);
# 5. with a GPU: the main job again with the GPU hidden (llvm_ad_rgb on the same machine's cores), and one
#    iteration at 256 spp (benchmarks/bench_iteration.py) on each: the ratios of one machine.
#
# Everything it prints also goes to OUT_DIR (default build/gpu_check). No GPU: step 1 says why
# (undream falls back to llvm_ad_rgb, and the rest then measures the CPU).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
OUT=${1:-build/gpu_check}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version --format=csv | tee "$OUT/gpu.txt"
"$PY" -c 'import logging; logging.basicConfig(level=logging.INFO)
from undream.variant import mitsuba; print("variant", mitsuba().variant())' 2>&1 | tee "$OUT/variant.txt"
DEVICE=$("$PY" -c 'import torch; print("cuda" if torch.cuda.is_available() else "cpu")')
if [ "$DEVICE" = cuda ]; then
    "$PY" benchmarks/bench_main_job.py --before '' --seeds 0 --device cuda 2>&1 | tee "$OUT/one_scene_victim_cuda.txt"
fi
"$PY" benchmarks/bench_main_job.py --before '' --seeds 0 2>&1 | tee "$OUT/one_scene_victim_cpu.txt"
"$PY" benchmarks/bench_main_job.py --before '' --seeds 0 --config examples/runs/bin_orbit_conditions.yaml \
    --device "$DEVICE" 2>&1 | tee "$OUT/main_job.txt"
"$PY" -m pytest -q -p no:cacheprovider tests/test_gradient_path.py tests/test_batched_frames.py tests/test_transport.py \
    2>&1 | tail -30 | tee "$OUT/tests.txt"
if [ "$DEVICE" = cuda ]; then
    CUDA_VISIBLE_DEVICES= "$PY" benchmarks/bench_main_job.py --before '' --seeds 0 \
        --config examples/runs/bin_orbit_conditions.yaml 2>&1 | tee "$OUT/main_job_cpu.txt"
    "$PY" benchmarks/bench_iteration.py --sim-spp 256 --grad-spp 64 --iterations 2 \
        2>&1 | tee "$OUT/iteration256_gpu.txt"
    CUDA_VISIBLE_DEVICES= "$PY" benchmarks/bench_iteration.py --sim-spp 256 --grad-spp 64 --iterations 2 \
        2>&1 | tee "$OUT/iteration256_cpu.txt"
fi
