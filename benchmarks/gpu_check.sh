#!/usr/bin/env bash
# The GPU checks of device=cuda and compile=true, for a session that has a CUDA GPU (at most 8 minutes: the
# steps' time limits add up to 480 s). Run from the repository root:   bash benchmarks/gpu_check.sh
# Results land in $OUT (default ./gpu_check_out): gpu_check.log (each step's command, exit code and time), gpu.txt
# (the GPU and the versions in use), one log per step, the benchmarks' records (bench_compile.json, ...), the tiny
# run's summary.json and the FQE records; the batch and the run themselves stay in a scratch directory. With
# GPU_CHECK_BUNDLE=1 all but gpu_check.log and gpu.txt go into one archive, gpu_check_records.tar.gz (for a machine
# that hands back only a few files).
#   1. tests/test_compile.py on cuda: no host reads between log points (and torch.cuda.set_sync_debug_mode("error")),
#      tensors made on the device, one transfer each way per evaluation step, compiled == eager, and the whole-update
#      CUDA graph (compile=true) against eager;
#   2. a tiny end-to-end run with device=cuda compile=true (batch generation, training, evaluation, checkpoint);
#   3. benchmarks/bench_compile.py --device cuda: compile=true (one CUDA graph per update) vs eager updates/s for every
#      algorithm, and BC under reduce-overhead and default;
#   4. benchmarks/bench_seed_stack.py --device cuda, when that benchmark exists;
#   5. python -m torchrl_bail.ope --device cuda on the tiny run (BCQ: a sampling policy), then the same fit on the
#      CPU: ope_cuda.json and ope_cpu.json (the estimates agree to float precision, not bit for bit).
# Each step has its own time limit and a failing step does not stop the later ones; the exit code is the number
# of failed steps.
# A GPU machine without network and without this package's dependencies (a stock CUDA PyTorch image): run
# benchmarks/gpu_wheels.sh first where PyPI is reachable and bring .whl/ along; the wheels found there are installed
# offline into a folder of their own (the image's torch is used as it is), and the versions in use go to gpu.txt.
set -u
OUT="${OUT:-$PWD/gpu_check_out}"
mkdir -p "$OUT"
WORK=$(mktemp -d)  # the tiny run's batch and run directory
PY=${PYTHON:-$(command -v python3 || command -v python)}
if compgen -G ".whl/*.whl" > /dev/null; then
  site=$(mktemp -d)
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$site" .whl/*.whl \
    > "$OUT/wheels.log" 2>&1 || { echo "installing .whl/ failed:"; tail -n 20 "$OUT/wheels.log"; }
  export PYTHONPATH="$site"
fi
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" RL_WARNINGS=0 TORCHRL_BAIL_TEST_DEVICE=cuda
failed=0
step() {  # step NAME SECONDS COMMAND...: runs COMMAND with a time limit, output to $OUT/NAME.log
  local name=$1 limit=$2
  shift 2
  echo "== $name (limit ${limit}s): $*" | tee -a "$OUT/gpu_check.log"
  local start=$SECONDS
  timeout "$limit" "$@" >"$OUT/$name.log" 2>&1
  local rc=$?
  echo "   rc=$rc in $((SECONDS - start))s" | tee -a "$OUT/gpu_check.log"
  tail -n 25 "$OUT/$name.log"
  [ "$rc" -eq 0 ] || failed=$((failed + 1))
}

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv >"$OUT/gpu.txt" 2>&1
"$PY" -c "import sys, torch, torchrl, tensordict, gymnasium, mujoco, hydra
print(sys.version.split()[0], 'torch', torch.__version__, torch.cuda.get_device_name(0), 'torchrl', torchrl.__version__,
      'tensordict', tensordict.__version__, 'gymnasium', gymnasium.__version__, 'mujoco', mujoco.__version__,
      'hydra', hydra.__version__)" 2>&1 | tail -n 3 | tee -a "$OUT/gpu.txt"

step tests_cuda 150 "$PY" -m pytest -q -p no:cacheprovider tests/test_compile.py
step tiny_run_cuda 90 "$PY" -m torchrl_bail.train +exp=hopper_ddpg05 preset=quick algo=bcq device=cuda compile=true \
  progress=false batch.steps=1000 batch.start_steps=200 batch.agent.actor_hidden=[32,32] \
  batch.agent.critic_hidden=[32,32] env.max_episode_steps=50 eval.episodes=2 eval.max_steps=50 returns.horizon=50 \
  algo.epochs=0.004 eval.every_epochs=0.002 "data_dir=$WORK/data" "hydra.run.dir=$WORK/tiny_run"
step bench_compile_cuda 115 "$PY" benchmarks/bench_compile.py --device cuda --threads 0 --algos bc,pbail,marwil,bcq,bear \
  --modes true --updates 100 --repeats 3 --json "$OUT/bench_compile.json"
step bench_compile_reduce_overhead_cuda 45 "$PY" benchmarks/bench_compile.py --device cuda --threads 0 --algos bc \
  --modes reduce-overhead,default --updates 100 --repeats 3 --json "$OUT/bench_compile_reduce_overhead.json"
if [ -f benchmarks/bench_seed_stack.py ]; then
  step bench_seed_stack_cuda 45 "$PY" benchmarks/bench_seed_stack.py --device cuda --json "$OUT/bench_seed_stack.json"
fi
step ope_cuda 35 bash -c 'for device in cuda cpu; do "$1" -m torchrl_bail.ope "$0/tiny_run" --device "$device" \
  --updates 300 --force --no-progress && cp "$0/tiny_run/ope.json" "$2/ope_$device.json" || exit 1; done' \
  "$WORK" "$PY" "$OUT"
[ -f "$WORK/tiny_run/summary.json" ] && cp "$WORK/tiny_run/summary.json" "$OUT/tiny_run_summary.json"
echo "failed steps: $failed" | tee -a "$OUT/gpu_check.log"
if [ "${GPU_CHECK_BUNDLE:-0}" = 1 ]; then
  (cd "$OUT" && find . -maxdepth 1 -type f ! -name gpu_check.log ! -name gpu.txt -printf '%P\n' |
     tar -czf gpu_check_records.tar.gz -T - --remove-files)
fi
exit "$failed"
