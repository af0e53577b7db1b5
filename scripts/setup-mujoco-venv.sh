#!/usr/bin/env bash
# Creates `.venv-mujoco`: MuJoCo 4 from PyPI (pinned in
# requirements-mujoco-lock.txt) over the project venv's numpy, for
# `bridgev2w synth --engine mujoco` (the synthetic world simulated and
# rendered by MuJoCo) and the checks of this project's masks against
# MuJoCo's renderer (scripts/mujoco/masks_check.py). Renders headless through
# EGL (MUJOCO_GL=egl; Mesa's libEGL and llvmpipe on a machine without a GPU):
# where offscreen rendering fails, Debian's libegl1, libegl-mesa0 and
# libgl1-mesa-dri are installed with apt-get when running as root, else the
# script stops naming them. Idempotent (a venv whose stamp matches the lock
# file is kept). Needs .venv.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$root/scripts/lib/overlay-venv.sh"
make_overlay_venv "$root/.venv-mujoco" "$root/scripts/requirements-mujoco-lock.txt" \
  "import mujoco; print('mujoco venv ready: mujoco', mujoco.__version__)" >&2
# Offscreen rendering, as the engine uses it.
render_check() {
  MUJOCO_GL=egl "$root/.venv-mujoco/bin/python" -c \
    'import mujoco; m = mujoco.MjModel.from_xml_string("<mujoco/>"); mujoco.Renderer(m, 8, 8).render()' \
    > /dev/null 2>&1
}
if ! render_check; then
  packages=(libegl1 libegl-mesa0 libgl1-mesa-dri)
  if [[ "$(id -u)" == 0 ]] && command -v apt-get > /dev/null; then
    echo "setup-mujoco-venv: no offscreen OpenGL (EGL): installing ${packages[*]}" >&2
    apt-get update -qq > /dev/null 2>&1 || true
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${packages[@]}" > /dev/null
  fi
  if ! render_check; then
    echo "setup-mujoco-venv: MuJoCo cannot render offscreen with MUJOCO_GL=egl: install Mesa's EGL (Debian: ${packages[*]}) and run this again" >&2
    exit 1
  fi
fi
