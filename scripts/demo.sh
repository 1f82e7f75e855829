#!/usr/bin/env bash
# The main job end to end on the simulated rig (the twins speak the real byte protocols).
set -euo pipefail
VENV=${VENV:-.venv}
OUT=${DEMO_OUT:-demo-out}
RIG="$VENV/bin/rig"
mkdir -p "$OUT"
echo "== rig devices --sim"
"$RIG" devices --sim --log-io "$OUT/devices-io.log"
echo "demo: done; outputs in $OUT/"
