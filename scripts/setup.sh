#!/usr/bin/env bash
# Installs everything vinetwin needs on a fresh Debian machine (Python 3.11+, run as root or
# with sudo): the system libraries (libusb for open3d, EGL/OSMesa/Mesa for headless rendering,
# and with --test Debian's chromium for the browser tests), then a virtual environment in .venv
# with vinetwin and its extras. Safe to run again: it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

with_test=0
for arg in "$@"; do
  case "$arg" in
    --test) with_test=1 ;;
    *) echo "usage: scripts/setup.sh [--test]" >&2; exit 2 ;;
  esac
done

pkgs=(libusb-1.0-0 libgomp1 libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libglx-mesa0 libosmesa6)
if [ "$with_test" = 1 ]; then pkgs+=(chromium); fi

missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  echo "setup: installing system packages: ${missing[*]}"
  SUDO=""
  if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
extras="all"
if [ "$with_test" = 1 ]; then extras="all,dev"; fi
echo "setup: installing vinetwin[$extras] into .venv"
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[$extras]"
echo "setup: done"
