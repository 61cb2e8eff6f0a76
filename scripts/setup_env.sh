#!/usr/bin/env bash
# Create .venv and install tactile-slam with its tested dependencies.
# torch 2.13.0 (CPU build) goes in first: a range that admits a newer torch would
# otherwise pull a multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

# open3d needs the system library libusb-1.0 on Debian/Ubuntu.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "setup: installing libusb-1.0-0 (needed by open3d)"
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1 \
            || { apt-get update -qq >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; }
    else
        echo "setup: open3d needs the system library libusb-1.0. Install it with:" >&2
        echo "    sudo apt-get install -y libusb-1.0-0" >&2
        exit 1
    fi
fi

"$PYTHON" - <<'PY'
import sys
if sys.version_info < (3, 11):
    sys.exit(f"setup: Python >= 3.11 is required, found {sys.version.split()[0]}")
PY

[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
PIP=("$VENV/bin/python" -m pip install -q --no-cache-dir --disable-pip-version-check)
"${PIP[@]}" torch==2.13.0
"${PIP[@]}" -e ".[test]"
"$VENV/bin/python" -c "import torch, open3d, cv2, kornia, pypose; print('setup: torch', torch.__version__, '| open3d', open3d.__version__, '| opencv', cv2.__version__)"
