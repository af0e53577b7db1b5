#!/usr/bin/env bash
# Draws the pictures of docs/guide/rerun.md (docs/images/rerun-{episode,masks,prediction}.png):
# makes the guide's three recordings again in a scratch folder, then has the Rerun
# viewer render each one offscreen (`rerun --headless --screenshot-to`) on the CPU,
# on Mesa's software Vulkan driver lavapipe. lavapipe comes from Debian's
# mesa-vulkan-drivers and libvulkan1, unpacked into .venv/lavapipe without root
# (apt-get download, as scripts/setup-venv.sh does for its headers); no X server
# or GPU is needed.
#
#   cargo build --release -p bridgev2w-cli && ./run setup && scripts/rerun-pictures.sh
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
bin="$root/target/release/bridgev2w"
lvp="$venv/lavapipe"
for need in "$venv/bin/python" "$venv/bin/rerun" "$bin"; do
  if [[ ! -x "$need" ]]; then
    echo "scripts/rerun-pictures.sh: $need is missing: run ./run setup (the venv, rerun-sdk)" \
      "and cargo build --release -p bridgev2w-cli first" >&2
    exit 1
  fi
done

lavapipe() {
  # Mesa's lavapipe (software Vulkan) and the Vulkan loader, unpacked here once.
  [[ -f "$lvp/lvp_icd.json" ]] && return 0
  local tmp lib
  tmp="$(mktemp -d)"
  if ! (cd "$tmp" && apt-get download mesa-vulkan-drivers libvulkan1 >/dev/null 2>&1); then
    if [[ "$(id -u)" == 0 ]] && command -v apt-get >/dev/null; then
      apt-get update -qq >/dev/null 2>&1 || true
      (cd "$tmp" && apt-get download mesa-vulkan-drivers libvulkan1 >/dev/null 2>&1) || true
    fi
  fi
  local debs=("$tmp"/mesa-vulkan-drivers_*.deb "$tmp"/libvulkan1_*.deb)
  if [[ ! -f "${debs[0]}" || ! -f "${debs[1]}" ]]; then
    echo "scripts/rerun-pictures.sh: could not fetch Debian's mesa-vulkan-drivers and libvulkan1" \
      "(apt-get download); install them, or draw the pictures on a machine with a GPU" >&2
    rm -rf "$tmp"
    exit 1
  fi
  rm -rf "$lvp.tmp"
  mkdir -p "$lvp.tmp"
  for deb in "${debs[@]}"; do dpkg-deb -x "$deb" "$lvp.tmp/root"; done
  lib="$lvp/root/usr/lib/x86_64-linux-gnu"
  local missing
  missing="$(ldd "$lvp.tmp/root/usr/lib/x86_64-linux-gnu/libvulkan_lvp.so" | grep 'not found' || true)"
  if [[ -n "$missing" ]]; then
    echo "scripts/rerun-pictures.sh: lavapipe needs libraries this system lacks (install them):" >&2
    echo "$missing" >&2
    rm -rf "$tmp" "$lvp.tmp"
    exit 1
  fi
  printf '{"file_format_version": "1.0.0", "ICD": {"library_path": "%s/libvulkan_lvp.so", "api_version": "1.1.230"}}\n' \
    "$lib" >"$lvp.tmp/lvp_icd.json"
  rm -rf "$lvp"
  mv "$lvp.tmp" "$lvp"
  rm -rf "$tmp"
}

# screenshot IN.rrd OUT.png: the viewer at 1100x640 points (drawn at 2x), halved.
screenshot() {
  local shot="$scratch/shot.png"
  rm -f "$shot"
  VK_ICD_FILENAMES="$lvp/lvp_icd.json" LD_LIBRARY_PATH="$lvp/root/usr/lib/x86_64-linux-gnu" RUST_LOG=error \
    "$venv/bin/rerun" --headless --renderer vulkan --screenshot-to "$shot" --window-size 1100x640 "$1"
  "$venv/bin/python" - "$shot" "$2" <<'EOF'
import os, sys
from PIL import Image
shot, out = sys.argv[1], sys.argv[2]
im = Image.open(shot).convert("RGB")
im = im.resize((im.width // 2, im.height // 2), Image.LANCZOS)
im.save(out + ".tmp.png", optimize=True)
os.replace(out + ".tmp.png", out)
print("wrote", out, im.size)
EOF
}

lavapipe
scratch="$(mktemp -d)"
trap 'rm -rf "$scratch"' EXIT
ln -s "$root/assets" "$scratch/assets"
cd "$scratch"
export PATH="$(dirname "$bin"):$venv/bin:$PATH"
# The recordings of docs/guide/rerun.md.
bridgev2w synth --out data --episodes-per-split 1,0,1,0 --frames 9 --tasks pick_place --seed 3 >/dev/null
python -m bridgev2w.rerun view data --episode 0 --rerun episode.rrd
bridgev2w demo --no-predict --out demo-out >/dev/null
python -m bridgev2w.rerun masks --robot franka --camera demo-out/camera.json \
  --actions demo-out/actions.json --width 360 --height 240 --rerun masks.rrd
python - <<'EOF'
import json
import numpy as np
from PIL import Image
import bridgev2w as bw

ep = bw.read_episode("data", 1)
open("camera.json", "w").write(ep.camera.to_json())
json.dump(ep.states.tolist(), open("joints.json", "w"))
Image.fromarray(ep.frames[0]).save("first.png")
np.save("truth.npy", ep.frames)
EOF
bridgev2w masks --robot franka --camera camera.json --joints joints.json --width 96 --height 64 \
  --out masks-out --no-png >/dev/null
bridgev2w predict --model assets/demo-model/backbone --weights assets/demo-model/bridgev2w.safetensors \
  --image first.png --masks masks-out/labels.npy --steps 4 --guidance 1 --seed 0 --device cpu --out pred 2>/dev/null
python -m bridgev2w.rerun predict --video pred --masks masks-out/labels.npy --robot franka \
  --truth truth.npy --image first.png --rerun prediction.rrd
for name in episode masks prediction; do
  screenshot "$name.rrd" "$root/docs/images/rerun-$name.png"
done
