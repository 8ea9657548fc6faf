#!/usr/bin/env bash
# Several GPUs, measured (issue 34; docs/benchmarks.md "Several GPUs"), on one host of 4 GPUs, in phases
# chosen by the arguments (default: all, in this order):
#   data   demo rooms built into shards on GPU 0 (the training data), and their encoder cache (`sgmodel
#          encode` under torchrun on every GPU)
#   live   scripts/checks/ddp_check.py with the encoder run live: 1 GPU, 1 GPU again (the weights' noise floor),
#          2 and 4 GPUs under torchrun at BATCH pairs a step over all ranks, and at BATCH pairs per rank
#          (--weak-ranks: the paper's effective batch, GPUs x per-GPU batch); median step, pairs/s, speed-up,
#          weights vs 1 GPU, per-rank profile
#   cache  the same with --encoder-cache (each rank reads its share of the cache), without the noise floor
#   build  scripts/checks/ray_build_scale.py: `scenesplat-stereo build --backend ray` on 1, 2, 4 GPUs (16 demo
#          teachers at 616x456; nvJPEG when the machine has it), and the paper's build projected for 4 GPUs
#   weights  where DDP's weights part from one process's (not in the default list): in bf16 autocast and in
#          float32, one process, the same again (the noise floor), one process computing the 2 ranks' shares
#          (`--accumulate 2`: the split without DDP) and DDP on 2 GPUs (ddp_check.py --split-floor)
# Each phase writes its markdown table to $OUT (data.md, live.md, cache.md, build.md, weights-bf16.md and
# weights-float32.md)
# for docs/benchmarks.md.
# Here, once (git-ignored folders):
#   bash ../shared/tools/warp-gpu-kit .gpukit
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 -d .whl OpenImageIO
#   mkdir -p .devdata/weights && cp ~/.cache/sgmodel/*.{tar,pth} .devdata/weights/
#   bash scripts/inputs/ray_kit.sh                       (.raykit: Ray, about 30 MB)
# Device calls on kind nvidia-h100-x4, each within 30 s of the one before (the machine stays the same; one call
# carries at most 64 MiB and runs at most 10 minutes, so the phases run as a background job,
# scripts/gpu/background.sh):
#   1 (carry .gpukit/a):               bash .gpukit/a/stash.sh
#   2 (carry .gpukit/b, .whl):         source .gpukit/b/install.sh
#   3 (carry .devdata/weights, .raykit):
#       mkdir -p /root/sgcache && cp .devdata/weights/* /root/sgcache/ && source .raykit/install.sh &&
#       SGMODEL_CACHE=/root/sgcache STEPS=40 SKIP=10 bash scripts/gpu/background.sh start scale \
#         bash scripts/gpu/scale.sh data live cache build
#   4.. (no carry):                    bash scripts/gpu/background.sh wait scale      (until it exits 0)
# STEPS (default 60), SKIP (15), BATCH (32),
# FRAMES (100), BUILD_FRAMES (150) change the sizes; TRAIN_MORE adds `sgmodel train` flags to every training
# run (e.g. TRAIN_MORE="--ddp-bf16-grads" or "--ddp-bucket-mb 2" with the phase cache, OUT elsewhere).
# DEVICE=cpu runs every phase tiny on the CPU with gloo and 2 ranks (a dry run, about 10 minutes on 2 cores).
set -uo pipefail
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
phases=${*:-data live cache build}
for phase in $phases; do
  [[ " data live cache build weights " == *" $phase "* ]] || {
    echo "gpu_scale.sh: unknown phase $phase (data, live, cache, build, weights)" >&2; exit 2; }
done
dev=${DEVICE:-cuda}
work=/tmp/sgscale; mkdir -p $work
if [[ $dev == cuda ]]; then
  source .gpukit/b/install.sh || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD:${PYTHONPATH:-} SGMODEL_CACHE=${SGMODEL_CACHE:-$PWD/.devdata}
  [[ -d /root/raykit/site ]] && export PYTHONPATH=/root/raykit/site:$PYTHONPATH
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  gpus=$(python3 -c "import torch; print(torch.cuda.device_count())")
  ranks=$( ((gpus >= 4)) && echo "2 4" || echo "$gpus" ); counts=$( ((gpus >= 4)) && echo "1 2 4" || echo "1 $gpus" )
  S=256 BATCH=${BATCH:-32} STEPS=${STEPS:-60} SKIP=${SKIP:-15} FRAMES=${FRAMES:-100} RES=340x256 ENC=psmnet-kitti
  VAL=16 TRAIN_EXTRA="" BUILD_FRAMES=${BUILD_FRAMES:-150} BUILD_RES=616x456 BUILD_EXTRA="--jpeg-encoder cpu"
  # nvJPEG where the machine has it (the fastest build, docs/dataset.md), else the host's JPEG encoder
  python3 -c "from scenesplat_stereo.shards.nvjpeg import load_library; load_library()" 2>/dev/null \
    && BUILD_EXTRA="--jpeg-encoder nvjpeg"
  teachers=16 gaussians=200000
