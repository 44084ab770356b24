#!/usr/bin/env bash
# The README's main job: set up if needed, then reproduce the paper's Section 4.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
python -m experiments.reproduce_paper "$@"
