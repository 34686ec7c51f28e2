#!/usr/bin/env bash
# Install the peer libraries for benchmarks/compare_peers.py into their own virtualenv,
# benchmarks/peers/.venv, beside an editable ceemx (so both run in one process on one JAX):
#   dynamax  — extended Kalman smoother (state estimation at known θ)
#
#   bash benchmarks/peers/setup.sh
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
venv="$here/.venv"
python="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
  "$python" -m venv "$venv"
fi
"$venv/bin/pip" install -q --upgrade pip
"$venv/bin/pip" install -q -e "$root"
"$venv/bin/pip" install -q dynamax
"$venv/bin/python" -c "import dynamax, jax, ceemx; print('peers ready: dynamax', \
getattr(dynamax, '__version__', '?'), '| jax', jax.__version__)"
