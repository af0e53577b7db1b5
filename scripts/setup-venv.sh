#!/usr/bin/env bash
# Creates the project-local Python venv `.venv` with torch 2.11.0 (its libtorch is
# what the `world-model` crate links through tch) and diffusers (the reference for
# parity fixtures). Idempotent: a venv whose stamp matches the requirements is kept.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
req="$root/scripts/requirements-torch.txt"
stamp="$venv/.bridgev2w-requirements"
link_libtorch() {
  # tch links the libtorch inside the wheel; .cargo/config.toml points LIBTORCH here.
  local torch_dir
  torch_dir="$("$venv/bin/python" -c 'import os, importlib.util as u; print(os.path.dirname(u.find_spec("torch").origin))')"
  ln -sfn "$torch_dir" "$venv/libtorch"
}
if [[ -x "$venv/bin/python" && -f "$stamp" ]] && cmp -s "$req" "$stamp"; then
  [[ -e "$venv/libtorch/lib/libtorch_cpu.so" ]] || link_libtorch
  exit 0
fi
python3 -m venv "$venv"
"$venv/bin/python" -m pip install --disable-pip-version-check --no-cache-dir -q -r "$req"
"$venv/bin/python" -c "import torch, diffusers; print('venv ready: torch', torch.__version__, 'diffusers', diffusers.__version__)"
link_libtorch
cp "$req" "$stamp"
