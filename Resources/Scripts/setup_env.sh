#!/usr/bin/env bash
# Creates/updates the project's virtual environment (.venv) with pinned dependencies, installs
# the package itself (editable: the `bonewatertight` command) and, when run as root on
# Debian/Ubuntu, the system libraries open3d and VTK's offscreen rendering need. Idempotent.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
VENV="${BONEWATERTIGHT_VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3}"

if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = "0" ]; then
  # open3d's wheel links libusb, libgomp and GL/EGL; VTK renders pictures offscreen through
  # EGL with Mesa's software driver (no X server); cmake evaluates the extension's CMake glob
  # in the packaging test.
  need=""
  for pkg in libusb-1.0-0 libgomp1 libgl1 libegl1 libegl-mesa0 libgl1-mesa-dri cmake; do
    dpkg -s "$pkg" >/dev/null 2>&1 || need="$need $pkg"
  done
  if [ -n "$need" ]; then
    echo "[setup] apt-get install$need"
    apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $need >/dev/null
  fi
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating $VENV"
  "$PY" -m venv "$VENV"
fi
stamp="$VENV/.requirements.sha"
want="$( (cat "$ROOT/requirements.txt" "$ROOT/requirements-dev.txt" "$ROOT/pyproject.toml"; echo "$ROOT") \
  | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] || [ ! -x "$VENV/bin/bonewatertight" ]; then
  echo "[setup] installing Python packages (first run takes a few minutes)"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -r "$ROOT/requirements-dev.txt"
  # The package itself, editable (the dependencies are the pinned ones above): puts the
  # `bonewatertight` command into the environment.
  "$VENV/bin/python" -m pip install -q --no-deps --no-build-isolation -e "$ROOT"
  echo "$want" > "$stamp"
fi
