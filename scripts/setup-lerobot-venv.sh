#!/usr/bin/env bash
# Creates `.venv-lerobot`, the venv of the LeRobot round-trip tests: the real
# `lerobot` package (PyPI, pinned in requirements-lerobot-lock.txt) over the
# project venv's packages (torch, PyAV, numpy: a .pth file puts .venv's
# site-packages on its path). Run by `./run test`; idempotent (a venv
# whose stamp matches the lock file is kept). Needs .venv first.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$root/scripts/lib/overlay-venv.sh"
HF_HUB_OFFLINE=1 make_overlay_venv "$root/.venv-lerobot" "$root/scripts/requirements-lerobot-lock.txt" \
  "from lerobot.datasets.lerobot_dataset import LeRobotDataset; import lerobot; print('lerobot venv ready: lerobot', lerobot.__version__)"
