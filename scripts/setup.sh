#!/usr/bin/env bash
# Create .venv and install the project with its dev extras. Idempotent: a second run only checks.
# torch 2.13.0 goes first: on the lab machines that exact version installs from a local CPU wheel,
# and any other version would pull gigabytes of CUDA packages.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
VPY=.venv/bin/python
stamp=.venv/.hrc-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  "$VPY" -m pip install --quiet --upgrade pip
  if ! "$VPY" -c "import torch" 2>/dev/null; then
    "$VPY" -m pip install --quiet "torch==2.13.0"
  fi
  "$VPY" -m pip install --quiet -e ".[dev]"
  touch "$stamp"
fi
