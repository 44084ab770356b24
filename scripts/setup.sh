#!/usr/bin/env bash
# Create .venv (if needed) and install the project: torch first (see DEVELOPERS.md).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
stamp=.venv/.auv-follow-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  python -m pip install -q --upgrade pip
  python -m pip install -q ${TORCH_SPEC:-torch==2.13.0}
  python -m pip install -q -e ".[dev]"
  touch "$stamp"
fi
