#!/usr/bin/env bash
# Several GPUs in one device call (issue 23; docs/benchmarks.md "Several GPUs"): a dataset of the demo rooms
# and the real guitar built on GPU 0, then scripts/checks/ddp_check.py: one GPU against `torchrun` on all GPUs of the
# host (throughput, same seed), and runs stopped on one number of GPUs resumed on the other.
# Here, once (git-ignored folders):
#   bash ../shared/tools/warp-gpu-kit .gpukit
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 -d .whl OpenImageIO
#   mkdir -p .devdata && cp ~/.cache/sgmodel/* .devdata/ && cp ../shared/data/teachers/playcanvas-guitar/point_cloud.ply .devdata/guitar.ply
# Device call 1 (kind nvidia-h200-x2, carry .gpukit/a):  bash .gpukit/a/stash.sh
# Device call 2 (carry .devdata):                       mkdir -p /root/sgcache && cp .devdata/* /root/sgcache/
# Device call 3 (carry .gpukit/b, .whl):                SGMODEL_CACHE=/root/sgcache bash scripts/gpu/ddp.sh
# (one call carries at most 64 MiB; each call within 30 s of the one before, so the machine stays the same)
# STEPS (default 300), FRAMES (default 100), BATCH (default 32) change the sizes; DEVICE=cpu runs the same
# steps tiny on the CPU with gloo (a dry run).
set -uo pipefail
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
dev=${DEVICE:-cuda}
work=/tmp/sgddp; mkdir -p $work
if [[ $dev == cuda ]]; then
  source .gpukit/b/install.sh || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD:${PYTHONPATH:-} SGMODEL_CACHE=${SGMODEL_CACHE:-$PWD/.devdata}
  guitar=$SGMODEL_CACHE/guitar.ply
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  ranks=$(python3 -c "import torch; print(torch.cuda.device_count())")
  S=256 BATCH=${BATCH:-32} STEPS=${STEPS:-300} FRAMES=${FRAMES:-100} RES=340x256 ENC=psmnet-kitti WORKERS=6 SKIP=30
else
  guitar=${GUITAR:-../shared/data/teachers/playcanvas-guitar/point_cloud.ply}
  ranks=2 S=32 BATCH=4 STEPS=${STEPS:-8} FRAMES=${FRAMES:-6} RES=86x64 ENC=sgbm WORKERS=0 SKIP=2
fi
export PYTHONUNBUFFERED=1
set -e
rm -rf $work/teachers && mkdir -p $work/teachers/guitar && cp "$guitar" $work/teachers/guitar/point_cloud.ply
python3 -m scenesplat_stereo.cli demo-teachers $work/teachers --frames $FRAMES --no-progress
python3 -m scenesplat_stereo.cli build --teachers $work/teachers --out $work/dataset --device $dev --val-scenes 1 \
  --min-psnr none --orbit "radius=6,frames=$FRAMES" --resolution $RES --no-progress
python3 scripts/checks/ddp_check.py --data $work/dataset --work $work/runs --ranks $ranks --device $dev --steps $STEPS \
  --batch-size $BATCH --skip $SKIP --out "$OUT/ddp.md" -- --resolution $S --encoder $ENC --workers $WORKERS \
  $( [[ $dev == cpu ]] && echo --preset cpu-small --padding 2 --targets 2 )
