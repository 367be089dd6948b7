#!/usr/bin/env bash
# Builds the image folders the decoder work uses (docs/DECODER.md), outside the repository:
#   $DATA/train/photos  -> ../shared/data/images (the photos; their held-out split is kept out of training)
#   $DATA/train/renders/<scene>/  48 orbit views per shared scene at 256² (6 elevations, black background)
#   $DATA/probe/renders/<scene>/  8 views per scene at elevations and azimuths no training render uses
# Usage: scripts/decoder-data.sh SPLATMARK_BINARY [DATA=/var/tmp/splatmark-data]
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${1:?usage: decoder-data.sh SPLATMARK_BINARY [DATA]}
data=${2:-/var/tmp/splatmark-data}
scenes=../shared/data/scenes
[ -d "$scenes" ] || { echo "decoder-data: $scenes is missing" >&2; exit 1; }
mkdir -p "$data/train" "$data/probe/renders"
ln -sfn "$(cd ../shared/data/images && pwd)" "$data/train/photos"
for s in donut:donut/fused.ply plant:plant/plant.splat udon:udon/point_cloud.ply; do
  name=${s%%:*}; file=$scenes/${s#*:}
  "$bin" render "$file" --orbit 48 --width 256 --height 256 \
    --elevations=-20,0,10,20,35,50 --out "$data/train/renders/$name" >/dev/null
  "$bin" render "$file" --orbit 8 --width 256 --height 256 \
    --elevations=5,42 --azimuth-offset 11 --out "$data/probe/renders/$name" >/dev/null
done
find "$data" -name '*.png' | wc -l
