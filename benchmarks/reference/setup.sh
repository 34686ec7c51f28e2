#!/usr/bin/env bash
# Install the authors' reference implementation, `ceem` 0.0.4 (PyTorch CPU), into its own
# virtualenv benchmarks/reference/.venv, for benchmarks/compare_reference.py.
#
#   bash benchmarks/reference/setup.sh            # create or update the environment
#
# `ceem` is installed with --no-deps (its metadata pins nothing and pulls pytest; its logger
# imports tensorboard); its run-time dependencies are listed here explicitly. Two one-line compatibility
# patches for current SciPy and PyTorch are applied to the installed copy by patch_ceem.py —
# nothing of the authors' code is copied into ceemx.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
venv="$here/.venv"
python="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
  "$python" -m venv "$venv"
fi
"$venv/bin/pip" install -q --upgrade pip
# torch 2.13.0 CPU (a local wheel on this machine kind; the registry's newest otherwise).
"$venv/bin/pip" install -q "torch==2.13.0" numpy scipy joblib tqdm termcolor pandas \
  matplotlib click python-dateutil future tensorboard
"$venv/bin/pip" install -q --no-deps "ceem==0.0.4"
"$venv/bin/python" "$here/patch_ceem.py"
"$venv/bin/python" -c "import ceem, torch, scipy; print('reference ready: ceem', \
ceem.__file__, '| torch', torch.__version__, '| scipy', scipy.__version__)"
