#!/usr/bin/env bash
# Install the peer libraries for benchmarks/compare_peers.py and benchmarks/compare_peers_sysid.py
# into their own virtualenv, benchmarks/peers/.venv, beside an editable ceemx (so all run in one
# process on one JAX):
#   dynamax    — extended Kalman filter / smoother (state estimation; EKF likelihood + optax L-BFGS)
#   cuthbert   — linearised-moments (extended) Kalman filter / smoother (state estimation)
#   jax-sysid  — output-error fit of a nonlinear state-space model (parameter estimation)
# The versions used for benchmarks/results/compare_peers*.json are pinned. cuthbert and jax-sysid
# are optional: one that fails to install is reported and the scripts skip it.
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
"$venv/bin/pip" install -q "cuthbert==0.1.1" || echo "cuthbert unavailable: compare_peers.py will skip it"
"$venv/bin/pip" install -q "jax-sysid==1.0.1" || echo "jax-sysid unavailable: compare_peers_sysid.py will skip it"
"$venv/bin/python" - <<'PY'
from importlib import metadata

import jax

def v(name):
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "absent"

import ceemx, dynamax  # noqa: E401,F401  (required)
print("peers ready: dynamax", v("dynamax"), "| cuthbert", v("cuthbert"), "| jax-sysid",
      v("jax-sysid"), "| optax", v("optax"), "| jax", jax.__version__)
PY
