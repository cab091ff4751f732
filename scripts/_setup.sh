# Shared bootstrap of scripts/test and scripts/demo (sourced, not run).
# Creates or reuses .venv, installs the project (editable, with test extras) when
# pyproject.toml changed, and the system library open3d needs (libusb-1.0-0).
# Idempotent: a second run only checks a stamp file.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else return 1; fi; }
apt_install() {
  if ! command -v apt-get >/dev/null; then
    echo "mvreg setup: please install the system package(s): $*" >&2; exit 1
  fi
  if ! as_root true 2>/dev/null; then
    echo "mvreg setup: missing system package(s). Run:  sudo apt-get update && sudo apt-get install -y $*" >&2
    exit 1
  fi
  echo "mvreg setup: installing system package(s): $*" >&2
  as_root apt-get update -qq >/dev/null
  DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq "$@" >/dev/null
}

PY="${PYTHON:-python3}"
if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))' 2>/dev/null; then
  echo "mvreg setup: Python >= 3.10 is required (found: $("$PY" --version 2>&1))" >&2; exit 1
fi
# open3d's native module links against libusb-1.0.
if ! { ldconfig -p 2>/dev/null || true; } | grep -q 'libusb-1.0.so.0'; then
  apt_install libusb-1.0-0
fi
if [ ! -x .venv/bin/python ]; then
  if ! "$PY" -m venv .venv 2>/dev/null; then
    rm -rf .venv
    apt_install python3-venv
    "$PY" -m venv .venv
  fi
fi
STAMP=.venv/.mvreg-installed
WANT="$(cat pyproject.toml | sha256sum | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  echo "mvreg setup: installing the project into .venv (first run takes a few minutes)" >&2
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
  .venv/bin/python -m pip install -q -e '.[test]'
  echo "$WANT" > "$STAMP"
fi
export PATH="$ROOT/.venv/bin:$PATH"