else
  export PYTHONPATH=$PWD:${PYTHONPATH:-}
  ranks=2 counts="1 2" S=32 BATCH=4 STEPS=${STEPS:-8} SKIP=2 FRAMES=${FRAMES:-6} RES=86x64 ENC=sgbm VAL=2
  TRAIN_EXTRA="--preset cpu-small --padding 2 --targets 2 --workers 0"
  BUILD_FRAMES=${BUILD_FRAMES:-6} BUILD_RES=96x72 BUILD_EXTRA="--workers 1" teachers=2 gaussians=2000
fi
export PYTHONUNBUFFERED=1
set -e
py=python3
train_flags="--resolution $S --encoder $ENC --val-samples $VAL $TRAIN_EXTRA ${TRAIN_MORE:-}"
for phase in $phases; do
  t0=$SECONDS
  case $phase in
    data)
      rm -rf $work/teachers $work/dataset $work/cache && mkdir -p $work/teachers
      $py -m scenesplat_stereo.cli demo-teachers $work/teachers --frames $FRAMES --no-progress
      $py -m scenesplat_stereo.cli build --teachers $work/teachers --out $work/dataset --device $dev --val-scenes 1 \
        --min-psnr none --resolution $RES --no-progress
      n=$(echo $counts | awk '{print $NF}')
      launch=$( ((n > 1)) && echo "$py -m torch.distributed.run --standalone --nproc_per_node=$n" || echo $py )
      $launch -m sgmodel.cli encode --data $work/dataset --out $work/cache --encoder $ENC --resolution $S \
        --device $dev --no-progress $( [[ $dev == cpu ]] && echo --preset cpu-small --workers 0 )
      pairs=$($py -c "import sys; from sgmodel.data.loader import read_split; print(', '.join(f'{s} {sum(len(x.keys) \
for x in read_split(sys.argv[1], s))}' for s in ('train', 'val')))" $work/dataset)
      echo "data: demo rooms, pairs: $pairs, $RES, encoder cache of $ENC at ${S}x$S, on $dev" | tee "$OUT/data.md" ;;
    live|cache)
      rm -rf $work/runs-$phase
      extra=$( [[ $phase == live ]] && echo "--noise-floor --label encoder-live" || \
               echo "--no-resume --label encoder-cache" )
      cache=$( [[ $phase == cache ]] && echo "--encoder-cache $work/cache" || true )
      $py scripts/checks/ddp_check.py --data $work/dataset --work $work/runs-$phase --ranks $ranks --weak-ranks $ranks \
        --device $dev \
        --steps $STEPS --batch-size $BATCH --skip $SKIP --profile $extra $( [[ $phase == live ]] && echo --no-resume ) \
        --out "$OUT/$phase.md" -- $train_flags $cache ;;
    weights)
      [[ $ranks == 1 ]] && { echo "scale.sh weights: needs 2 GPUs or more" >&2; exit 2; }
      first=$(echo $ranks | awk '{print $1}')
      for precision in bf16 float32; do
        rm -rf $work/runs-weights-$precision
        $py scripts/checks/ddp_check.py --data $work/dataset --work $work/runs-weights-$precision --ranks $first \
          --device $dev --steps $STEPS --batch-size $BATCH --skip $SKIP --noise-floor --split-floor --no-resume \
          --label "$precision" --out "$OUT/weights-$precision.md" \
          -- $train_flags $( [[ $precision == float32 ]] && echo --no-amp )
      done ;;
    build)
      rm -rf $work/build-teachers
      $py -m scenesplat_stereo.cli demo-teachers $work/build-teachers --scenes $teachers --frames $BUILD_FRAMES \
        --gaussians $gaussians --no-progress
      $py scripts/checks/ray_build_scale.py --teachers $work/build-teachers --work $work/builds --gpus $counts --device $dev \
        --out "$OUT/build.md" -- --resolution $BUILD_RES --val-scenes 0 --min-psnr none $BUILD_EXTRA ;;
  esac
  echo "== phase $phase: $((SECONDS - t0)) s"
done
