#!/usr/bin/env bash
# The main job end to end on the simulated rig (the twins speak the real byte protocols).
set -euo pipefail
VENV=${VENV:-.venv}
OUT=${DEMO_OUT:-demo-out}
RIG="$VENV/bin/rig"
STAMP=$(date -u +%Y%m%dT%H%M%SZ)
RUN="$OUT/$STAMP"
mkdir -p "$RUN"
echo "== rig devices --sim"
"$RIG" devices --sim --log-io "$RUN/devices-io.log"
echo "== rig snap --sim (first light: a light and a dark frame)"
"$RIG" snap --sim --angle 45 --filter g --exposure 0.05 --out "$RUN/first-light.npz"
"$RIG" snap --sim --exposure 0.05 --dark --out "$RUN/first-dark.npz"
echo "demo: done; outputs in $RUN/"
