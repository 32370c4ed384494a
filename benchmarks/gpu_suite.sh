#!/usr/bin/env bash
# The GPU measurements in one go, for a machine with a CUDA device and the project importable
# (about 9 minutes with the default limits; each part has its own time limit, so a slow part cannot
# eat the others'):
#   1. the GPU tests (tests/project/test_gpu.py: every task, compiled chunks, CUDA graphs, the
#      synchronisations of one env step, train.py with each loss on CUDA and resumed on the CPU);
#   2. eager throughput at N = 65536 of HalfCheetah-v5 (MuJoCo's contact model, recompute_in_backward)
#      and the Ant, with and without gradient (16-step BPTT windows, peak memory), and the kernels
#      and synchronisations per step with the lines that synchronise (benchmarks/gpu_throughput.py);
#   3. train.py on HalfCheetah-v5 on CUDA, scored in MuJoCo: PPO with massively parallel settings,
#      then the gradient learner GRAD_LOSS (default ahac), TRAIN_S seconds each (PPO_S, GRAD_S for
#      one), one after the other (benchmarks/gpu_training.py: the time to tuned PPO's final MuJoCo
#      return in the CPU race); each run's metrics.jsonl is copied to OUT_DIR/<loss>_metrics.jsonl;
#   4. HalfCheetah-v5 compiled and with CUDA graphs, with what is left of TOTAL_S.
# PARTS names the parts to run (default: tests eager train compiled); HOTSPOTS=K adds to the eager
# diagnostics the K source lines that take the most GPU time in one env step; COMPILED_MODES and
# COMPILED_KINDS choose the compiled cells (default: cudagraphs,compiled and rollout).
# Every result is a flat file directly under OUT_DIR (suite.log holds the summary).
# Usage: bash benchmarks/gpu_suite.sh OUT_DIR
set -u
out=${1:?usage: bash benchmarks/gpu_suite.sh OUT_DIR}
mkdir -p "$out"
work=$(mktemp -d)
start=$(date +%s); elapsed() { echo $(( $(date +%s) - start )); }
export PYTHONUNBUFFERED=1 WANDB_MODE=disabled OMP_NUM_THREADS=1
py=${PYTHON:-python3}
parts=" ${PARTS:-tests eager train compiled} "
run_part() { [[ "$parts" == *" $1 "* ]]; }
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
"$py" -c "import torch, torchrl, tensordict; print('torch', torch.__version__, 'torchrl', torchrl.__version__, 'tensordict', tensordict.__version__)"

if run_part tests; then
echo "== tests ($(elapsed) s)"
# -v writes each test's outcome as it ends, so a run stopped at its limit still names what failed
timeout "${TEST_S:-150}" "$py" -m pytest -v tests/project/test_gpu.py -n 8 -p no:cacheprovider --timeout=120 \
    --tb=short -rfE > "$out/pytest_gpu.txt" 2>&1
echo "pytest exit $?"; grep -E "(FAILED|ERROR)|passed|failed" "$out/pytest_gpu.txt" | tail -40
fi

if run_part eager; then
echo "== eager throughput ($(elapsed) s)"
timeout "${EAGER_S:-170}" "$py" benchmarks/gpu_throughput.py modes=[eager] \
    "tasks=[${EAGER_TASKS:-HalfCheetah-v5:recompute,Ant-v5}]" \
    "sizes=[${EAGER_SIZES:-65536}]" steps=8 window=16 repeats=1 budget_s="${EAGER_BUDGET_S:-150}" \
    hotspots="${HOTSPOTS:-0}" out="$out/gpu_eager.json" data=none
fi

if run_part train; then
echo "== train.py on CUDA ($(elapsed) s)"
grad=${GRAD_LOSS:-ahac}
ppo_s=${PPO_S:-${TRAIN_S:-100}} grad_s=${GRAD_S:-${TRAIN_S:-100}}
# each run: its seconds, up to 60 s to end after SIGTERM, and its start
timeout $(( ppo_s + grad_s + 240 )) "$py" benchmarks/gpu_training.py "learners=[ppo,$grad]" \
    "seconds=[ppo=$ppo_s,$grad=$grad_s]" train_dir="$work/train" out="$out/gpu_training.json" data=none
for run in ppo "$grad"; do
    cp "$work/train/$run/metrics.jsonl" "$out/${run}_metrics.jsonl" 2>/dev/null
    cat "$work/train/$run.log" >> "$out/train.log" 2>/dev/null
done
fi

left=$(( ${TOTAL_S:-540} - $(elapsed) ))
if run_part compiled && [ "$left" -gt 30 ]; then
    echo "== compiled and CUDA graphs ($(elapsed) s)"
    timeout "$left" "$py" benchmarks/gpu_throughput.py "modes=[${COMPILED_MODES:-cudagraphs,compiled}]" tasks=[HalfCheetah-v5] \
        "kinds=[${COMPILED_KINDS:-rollout}]" sizes=[65536] steps=16 window=16 budget_s=$(( left - 10 )) out="$out/gpu_compiled.json" data=none
fi
echo "== done ($(elapsed) s)"
