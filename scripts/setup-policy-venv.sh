#!/usr/bin/env bash
# Creates `.venv-policy`, the venv of the served-policy tests: openpi-client's
# msgpack-numpy and websockets (PyPI, pinned in requirements-policy-lock.txt)
# over the project venv's numpy (a .pth file puts .venv's site-packages on its
# path). The tests start a policy server with it (crates/plan/tests/data/
# openpi_server.py). Run by `./run test`; idempotent (a venv whose stamp
# matches the lock file is kept). Needs .venv first.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$root/scripts/lib/overlay-venv.sh"
make_overlay_venv "$root/.venv-policy" "$root/scripts/requirements-policy-lock.txt" \
  "import openpi_client.msgpack_numpy, websockets.sync.server, numpy; print('policy venv ready: websockets', websockets.__version__)"
