#!/usr/bin/env bash
# Create the virtual environment, install the pinned dependencies and every ament_python package
# of ros2_ws/src (editable, so their console scripts, package data and ament index markers land
# in the venv prefix). Called by `make setup`; safe to run again.
# Usage: scripts/setup.sh PYTHON VENV PKG_DIR...
set -euo pipefail
python=$1; venv=$2; shift 2
if [ ! -x "$venv/bin/python" ]; then
  echo "setup: creating $venv"
  "$python" -m venv "$venv"
fi
echo "setup: installing pinned requirements"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r requirements.txt
echo "setup: installing workspace packages: $(for d in "$@"; do basename "$d"; done | tr '\n' ' ')"
args=()
for d in "$@"; do args+=(-e "$d"); done
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
  --no-build-isolation --config-settings editable_mode=compat "${args[@]}"
# Editable installs skip data_files: link them into the prefix as colcon --symlink-install would.
"$venv/bin/python" scripts/install_data_files.py "$venv" "$@"
echo "setup: done"
