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
# compile the env's numba kernels into the on-disk cache once (about a minute on a fresh clone,
# a second or two when cached), so that the first reset and step of an env load in under a second
python -m auv_follow_env.warm
