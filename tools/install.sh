#!/usr/bin/env bash
# Install detbench (editable) and what it needs. Usage: bash tools/install.sh [--dev]
#   --dev   also install what the test suite and the CI need (pytest, ruff) and the cluster extra (Ray), whose
#           executor the CI tests on a local Ray instance.
# torch is installed first only when it is not importable, so a user who already has a
# CUDA build keeps it; on a fresh machine `pip install torch==2.13.0` takes the platform's
# default wheel (a CPU build where one is provided locally, the CUDA build from PyPI on Linux).
# TORCH_INDEX_URL picks another wheel index for that step, e.g. the small CPU-only build:
#   TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu bash tools/install.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
extra=""
[ "${1:-}" = "--dev" ] && extra="[dev,cluster]"
if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  echo "[install] torch not importable: installing torch==2.13.0${TORCH_INDEX_URL:+ from $TORCH_INDEX_URL}"
  "$PY" -m pip install --quiet "torch==2.13.0" ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"}
fi
"$PY" -m pip install --quiet -e ".${extra}"
echo "[install] detbench installed ($("$PY" -c 'import torch; print("torch", torch.__version__)'))"
