#!/usr/bin/env bash
# Prepares the GPU checklist here, before a GPU machine is lent, so that its
# minutes go to measuring: a stripped release binary and the Python wheels
# the GPU image lacks (diffusers and what it needs beyond torch,
# transformers, safetensors and huggingface_hub), in gpu-bundle/ (ignored by
# git; hand it to the device tool as `carry: ["gpu-bundle"]`), at most 64 MiB.
#
# Usage: scripts/gpu/prepare.sh            then, on the GPU machine:
#        OUT=$OUT scripts/gpu/run.sh      (the device tool's $OUT)
set -euo pipefail
cd "$(dirname "$0")/../.."
BUNDLE=gpu-bundle
LIMIT_MIB=64
PY=${PYTHON:-.venv/bin/python}
[[ -x $PY ]] || { echo "prepare: $PY not found: run scripts/setup-venv.sh first" >&2; exit 1; }
rm -rf "$BUNDLE.tmp"
mkdir -p "$BUNDLE.tmp/wheels"
echo "prepare: building the release binary..." >&2
cargo build --release -p bridgev2w-cli >&2
cp target/release/bridgev2w "$BUNDLE.tmp/bridgev2w"
strip "$BUNDLE.tmp/bridgev2w"
# The pinned diffusers of the project venv, and the small packages it needs
# that the GPU image does not bring along (pure-Python wheels).
DIFFUSERS=$("$PY" -c 'import diffusers; print(diffusers.__version__)')
echo "prepare: downloading diffusers $DIFFUSERS..." >&2
"$PY" -m pip download --quiet --no-deps --only-binary=:all: --dest "$BUNDLE.tmp/wheels" \
    "diffusers==$DIFFUSERS" importlib_metadata zipp >&2
git rev-parse HEAD > "$BUNDLE.tmp/commit"
SIZE=$(du -sm "$BUNDLE.tmp" | cut -f1)
if (( SIZE > LIMIT_MIB )); then
    echo "prepare: $BUNDLE is $SIZE MiB, above the device tool's $LIMIT_MIB MiB" >&2
    exit 1
fi
rm -rf "$BUNDLE"
mv "$BUNDLE.tmp" "$BUNDLE"
echo "prepare: $BUNDLE/ ready ($SIZE MiB: $(ls "$BUNDLE" "$BUNDLE/wheels" | tr '\n' ' '))"
