#!/usr/bin/env bash
# Set up o3dsoft for development in ./.venv: system library for Open3D, torch, the package.
# Safe to run again: it only installs what is missing.
#   TORCH_SPEC   torch requirement to install (default torch==2.13.0: a CPU build where pip finds
#                one, as on the project's machines; from PyPI on Linux the CUDA build)
#   TORCH_INDEX_URL  the index torch comes from, e.g. https://download.pytorch.org/whl/cpu (PyTorch's CPU builds)
#   VENV         virtual environment folder (default .venv)
set -euo pipefail
cd "$(dirname "$0")"
VENV=${VENV:-.venv}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}
PYTHON=${PYTHON:-python3}

# Open3D 0.20 loads libusb-1.0 at import time.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
        echo "install.sh: installing libusb-1.0-0 (needed by Open3D)" >&2
        (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null
    elif command -v apt-get >/dev/null 2>&1 && command -v sudo >/dev/null 2>&1; then
        echo "install.sh: installing libusb-1.0-0 (needed by Open3D) with sudo" >&2
        (sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0) >/dev/null
    else
        echo "install.sh: Open3D needs the system library libusb-1.0; install it (Debian/Ubuntu: apt-get install libusb-1.0-0) and run again." >&2
        exit 1
    fi
fi

if [ ! -x "$VENV/bin/python" ]; then
    "$PYTHON" -m venv "$VENV"
fi
PIP="$VENV/bin/python -m pip --disable-pip-version-check -q"
# torch first and pinned: an unpinned torch would pull whatever build is newest; TORCH_INDEX_URL picks the index
# (PyTorch's CPU index for a CPU build where pip would find the CUDA one on PyPI).
$PIP install ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"} "$TORCH_SPEC" 2>&1 | grep -v "^WARNING: Location" || true
$VENV/bin/python -c "import torch" 2>/dev/null || { echo "install.sh: torch failed to install ($TORCH_SPEC)" >&2; exit 1; }
$PIP install -e ".[test,peers,ray]" 2>&1 | grep -v "^WARNING: Location" || true
$VENV/bin/python -c "import o3dsoft, open3d" || { echo "install.sh: o3dsoft failed to install" >&2; exit 1; }
echo "install.sh: ready ($VENV)" >&2
