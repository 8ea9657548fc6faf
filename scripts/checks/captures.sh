#!/usr/bin/env bash
# Done-when check of issue 35: every real capture renders through `scenesplat-stereo render` and builds as a
# teacher from a folder holding only that file (symlinks in a temporary root), on the CPU at a tiny size.
#   scripts/checks/captures.sh [CAPTURES (default ../shared/data/captures)] [STREAMED (folders with lod-meta.json)]
# Run from the repository root with the project's Python on PATH as `python` (or set PYTHON).
set -euo pipefail
CAPTURES=${1:-../shared/data/captures}
STREAMED=${2:-}
PY=${PYTHON:-python}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
mkdir -p "$TMP/teachers"
for f in "$CAPTURES"/*/*.sog "$CAPTURES"/*/*.splat ${STREAMED:+"$STREAMED"/*/lod-meta.json}; do
  [ -e "$f" ] || continue
  name=$(basename "$(dirname "$f")")
  "$PY" -m scenesplat_stereo.cli render "$f" --out "$TMP/render/$name" --device cpu \
      --orbit radius=2.5,frames=1,size=64x48 2>&1 | tail -1
  if [ "$(basename "$f")" = lod-meta.json ]; then ln -s "$(realpath "$(dirname "$f")")" "$TMP/teachers/$name"
  else mkdir "$TMP/teachers/$name" && ln -s "$(realpath "$f")" "$TMP/teachers/$name/"; fi
done
"$PY" -m scenesplat_stereo.cli build --teachers "$TMP/teachers" --out "$TMP/out" --device cpu --min-psnr none \
    --orbit radius=2.5,frames=2,size=48x32 --val-scenes 0 --targets 2 --no-progress 2>&1 | tail -25
"$PY" -m scenesplat_stereo.cli inspect "$TMP/out" --no-progress 2>&1 | tail -6
