#!/usr/bin/env bash
# Composed teachers at training size on the lent GPU: every real capture of shared/data/captures (and the guitar)
# composed into rooms, built into shards with depth, their depth percentiles and a contact sheet
# (docs/dataset.md "Captures composed into rooms"). Needs the SOG and .splat readers (branch formats-read) merged.
# Here, once (git-ignored folder; 17 MB):
#   mkdir -p .devdata/captures && cp -r ../shared/data/captures/*/ .devdata/captures/ \
#     && cp ../shared/data/teachers/playcanvas-guitar/point_cloud.ply .devdata/captures/guitar.ply
# Device call (carry .gpukit/b, .devdata): bash scripts/gpu/compose.sh
# Results (no shards) come back in $OUT: depth.md, composed_teachers.png, build.log.
# ROOMS, FRAMES, SIZE override the sizes; DEVICE=cpu runs the same steps tiny on a CPU (a dry run).
set -uo pipefail
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
dev=${DEVICE:-cuda}
if [[ $dev == cuda ]]; then
  source .gpukit/b/install.sh || exit 1
  export PYTHONPATH=/root/site:$PWD:$PYTHONPATH
  caps=.devdata/captures; ROOMS=${ROOMS:-4} FRAMES=${FRAMES:-60} SIZE=${SIZE:-616x456} G=36000
else
  export PYTHONPATH=$PWD:${PYTHONPATH:-}
  caps=${CAPTURES:-../shared/data/teachers/playcanvas-guitar/point_cloud.ply}; ROOMS=${ROOMS:-2} FRAMES=${FRAMES:-4}
  SIZE=${SIZE:-64x48} G=2000
fi
export PYTHONUNBUFFERED=1
work=/tmp/sgcompose; rm -rf $work
set -e
python3 -m scenesplat_stereo.cli compose-teachers --captures $caps --out $work/teachers --rooms $ROOMS \
  --frames $FRAMES --size $SIZE --gaussians $G --no-progress | tee "$OUT/build.log"
( time python3 -m scenesplat_stereo.cli build --teachers $work/teachers --out $work/dataset --device $dev \
  --min-psnr none --val-scenes 0 --targets 1 --with-depth --no-progress ) 2>&1 | tail -20 | tee -a "$OUT/build.log"
python3 scripts/figures/depth_percentiles.py $work/dataset --group scene | tee "$OUT/depth.md"
python3 scripts/figures/depth_percentiles.py $work/dataset | tee -a "$OUT/depth.md"
python3 scripts/figures/composed_teachers.py $work/teachers "$OUT/composed_teachers.png" --thumb 112x84 --frames 2
