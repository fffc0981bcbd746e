#!/usr/bin/env bash
# `make demo`: one 50-iteration AL calibration of the simulated iCub arm as a node graph.
set -euo pipefail
cd "$(dirname "$0")/.."
# `make demo VIZ=1` also serves the live 3D view and prints its URL (off by default: no extra node).
viz=(); [ "${VIZ:-0}" = 0 ] || viz=(--viz)
# --overwrite: a demo is run again and again; it replaces its own previous results/demo.
# DEMO_ARGS (word-split) come last and so win, e.g. DEMO_ARGS='--iterations 3 --output /tmp/demo'.
# shellcheck disable=SC2086
exec scripts/run_calibration.sh --strategy al --iterations 50 --seed 1 --output results/demo --overwrite "${viz[@]}" ${DEMO_ARGS:-}
