#!/usr/bin/env bash
# Creates the project-local Python venv `.venv` with torch 2.11.0 (its libtorch is
# what the `world-model` crate links through tch) and diffusers (the reference for
# parity fixtures). Idempotent: a venv whose stamp matches the lock file is kept.
#
# Disk: the venv takes about 5 GiB (torch's CUDA libraries are most of it: the
# PyPI torch wheel for Linux needs them even to run on the CPU; rerun-sdk and
# pyarrow, for the Rerun recordings, 0.7 GiB). Packages are
# installed from the pinned closure in requirements-lock.txt without resolving,
# the large wheels one per pip call, so at most one downloaded wheel sits on disk
# beside the installed tree.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
lock="$root/scripts/requirements-lock.txt"
stamp="$venv/.bridgev2w-requirements"
# What a fresh install needs free (KiB): the installed tree plus the largest wheel.
need_kib=$((5500 * 1024))
link_libtorch() {
  # tch links the libtorch inside the wheel; .cargo/config.toml points LIBTORCH here.
  local torch_dir
  torch_dir="$("$venv/bin/python" -c 'import os, importlib.util as u; print(os.path.dirname(u.find_spec("torch").origin))')"
  ln -sfn "$torch_dir" "$venv/libtorch"
}
gloo_headers() {
  # The gloo headers c10d's ProcessGroupGloo.hpp includes (for pointer types only;
  # the code is libtorch's own): the PyPI wheel ships none, so crates/torch-ext
  # compiles against Debian's libgloo-dev headers, unpacked here without root.
  [[ -f "$venv/include/gloo/context.h" ]] && return 0
  local tmp
  tmp="$(mktemp -d)"
  if ! (cd "$tmp" && apt-get download libgloo-dev >/dev/null 2>&1); then
    if [[ "$(id -u)" == 0 ]] && command -v apt-get >/dev/null; then
      apt-get update -qq >/dev/null 2>&1 || true
      (cd "$tmp" && apt-get download libgloo-dev >/dev/null 2>&1) || true
    fi
  fi
  local deb
  deb="$(ls "$tmp"/libgloo-dev_*.deb 2>/dev/null | head -n 1)"
  if [[ -n "$deb" ]] && dpkg-deb -x "$deb" "$tmp/x" && [[ -f "$tmp/x/usr/include/gloo/context.h" ]]; then
    mkdir -p "$venv/include"
    rm -rf "$venv/include/gloo.tmp"
    cp -r "$tmp/x/usr/include/gloo" "$venv/include/gloo.tmp"
    mv "$venv/include/gloo.tmp" "$venv/include/gloo"
  else
    echo "scripts/setup-venv.sh: could not fetch Debian's libgloo-dev (apt-get download):" \
      "data-parallel training on the CPU (Gloo) will be unavailable. Install libgloo-dev" \
      "or set BRIDGEV2W_GLOO_INCLUDE to a folder holding gloo/context.h." >&2
  fi
  rm -rf "$tmp"
}
dejavu_font() {
  # The text of the results' figures (eval-report, plan-report draw PNGs with
  # plotters): DejaVu Sans from the system, else Debian's fonts-dejavu-core
  # unpacked here without root (crates/io/src/plot/font.rs looks in both, after
  # BRIDGEV2W_FONT). Without it the figures are drawn without text.
  [[ -f /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf || -f "$venv/fonts/DejaVuSans.ttf" ]] && return 0
  local tmp deb ttf=usr/share/fonts/truetype/dejavu/DejaVuSans.ttf
  tmp="$(mktemp -d)"
  if ! (cd "$tmp" && apt-get download fonts-dejavu-core >/dev/null 2>&1); then
    if [[ "$(id -u)" == 0 ]] && command -v apt-get >/dev/null; then
      apt-get update -qq >/dev/null 2>&1 || true
      (cd "$tmp" && apt-get download fonts-dejavu-core >/dev/null 2>&1) || true
    fi
  fi
  deb="$(ls "$tmp"/fonts-dejavu-core_*.deb 2>/dev/null | head -n 1)"
  if [[ -n "$deb" ]] && dpkg-deb -x "$deb" "$tmp/x" && [[ -f "$tmp/x/$ttf" ]]; then
    mkdir -p "$venv/fonts"
    cp "$tmp/x/$ttf" "$venv/fonts/DejaVuSans.ttf.tmp"
    mv "$venv/fonts/DejaVuSans.ttf.tmp" "$venv/fonts/DejaVuSans.ttf"
  else
    echo "scripts/setup-venv.sh: could not fetch Debian's fonts-dejavu-core (apt-get download):" \
      "the figures of eval-report and plan-report will be drawn without text. Install" \
      "fonts-dejavu-core or set BRIDGEV2W_FONT to a .ttf file." >&2
  fi
  rm -rf "$tmp"
}
if [[ -x "$venv/bin/python" && -f "$stamp" ]] && cmp -s "$lock" "$stamp"; then
  [[ -e "$venv/libtorch/lib/libtorch_cpu.so" ]] || link_libtorch
  gloo_headers
  dejavu_font
  exit 0
fi
free_kib="$(df -Pk "$root" | awk 'NR == 2 { print $4 }')"
if [[ -n "$free_kib" && "$free_kib" -lt "$need_kib" && ! -d "$venv/lib" ]]; then
  echo "scripts/setup-venv.sh: $((free_kib / 1024)) MiB free on the file system of $root," \
    "but the project venv .venv needs about $((need_kib / 1024)) MiB (torch 2.11 and its CUDA" \
    "libraries, plus one downloaded wheel at a time). Free some space (cargo clean drops" \
    "target/) and run it again." >&2
  exit 1
fi
python3 -m venv "$venv"
pip_install() {
  "$venv/bin/python" -m pip install --disable-pip-version-check --no-cache-dir \
    --no-compile --no-deps -q "$@"
}
mapfile -t pins < <(grep -v -E '^[[:space:]]*(#|$)' "$lock")
small=()
for pin in "${pins[@]}"; do
  case "$pin" in
    torch==* | nvidia-* | rerun-sdk==* | pyarrow==*) pip_install "$pin" ;;
    *) small+=("$pin") ;;
  esac
done
pip_install "${small[@]}"
"$venv/bin/python" -c "import torch, diffusers, torchvision, transformers, lpips, h5py, peft, av, rerun; print('venv ready: torch', torch.__version__, 'diffusers', diffusers.__version__)"
link_libtorch
gloo_headers
dejavu_font
cp "$lock" "$stamp"
