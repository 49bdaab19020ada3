#!/usr/bin/env bash
# Sets everything up (scripts/setup.sh), then opens the authoring app on the bundled sample vine:
# open the printed address in a browser (Ctrl-C stops the server). Extra arguments go to
# `vinetwin web` (e.g. --port 8081, or a twin folder). The headless job is `vinetwin demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl} MUJOCO_GL=${MUJOCO_GL:-egl}
exec .venv/bin/vinetwin web "$@"
