#!/usr/bin/env bash
# Creates `.venv-lerobot`, the venv of the LeRobot round-trip tests: the real
# `lerobot` package (PyPI, pinned in requirements-lerobot-lock.txt) over the
# project venv's packages (torch, PyAV, numpy: a .pth file puts .venv's
# site-packages on its path). Run by `./run test`; idempotent (a venv
# whose stamp matches the lock file is kept). Needs .venv first.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv-lerobot"
lock="$root/scripts/requirements-lerobot-lock.txt"
stamp="$venv/.bridgev2w-requirements"
if [[ -x "$venv/bin/python" && -f "$stamp" ]] && cmp -s "$lock" "$stamp"; then
  exit 0
fi
project_site="$("$root/.venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
python3 -m venv "$venv"
site="$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
echo "$project_site" > "$site/bridgev2w-project-venv.pth"
mapfile -t pins < <(grep -v -E '^[[:space:]]*(#|$)' "$lock")
"$venv/bin/python" -m pip install --disable-pip-version-check --no-cache-dir --no-compile \
  --no-deps -q "${pins[@]}"
HF_HUB_OFFLINE=1 "$venv/bin/python" -c "from lerobot.datasets.lerobot_dataset import LeRobotDataset; import lerobot; print('lerobot venv ready: lerobot', lerobot.__version__)"
cp "$lock" "$stamp"
