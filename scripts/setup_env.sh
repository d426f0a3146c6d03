#!/usr/bin/env bash
# Create .venv and install polargs_plugin with everything the demo and the tests need.
# Safe to re-run: it only installs what is missing. Works on a bare Debian/Ubuntu machine.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${VENV:-.venv}
EXTRAS=${EXTRAS:-dev}

if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating $VENV with $($PY --version)"
  "$PY" -m venv "$VENV"
fi
PIP=("$VENV/bin/python" -m pip --disable-pip-version-check -q)

# torch: a CPU-only machine gets the small CPU build pinned at 2.13.0; with an NVIDIA driver we
# leave the choice of the CUDA build to pip.
if ! "$VENV/bin/python" -c "import torch" 2>/dev/null; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    echo "[setup] NVIDIA GPU found: installing a CUDA build of torch"
    "${PIP[@]}" install "torch>=2.4"
  else
    echo "[setup] no CUDA: installing the CPU build torch==2.13.0"
    "${PIP[@]}" install "torch==2.13.0"
  fi
fi

stamp="$VENV/.polargs-installed-$EXTRAS"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[setup] installing polargs_plugin[$EXTRAS] (editable)"
  "${PIP[@]}" install -e ".[$EXTRAS]"
  touch "$stamp"
fi

# open3d needs the system library libusb-1.0 at import time.
if ! "$VENV/bin/python" -c "import open3d" 2>/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "[setup] open3d cannot import: installing libusb-1.0-0 with apt-get"
    (apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1 || { apt-get update -qq >/dev/null && apt-get install -y -qq libusb-1.0-0 >/dev/null; })
  else
    echo "[setup] open3d cannot import. Run as root:  apt-get install -y libusb-1.0-0" >&2
    exit 1
  fi
  "$VENV/bin/python" -c "import open3d" || { echo "[setup] open3d still fails to import" >&2; exit 1; }
fi
echo "[setup] ready: $VENV"
