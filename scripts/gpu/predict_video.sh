#!/usr/bin/env bash
# Issue 21's measurements on the lent GPU (docs/benchmarks.md "Prediction and stereo video"): one pair by stage
# with every scene format's write time and size at 202,752 Gaussians (320x256, the count), then a stereo
# video's pairs/s and latency at 448x256, model alone and end to end (decode, model, one novel view, encode), in
# batches of 1, 4 and 8, float32 and bf16 autocast; last, `sgmodel predict --video` on a rendered demo clip.
#
# Here, in /work/main (git-ignored folders; the code of the branch, the PSMNet weights):
#   rsync -a --delete --exclude .git --exclude .venv --exclude __pycache__ --exclude scripts/checks/viewer/node_modules \
#         /work/wt21/ .dev21/
#   mkdir -p .dev21w && cp ~/.cache/sgmodel/psmnet_kitti2015.tar .dev21w/
# Device call 1 (carry .gpukit/a):  bash .gpukit/a/stash.sh
# Device call 2 (carry .dev21w):    mkdir -p /root/sgcache && cp .dev21w/* /root/sgcache/
# Device call 3 (carry .gpukit/b, .whl, .dev21), each call within 30 s of the one before (the machine stays warm):
#   source .gpukit/b/install.sh && python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site \
#     .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD/.dev21 && cd .dev21 && bash scripts/gpu/predict_video.sh
# Results: $OUT/predict_video.tgz (the markdown tables and log.txt), about 4 minutes on an H100.
# DEVICE=cpu runs the same steps tiny on a CPU (a dry run: cpu-small preset, sgbm encoder, 96x64).
set -uo pipefail
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
out=/tmp/sg21; rm -rf $out; mkdir -p $out
dev=${DEVICE:-cuda}
export PYTHONUNBUFFERED=1
if [[ $dev == cuda ]]; then
  export SGMODEL_CACHE=/root/sgcache
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  PAIR=320x256 VIDEO=448x256 FRAMES=${FRAMES:-240} REPEATS=${REPEATS:-50} WARMUP=10 MODEL=() BATCHES="1 4 8"
  CLIP=448x256 CLIP_FRAMES=120 ENCODER=psmnet-kitti
else
  PAIR=96x64 VIDEO=96x64 FRAMES=${FRAMES:-8} REPEATS=${REPEATS:-2} WARMUP=1 MODEL=(--preset cpu-small) BATCHES="1 4"
  CLIP=96x64 CLIP_FRAMES=6 ENCODER=sgbm
fi
run() { echo "+ $*"; "$@" || { echo "FAILED ($?): $*"; rc=1; }; }
main() {
  rc=0
  python3 -c "import torch, cv2; print('torch', torch.__version__, 'opencv', cv2.__version__, 'cpus', __import__('os').cpu_count())"
  # 1. one pair by stage, and the write time and size of every scene format (with the fsync'd .ply)
  run python3 -m sgmodel.cli bench predict "${MODEL[@]}" --device $dev --size $PAIR --warmup $WARMUP \
    --repeats $REPEATS --out $out/bench_predict_pair.md
  # 2. a stereo video, model alone and end to end, by batch size; then bf16 autocast (--amp)
  for b in $BATCHES; do
    run python3 -m sgmodel.cli bench predict --video "${MODEL[@]}" --device $dev --size $VIDEO --frames $FRAMES \
      --batch-size $b --warmup $WARMUP --repeats $REPEATS --out $out/bench_video_b$b.md
  done
  run python3 -m sgmodel.cli bench predict --video "${MODEL[@]}" --device $dev --size $VIDEO --frames $FRAMES \
    --batch-size 1 --warmup $WARMUP --repeats $REPEATS --amp --out $out/bench_video_b1_bf16.md
  # 3. the command itself on a rendered stereo clip (naive-GS: no checkpoint here), with one scene per frame
  run python3 -c "from pathlib import Path; from scripts.figures.video_demo import render_clip; \
render_clip(Path('$out/clip'), $CLIP_FRAMES, *map(int, '$CLIP'.split('x')))"
  run python3 -m sgmodel.cli predict --video $out/clip/sbs.mkv --calib $out/clip/K.txt --method naive-gs \
    --encoder $ENCODER --resolution ${CLIP#*x} --frames --batch-size 4 --device $dev --no-progress --out $out/predict
  du -sh $out/predict/frames $out/predict/novel_view.mp4 2>/dev/null
  return $rc
}
main 2>&1 | tee $out/log.txt
rc=${PIPESTATUS[0]}
tar -czf "$OUT/predict_video.tgz" -C $out --exclude=clip --exclude=predict . && ls -la "$OUT"
exit $rc
