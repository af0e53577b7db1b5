#!/usr/bin/env bash
# Creates `.venv-mujoco`: MuJoCo 4 from PyPI (pinned in
# requirements-mujoco-lock.txt) over the project venv's numpy, for the checks
# of this project's masks against MuJoCo's renderer
# (scripts/mujoco/masks_check.py). Renders headless through EGL
# (MUJOCO_GL=egl; Mesa's libEGL and llvmpipe on a machine without a GPU).
# Idempotent (a venv whose stamp matches the lock file is kept). Needs .venv.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$root/scripts/lib/overlay-venv.sh"
make_overlay_venv "$root/.venv-mujoco" "$root/scripts/requirements-mujoco-lock.txt" \
  "import mujoco; print('mujoco venv ready: mujoco', mujoco.__version__)"
