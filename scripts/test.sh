#!/usr/bin/env bash
# Sets everything up (scripts/setup.sh --test), then runs the whole check: ruff lint and format,
# pyright, the sample programs in quick mode, and the pytest suite. CI runs exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl} MUJOCO_GL=${MUJOCO_GL:-egl}
echo "== ruff"; .venv/bin/ruff check . && .venv/bin/ruff format --check .
echo "== pyright"; .venv/bin/pyright
echo "== pytest"; .venv/bin/python -m pytest -q -ra "$@"
