#!/usr/bin/env bash
# Creates `.venv-policy`, the venv of the served-policy tests: openpi-client's
# msgpack-numpy and websockets (PyPI, pinned in requirements-policy-lock.txt)
# over the project venv's numpy (a .pth file puts .venv's site-packages on its
# path). The tests start a policy server with it (crates/plan/tests/data/
# openpi_server.py). Run by `./run test`; idempotent (a venv whose stamp matches
# the lock file is kept). Needs .venv first.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv-policy"
lock="$root/scripts/requirements-policy-lock.txt"
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
"$venv/bin/python" -c "import openpi_client.msgpack_numpy, websockets.sync.server, numpy; print('policy venv ready: websockets', websockets.__version__)"
cp "$lock" "$stamp"
