#!/usr/bin/env bash
# Sets everything up (scripts/setup.sh), then runs the main job on the bundled sample vine.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl} MUJOCO_GL=${MUJOCO_GL:-egl}
exec .venv/bin/vinetwin demo "$@"
