#!/usr/bin/env bash
# Creates the peer tool's own virtual environment: CommonRoad's sampling-based Frenet planner
# (commonroad-reactive-planner 2025.1, Python < 3.12). It pins commonroad-io < 2025, so it can never share
# density-planner's environment (commonroad-io 2026 there). Facts about this install: ../shared/notes/reactive-planner.md
#
#   bash benchmarks/peers/make_reactive_venv.sh [VENV_DIR]     # default .peers/reactive-venv (git-ignored)
set -euo pipefail
cd "$(dirname "$0")/../.."
VENV="${1:-.peers/reactive-venv}"
PYTHON="${PEER_PYTHON:-python3}"
"$PYTHON" - <<'PY'
import sys
if not ((3, 9) <= sys.version_info[:2] < (3, 12)):
    sys.exit(f"commonroad-reactive-planner 2025.1 needs Python 3.9-3.11, this is {sys.version.split()[0]}; "
             "set PEER_PYTHON=/path/to/python3.11")
PY
test -x "$VENV/bin/python" || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install --quiet --upgrade pip
"$VENV/bin/python" -m pip install --quiet "commonroad-reactive-planner==2025.1"
"$VENV/bin/python" -c "import commonroad_rp, commonroad; print('reactive planner ready:', '$VENV')"
