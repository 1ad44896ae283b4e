#!/usr/bin/env bash
# Creates or refreshes .venv from environment/requirements.txt; called by `make`.
# Handles the one system library open3d's PyPI wheel needs and a fresh Debian lacks.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

# `setup_env.sh --browser` (make test): the headless Chromium of tests/test_site.py, the Debian
# package `chromium`, installed when running as root like libusb below; elsewhere the test skips.
if [ "${1:-}" = "--browser" ]; then
  if command -v chromium >/dev/null || command -v chromium-browser >/dev/null || command -v google-chrome >/dev/null; then
    exit 0
  fi
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing system package chromium (the site's browser test)"
    apt-get install -y -q chromium >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; } \
      || echo "setup: could not install chromium; tests/test_site.py's browser check will be skipped" >&2
  else
    echo "setup: no chromium on PATH (Debian/Ubuntu: sudo apt-get install chromium); the site's browser check will be skipped" >&2
  fi
  exit 0
fi

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
