#!/usr/bin/env bash
# The main job in one command: set up the environment, reconstruct the bundled sample bone and
# write OUTDIR/surface.stl, surface.vtp, report.json and surface.png (physical LPS mm).
# Usage: bash Resources/Scripts/demo.sh [OUTDIR]      (default: out)
# BONEWATERTIGHT_VENV=/path/to/venv reuses an existing environment (see setup_env.sh).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
VENV="${BONEWATERTIGHT_VENV:-$ROOT/.venv}"
OUT="${1:-out}"

bash "$ROOT/Resources/Scripts/setup_env.sh"
start=$(date +%s)
status=0
"$VENV/bin/python" "$ROOT/Resources/Scripts/demo.py" "$OUT" || status=$?
echo "[demo] finished in $(( $(date +%s) - start )) s with exit status $status"
exit "$status"
