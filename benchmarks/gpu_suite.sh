#!/usr/bin/env bash
# The GPU measurements in one go, for a machine with a CUDA device and the project installed
# (about 12 minutes on one H100/H200; each part has its own time limit, so a slow part cannot
# eat the others'):
#   1. the GPU tests (tests/project/test_gpu.py: every task, compiled chunks, CUDA graphs,
#      train.py with each loss on CUDA and resumed on the CPU);
#   2. eager throughput of the main tasks up to N = 65536, with and without gradient, and the
#      kernels and synchronisations per step (benchmarks/gpu_throughput.py);
#   3. train.py on HalfCheetah-v5 on CUDA, PPO with massively parallel settings (4096 envs,
#      Brax's discount and entropy), then SHAC with 1024 envs, TRAIN_S seconds each, one after the
#      other so that neither slows the other (stopped by SIGTERM, which ends a run cleanly with a
#      checkpoint); the evaluation curves are in each run's metrics.jsonl;
#   4. HalfCheetah-v5 through compile_physics with CUDA graphs and compiled, with what time is left.
# Usage: bash benchmarks/gpu_suite.sh OUT_DIR     (results and logs under OUT_DIR)
set -u
out=${1:?usage: bash benchmarks/gpu_suite.sh OUT_DIR}
mkdir -p "$out"
start=$(date +%s); elapsed() { echo $(( $(date +%s) - start )); }
export PYTHONUNBUFFERED=1 WANDB_MODE=disabled OMP_NUM_THREADS=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader

echo "== tests ($(elapsed) s)"
timeout "${TEST_S:-150}" python -m pytest -q tests/project/test_gpu.py -n 8 -p no:cacheprovider > "$out/pytest_gpu.txt" 2>&1
echo "pytest exit $?"; grep -E "^FAILED|passed|failed" "$out/pytest_gpu.txt"

echo "== eager throughput ($(elapsed) s)"
timeout "${EAGER_S:-150}" python benchmarks/gpu_throughput.py modes=[eager] \
    tasks=[HalfCheetah-v5,pendulum,Ant-v5,Hopper-v5,Humanoid-v5,Walker2d-v5,cartpole,swimmer] \
    sizes=[4096,16384,65536] steps=8 window=8 budget_s="${EAGER_BUDGET_S:-130}" \
    out="$out/gpu_eager.json" data=gpu_throughput_eager

echo "== train.py on CUDA ($(elapsed) s)"
common="env=HalfCheetah-v5 device=cuda seed=0 logger=csv eval.gif=false train.progress_bar=false
        train.checkpoint_interval=100000000 train.total_env_steps=100000000"
# shellcheck disable=SC2086
timeout -s TERM "${TRAIN_S:-180}" python sota_scripts/train.py $common loss=ppo env.num_envs=4096 \
    loss.rollout_len=20 loss.minibatch_size=10240 loss.epochs=8 loss.lr_schedule=constant loss.gamma=0.95 \
    loss.entropy_coeff=1e-3 eval.interval=3000000 hydra.run.dir="$out/ppo" > "$out/ppo.log" 2>&1
# shellcheck disable=SC2086
timeout -s TERM "${TRAIN_S:-180}" python sota_scripts/train.py $common loss=shac env.num_envs=1024 \
    eval.interval=300000 hydra.run.dir="$out/shac" > "$out/shac.log" 2>&1
for run in ppo shac; do
    echo "$run: env steps, wall s, eval return"
    python - "$out/$run/metrics.jsonl" <<'EOF'
import json, sys
wall = 0.0
for line in open(sys.argv[1]):
    row = json.loads(line)
    wall = row.get("time/wall_s", wall)
    if "eval/return" in row:
        print(f"  {row['env_steps']:>10,d} {wall:7.0f} {row['eval/return']:9.1f}")
EOF
done

echo "== compiled and CUDA graphs ($(elapsed) s)"
left=$(( ${TOTAL_S:-720} - $(elapsed) ))
if [ "$left" -gt 30 ]; then
    timeout "$left" python benchmarks/gpu_throughput.py modes=[cudagraphs,compiled] tasks=[pendulum,HalfCheetah-v5] \
        sizes=[65536] steps=16 window=16 out="$out/gpu_compiled.json" data=gpu_throughput_cudagraphs
fi
echo "== done ($(elapsed) s)"
