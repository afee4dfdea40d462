#!/usr/bin/env bash
# The test command of README.md: sets up the environment, then runs the whole pytest suite.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
bash "$ROOT/Resources/Scripts/setup_env.sh"
VENV="${BONEWATERTIGHT_VENV:-$ROOT/.venv}"
cd "$ROOT"
exec "$VENV/bin/python" -m pytest Testing -q -p no:cacheprovider "$@"
