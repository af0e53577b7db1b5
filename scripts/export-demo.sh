#!/usr/bin/env bash
# Exports the fine-tuned BridgeV2W of a `scripts/reproduce-synthetic.sh` run
# as the shipped demo model, assets/demo-model (the default model of
# `bridgev2w demo`): the prior's backbone folder, the fine-tuned weights and
# the fine-tuning config with paths relative to the repository root.
# Called by reproduce-synthetic.sh with EXPORT_DEMO=1.
#
# Usage: scripts/export-demo.sh [OUT_DIR]      (default runs/reproduce)
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
OUT=${1:-runs/reproduce}
for f in "$OUT/prior/final/backbone" "$OUT/bridgev2w/final/weights.safetensors" "$OUT/configs/bridgev2w.toml"; do
    [[ -e $f ]] || { echo "error: $f is missing: run scripts/reproduce-synthetic.sh $OUT first" >&2; exit 1; }
done
rm -rf assets/demo-model.tmp
mkdir -p assets/demo-model.tmp
cp -r "$OUT/prior/final/backbone" assets/demo-model.tmp/backbone
cp "$OUT/bridgev2w/final/weights.safetensors" assets/demo-model.tmp/bridgev2w.safetensors
# The config as it stands, paths relative to the repository root: the
# backbone is the exported one, the dataset and run folders the
# reproduction's (rerun the script to recreate them).
{
    echo "# BridgeV2W fine-tuning config of this model (scripts/reproduce-synthetic.sh $OUT);"
    echo "# paths are relative to the repository root."
    sed -e "s|\"$OUT/prior/final/backbone\"|\"assets/demo-model/backbone\"|" \
        -e "s|\"$ROOT/|\"|" "$OUT/configs/bridgev2w.toml"
} >assets/demo-model.tmp/train-config.toml
rm -rf assets/demo-model && mv assets/demo-model.tmp assets/demo-model
du -sh assets/demo-model
