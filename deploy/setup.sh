#!/usr/bin/env bash
# Set up (or refresh) flyslam's virtual environment in .venv: safe to run again and again.
# Needs only Python >= 3.11 and access to PyPI.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PY --version)" >&2
  "$PY" -m venv .venv
fi
stamp=.venv/.flyslam-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ deploy/constraints.txt -nt "$stamp" ]; then
  echo "[setup] installing flyslam and its dependencies (pinned in deploy/constraints.txt)" >&2
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
  .venv/bin/python -m pip install -q -c deploy/constraints.txt -e '.[test]'
  touch "$stamp"
fi
# Compile every numba kernel now (kept in numba's on-disk cache, see common/numba_cache.py), so no run
# pays for it; after a source change only the changed kernels compile again.
echo "[setup] compiling the numba kernels (minutes the first time, seconds after)" >&2
if ! .venv/bin/python -m common.warmup; then
  echo "[setup] warning: the kernels named above will compile during a run" >&2
fi
# Rerun's usage analytics stay off on every flyslam machine.
.venv/bin/rerun analytics disable >/dev/null 2>&1 || true
echo "[setup] ready: .venv/bin/flyslam" >&2
