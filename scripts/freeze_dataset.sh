#!/usr/bin/env bash
# Copies an N3DV-layout dataset (png/camXX/NNNNN.png, poses_bounds.npy, colmap_0/) with every
# frame replaced by its first: the same cameras and point cloud with nothing moving. Training on
# it and evaluating the result against the original's motion mask at frame 0
# (`acags eval --bitstream OUT_RUN/scene.acags --data ORIGINAL`) says how well the method draws
# the moving objects when they hold still (docs/results.md, Follow-up 19).
#
#   scripts/freeze_dataset.sh ~/.cache/acags/synthetic-crossing-v2 /tmp/frozen-crossing
set -euo pipefail
src=${1:?usage: freeze_dataset.sh SOURCE_DATASET OUT_DIR}
out=${2:?usage: freeze_dataset.sh SOURCE_DATASET OUT_DIR}
[ -f "$src/poses_bounds.npy" ] || { echo "$src: no poses_bounds.npy (not an N3DV-layout dataset)" >&2; exit 1; }
[ -d "$src/png" ] || { echo "$src: no png/ directory of extracted frames" >&2; exit 1; }
[ -e "$out" ] && { echo "$out already exists" >&2; exit 1; }
mkdir -p "$out/png"
# The point cloud, where the dataset has one (a failed copy stops the script).
if [ -d "$src/colmap_0" ]; then cp -r "$src/colmap_0" "$out/"; fi
for camera in "$src"/png/cam*; do
  name=$(basename "$camera")
  first=$(ls "$camera" | grep -E '\.png$' | sort | head -n 1)
  [ -n "$first" ] || { echo "$camera: no frames" >&2; exit 1; }
  mkdir -p "$out/png/$name"
  for frame in "$camera"/*.png; do
    cp "$camera/$first" "$out/png/$name/$(basename "$frame")"
  done
done
# Written last, as the generator does: its presence marks a complete dataset.
cp "$src/poses_bounds.npy" "$out/"
echo "$out: $(ls "$out/png" | wc -l) cameras, every frame the first"
