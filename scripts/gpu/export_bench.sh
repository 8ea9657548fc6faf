#!/usr/bin/env bash
# Issue 35's measurements on the lent GPU host (docs/benchmarks.md "Scene writers"): every scene writer's time
# and size at 202,752 Gaussians, SH degree 0 and 2 (`scenesplat-stereo bench scenes`, the host's cores), the
# same for a real prediction (`sgmodel bench predict`, 320x256), then a stereo video end to end without and
# with a scene per frame in each format (`sgmodel bench predict --video`, 448x256, batches of 1 and 4).
#
# Setup as for scripts/gpu/predict_video.sh (git-ignored folders in /work/main: .gpukit from
# ../shared/tools/warp-gpu-kit, .whl with the OpenImageIO wheel for Python 3.12, .devw with the PSMNet weights
# psmnet_kitti2015.tar from ~/.cache/sgmodel):
# Device call 1 (carry .gpukit/a):  bash .gpukit/a/stash.sh
# Device call 2 (carry .devw):      mkdir -p /root/sgcache && cp .devw/* /root/sgcache/
# Device call 3 (carry .gpukit/b, .whl), within 30 s of the one before (the machine stays the same):
#   source .gpukit/b/install.sh && python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site \
#     .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD && bash scripts/gpu/export_bench.sh
# Without the weights (skip call 2) the video runs use ENCODER=sgbm (OpenCV on the CPU: a slower model, the
# same writers). Results: $OUT/export_bench.tgz (markdown tables and log.txt), about 6 minutes on an H100.
# DEVICE=cpu runs the same steps tiny on a CPU (a dry run: 20,000 Gaussians, cpu-small preset, 96x64).
set -uo pipefail
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
out=/tmp/sg35; rm -rf $out; mkdir -p $out
dev=${DEVICE:-cuda}
export PYTHONUNBUFFERED=1
if [[ $dev == cuda ]]; then
  export SGMODEL_CACHE=${SGMODEL_CACHE:-/root/sgcache}
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  N=202752 REPEATS=${REPEATS:-21} WARMUP=3 PAIR=320x256 VIDEO=448x256 FRAMES=${FRAMES:-240} MODEL=() BATCHES="1 4"
  ENCODER=${ENCODER:-$( [[ -f $SGMODEL_CACHE/psmnet_kitti2015.tar ]] && echo psmnet-kitti || echo sgbm )}
else
  N=20000 REPEATS=${REPEATS:-3} WARMUP=1 PAIR=96x64 VIDEO=96x64 FRAMES=${FRAMES:-6} MODEL=(--preset cpu-small)
  BATCHES="2" ENCODER=sgbm
fi
run() { echo "+ $*"; "$@" || { echo "FAILED ($?): $*"; rc=1; }; }
main() {
  rc=0
  python3 -c "import os, numpy, torch, zlib; print('torch', torch.__version__, 'numpy', numpy.__version__, \
'zlib', zlib.ZLIB_RUNTIME_VERSION, 'cpus', len(os.sched_getaffinity(0)))"
  grep -m1 "model name" /proc/cpuinfo
  # 1. the writers alone on a prediction-shaped scene, SH 0 and 2 (with the .spz's deflate alone: its floor)
  run python3 -m scenesplat_stereo.cli bench scenes --gaussians $N --warmup $WARMUP --repeats $REPEATS \
    --out $out/bench_scenes.md
  # 2. a real prediction's scene (a fresh model: SH 0, and the same with degree-2 SH) by stage and format
  run python3 -m sgmodel.cli bench predict "${MODEL[@]}" --encoder $ENCODER --device $dev --size $PAIR \
    --warmup $WARMUP --repeats $REPEATS --out $out/bench_predict_pair.md
  # 3. a stereo video end to end, without and with a scene per frame in each format
  for b in $BATCHES; do
    run python3 -m sgmodel.cli bench predict --video "${MODEL[@]}" --encoder $ENCODER --device $dev --size $VIDEO \
      --frames $FRAMES --batch-size $b --warmup $WARMUP --repeats $REPEATS --out $out/bench_video_b$b.md
  done
  return $rc
}
main 2>&1 | tee $out/log.txt
rc=${PIPESTATUS[0]}
tar -czf "$OUT/export_bench.tgz" -C $out . && ls -la "$OUT"
exit $rc
