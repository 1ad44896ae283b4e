#!/usr/bin/env bash
# Creates or refreshes .venv from environment/requirements.txt; called by `make`.
# Handles the one system library open3d's PyPI wheel needs and a fresh Debian lacks.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing system package libusb-1.0-0 (open3d needs libusb-1.0.so.0)"
    apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null; }
  else
    echo "setup: open3d needs the system library libusb-1.0.so.0." >&2
    echo "       Install the package libusb-1.0-0 (Debian/Ubuntu: sudo apt-get install libusb-1.0-0), then re-run make." >&2
    exit 1
  fi
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PYTHON --version)"
  "$PYTHON" -m venv .venv
fi
echo "setup: installing pinned packages from environment/requirements.txt (first time takes a few minutes)"
.venv/bin/python -m pip install -q --disable-pip-version-check -r environment/requirements.txt
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
touch .venv/.installed
