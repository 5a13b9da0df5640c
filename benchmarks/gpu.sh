#!/usr/bin/env bash
# The whole GPU check (issue 44) in one command, under 8 minutes on one GPU; everything it prints and writes lands in
# $OUT (default benchmarks/gpu_out/):
#   machine.txt      the GPU, its driver, jax and mujoco versions
#   cpu2.json/.txt   the self-ID step against the bandwidth bound on 2 of this machine's CPU cores (the CPU row)
#   bandwidth.json/.txt  the self-ID step on the default device (the GPU) at 1,000,000 estimators: its traffic per
#                    estimator and sample (the state's minimum and XLA's count) and its fraction of the bound (a
#                    streaming copy of the state's size), both steps (closed form, rank-one block)
#   lowering.txt     tests/test_cuda_lowering.py, now on the real CUDA backend (host callbacks lowered too)
#   sweeps.txt       valid_region_ur5e and ablation_ur5e run by the CLI on the default device (no flag) and on the
#                    CPU, compared by scripts/compare_runs.py
#   results.json     benchmarks/run_all.py --gpu-scale with the time left as its --budget: every row with its device,
#                    rewritten after each
#   run_all.log      its output (the table at the end, also as Markdown)
# GPU_SH_SECONDS (default 470) bounds the whole script: each step gets at most the time left.
# Before: `bash benchmarks/gpu_wheels.sh` where an index is reachable, and carry .whl to the GPU machine (a machine
# with every dependency installed needs none). Each step has its own time limit; a step that fails is reported and
# the next still runs. See docs/benchmarks.md ("Running on a GPU").
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${OUT:-benchmarks/gpu_out}"
mkdir -p "$OUT"
PY="${PYTHON:-python3}"
if [ -d .whl ] && ls .whl/*.whl >/dev/null 2>&1; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        || { echo "gpu.sh: installing .whl/ failed" >&2; exit 1; }
    export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
# `python -P -m ...` below: the installed package, not the checkout's selfid_jax/ (which holds no experiments/; an
# editable install maps them, a wheel holds them)
export SELFID_JAX_NO_XLA_FLAGS=1 PYTHONUNBUFFERED=1 MUJOCO_GL=egl
T0=$(date +%s)
DEADLINE=$(( T0 + ${GPU_SH_SECONDS:-470} ))  # the whole script, every step included
step() { echo "== $1 ($(( $(date +%s) - T0 )) s)"; }
left() { local l=$(( DEADLINE - $(date +%s) )); [ "$l" -lt "$1" ] && echo "$l" || echo "$1"; }  # min(limit, left)

step machine
{ date -u; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1;
  "$PY" -c "import jax, jaxlib; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, jax.devices())";
  "$PY" -c "import mujoco; from mujoco import mjx; print('mujoco', mujoco.__version__)";
  "$PY" -c "import mujoco_warp, warp; print('mujoco_warp', getattr(mujoco_warp, '__version__', '?'), 'warp', warp.__version__)" 2>&1 | tail -1;
  "$PY" -c "import selfid_jax; print('selfid_jax', selfid_jax.__file__)"; } 2>&1 | tee "$OUT/machine.txt"

step "the 2-core CPU row (bandwidth bound, 10,000 estimators)"
SELFID_JAX_NO_XLA_FLAGS=0 JAX_PLATFORMS=cpu timeout "$(left 120)" taskset -c 0,1 "$PY" benchmarks/bandwidth.py --batch 10000 \
    --json "$OUT/cpu2.json" 2>&1 | tee "$OUT/cpu2.txt"

step "the step's traffic and fraction of the bound on the default device (1,000,000 estimators)"
timeout "$(left 120)" "$PY" benchmarks/bandwidth.py --batch 1000000 --copy-mib 2048 --reps 3 --rounds 2 \
    --json "$OUT/bandwidth.json" 2>&1 | tee "$OUT/bandwidth.txt"

step "lowering check on the CUDA backend"
timeout "$(left 60)" "$PY" -P -m pytest -q -p no:cacheprovider -o addopts="" tests/test_cuda_lowering.py 2>&1 | tail -15 \
    | tee "$OUT/lowering.txt"

step "sweeps: default device against the CPU"
{ for cfg in valid_region_ur5e ablation_ur5e; do
    timeout "$(left 45)" "$PY" -P -m selfid_jax.cli sweep "$cfg" --out "/tmp/gpu_sweeps/$cfg/default" --fresh \
        --no-progress | tail -3
    JAX_PLATFORMS=cpu SELFID_JAX_NO_XLA_FLAGS=0 timeout "$(left 60)" "$PY" -P -m selfid_jax.cli sweep "$cfg" \
        --out "/tmp/gpu_sweeps/$cfg/cpu" --fresh --no-progress | tail -1
    "$PY" scripts/compare_runs.py "/tmp/gpu_sweeps/$cfg/default" "/tmp/gpu_sweeps/$cfg/cpu"
  done; } 2>&1 | tee "$OUT/sweeps.txt"

step "run_all --gpu-scale"
BUDGET=$(( $(left 600) - 40 ))
timeout "$(left 600)" "$PY" benchmarks/run_all.py --gpu-scale --budget "$BUDGET" --out "$OUT/results.json" \
    --markdown 2>&1 | tee "$OUT/run_all.log"
step done
