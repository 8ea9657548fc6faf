#!/usr/bin/env bash
# The model on the lent GPU (see docs/benchmarks.md and docs/results.md). Here, once (git-ignored folders):
#   bash ../shared/tools/warp-gpu-kit .gpukit
#   pip download --no-deps -d .whl gsplat==1.5.3
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 -d .whl OpenImageIO lpips==0.1.4
#   mkdir -p .devdata && cp ~/.cache/sgmodel/* .devdata/ && cp ../shared/data/teachers/playcanvas-guitar/point_cloud.ply .devdata/guitar.ply
# Device call 1 (carry .gpukit/a, .whl): bash .gpukit/a/stash.sh && python3 -m pip install -q --no-index --no-deps --target /root/site .whl/*.whl
# Device call 2 (carry .devdata):        mkdir -p /root/sgcache && cp .devdata/* /root/sgcache/
# Device call 3 (carry .gpukit/b):       bash scripts/gpu/model.sh main      (data, benches, training, eval, predict)
# Device call 4 (carry .gpukit/b):       bash scripts/gpu/model.sh raster    (raster parity, batch bench, LPIPS parity)
# Device call 5 (carry .gpukit/b):       bash scripts/gpu/model.sh ablate    (Table 4 with a short schedule)
# Each phase packs its results (no checkpoints) into $OUT/<phase>.tgz.
# STEPS, ABLATE_STEPS, FRAMES override the sizes, SKIP_BENCH=1 skips the benches; DEVICE=cpu runs the same steps tiny on a CPU (a dry run).
set -uo pipefail
what=${1:-main}
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
out=/tmp/sgrun; mkdir -p $out  # results; packed into $OUT/<phase>.tgz at the end (no checkpoints, .ply, .gif, .csv: 16 MiB a file comes back)
dev=${DEVICE:-cuda}
if [[ $dev == cuda ]]; then
  source .gpukit/b/install.sh || exit 1
  export PYTHONPATH=/root/site:$PWD:$PYTHONPATH SGMODEL_CACHE=/root/sgcache
  guitar=/root/sgcache/guitar.ply
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  S=256 BATCH=32 STEPS=${STEPS:-400} VAL=${VAL:-100} FRAMES=${FRAMES:-100} RES=340x256 ENC=psmnet-kitti WORKERS=8 PAIR=320x256
else  # a CPU dry run of every command below, tiny
  guitar=${GUITAR:-../shared/data/teachers/playcanvas-guitar/point_cloud.ply}
  S=64 BATCH=2 STEPS=${STEPS:-4} VAL=${VAL:-2} FRAMES=${FRAMES:-6} RES=86x64 ENC=sgbm WORKERS=0 PAIR=96x64
fi
export PYTHONUNBUFFERED=1
data=/tmp/sgdata; rc=0
run() { echo "+ $*"; "$@" || { echo "FAILED ($?): $*"; rc=1; }; }

dataset() {  # the demo rooms and the real guitar (orbit) rendered into shards, with depth for the encoder bench
  [[ -f $data/dataset/val/index.json ]] && return
  rm -rf $data; mkdir -p $data/teachers/guitar
  run python3 -m scenesplat_stereo.cli demo-teachers $data/teachers --frames $FRAMES --no-progress
  cp "$guitar" $data/teachers/guitar/point_cloud.ply
  run python3 -m scenesplat_stereo.cli build --teachers $data/teachers --out $data/dataset --device $dev \
    --val-scenes 1 --min-psnr none --orbit "radius=6,frames=$FRAMES" --resolution $RES --with-depth --no-progress
}

if [[ $what == main ]]; then
  dataset
  # 3. a training step split by stage (with the SSIM and the LPIPS term), the encoders' time and disparity
  # error, one warm prediction by stage (SKIP_BENCH=1: not now)
  [[ -n ${SKIP_BENCH:-} ]] || {
  # the step with the SSIM and with the paper's LPIPS-VGG term (random VGG16 weights: the time does not depend on
  # their values; the ImageNet weights cannot be had here)
  run python3 -m sgmodel.cli bench train --device $dev --resolution $S --batch-size $BATCH --encoder $ENC \
    --repeats 5 --warmup 2 --lpips-random-vgg --out "$out/bench_train.md"
  run python3 -m sgmodel.cli bench train --device $dev --resolution $S --batch-size $BATCH --encoder $ENC \
    --repeats 5 --warmup 2 --data $data/dataset --workers $WORKERS --out "$out/bench_train_data.md"
  run python3 -m sgmodel.cli bench encoders --device $dev --data $data/dataset --resolution $S \
    --encoders $ENC --out "$out/bench_encoders.md"
  run python3 -m sgmodel.cli bench predict --device $dev --encoder $ENC --size $PAIR --repeats 20 \
    --out "$out/bench_predict.md"; }
  # 4. a short training run, evaluated with its baselines, then one prediction from a rendered guitar pair
  run python3 -m sgmodel.cli train --data $data/dataset --out $out/run --device $dev --resolution $S \
    --batch-size $BATCH --steps $STEPS --val-every $VAL --encoder $ENC --workers $WORKERS --no-progress
  run python3 -m sgmodel.cli eval --data $data/dataset --split val --checkpoint $out/run/checkpoints/best.pt \
    --device $dev --out $out/eval --no-progress
  for m in naive-gs forward-splat; do
    run python3 -m sgmodel.cli eval --data $data/dataset --split val --method $m --encoder $ENC --resolution $S \
      --device $dev --out $out/eval-$m --no-progress
  done
  run python3 scripts/inputs/guitar_pair.py "$guitar" $data/pair
  run python3 -m sgmodel.cli predict --left $data/pair/left.png --right $data/pair/right.png \
    --calib $data/pair/K.txt --checkpoint $out/run/checkpoints/best.pt --out $out/predict --device $dev
  run python3 scripts/figures/model_figure.py $out/run/checkpoints/best.pt $data/pair/left.png $data/pair/right.png \
    $data/pair/K.txt $out/prediction.png --device $dev
fi
if [[ $what == raster && $dev == cuda ]]; then  # the batched rasteriser against the float64 reference,
  # its model-workload bench, and LPIPS against the lpips package
  run python3 scripts/checks/gpu_parity.py
  run python3 -m scenesplat_stereo.bench.render --batch --device cuda --out "$out/bench_render_batch.md"
  run python3 scripts/checks/gpu_lpips_check.py
fi
if [[ $what == ablate ]]; then
  dataset
  run python3 -m sgmodel.cli ablate --data $data/dataset --out $out/ablate --device $dev --resolution $S \
    --batch-size $((BATCH / 2)) --steps ${ABLATE_STEPS:-100} --val-every ${ABLATE_STEPS:-100} --encoder $ENC \
    --workers $WORKERS --no-progress
fi
skip=(--exclude="*.pt" --exclude="*.ply" --exclude="*.gif" --exclude="*.csv")
[[ $what == ablate ]] && skip+=(--exclude="*.png")  # ten runs' contact sheets are over the 16 MiB a file
tar -czf "$OUT/$what.tgz" -C $out "${skip[@]}" . && ls -la "$OUT"
exit $rc
