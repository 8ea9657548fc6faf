#!/usr/bin/env bash
# The training step's speed on the lent GPU (issue 22; docs/benchmarks.md "The training step"), from the
# repository root there. Here, once (git-ignored folders; see scripts/gpu/model.sh for the same kit):
#   bash ../shared/tools/warp-gpu-kit .gpukit
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 \
#     -d .whl OpenImageIO
#   mkdir -p .devdata && cp ~/.cache/sgmodel/* .devdata/
#   cp ../shared/data/teachers/playcanvas-guitar/point_cloud.ply .devdata/guitar.ply
# Device call 1 (carry .gpukit/a):                 bash .gpukit/a/stash.sh
# Device call 2 (carry .devdata):                  mkdir -p /root/sgcache && cp .devdata/* /root/sgcache/
# Device call 3 (carry .gpukit/b, .whl; one call carries at most 64 MiB, each within 30 s of the one before):
#   SGMODEL_CACHE=/root/sgcache bash scripts/gpu/train_step.sh [tests] [bench] [profile] [big] [curve] [lpips] [convs]
#   [gntiles]
#   tests:   the CUDA tests of the layers, concatenation, SSIM term, LPIPS (its
#            tap-distance kernels), soft-argmin, rasteriser
#   bench:   `sgmodel bench train` with the SSIM and the LPIPS term (random VGG16 weights: the time does not
#            depend on them); with BASE=DIR (a copy of the code before a change) the same for it, interleaved
#   profile: scripts/profile/gpu_train_profile.py with each term
#   big:     512x512 (padding 32): `bench train` at batch 32, then smaller batches until one fits
#   curve:   a small dataset (demo rooms + the guitar), then short training runs: SEEDS of this code and, with
#            BASE, of the code before; the validation PSNR of every run side by side ($OUT/curves.md)
#   cache:   the encoder cache: `sgmodel encode` of the curve's dataset, scripts/checks/gpu_cache_check.py (cuDNN's
#            search off, then on in two processes), then
#            `bench train --data` with the encoder run and with --encoder-cache ($OUT/cache_bench.md)
#   cachestep: the step from the cache (real batches, both loss terms); with BASE the code before too,
#            interleaved, twice ($OUT/cache_step.md)
#   cachecurve: training runs with the encoder run and read from the cache, SEEDS each ($OUT/cache_curves.md)
#   convs:   the predictor's convolutions alone with their channels padded to 8, 16, 32 and 64
#            (scripts/profile/gpu_conv_channels.py; $OUT/conv_channels.md)
#   gntiles: the fused GroupNorm kernels at each tile size and warp count (scripts/profile/gpu_group_norm_tiles.py;
#            GN_TILES and GN_WARPS, comma-separated, choose others than its defaults; $OUT/gn_tiles.md)
#   lpips:   the step with the LPIPS term's VGG16 eager (--no-compile-lpips; `bench` times the compiled default),
#            then training runs with the LPIPS term (random VGG16) compiled and eager, SEEDS each
#            ($OUT/lpips_curves.md)
# WHEELS (default .whl), KIT (.gpukit/b), SGMODEL_CACHE (.devdata), GUITAR ($SGMODEL_CACHE/guitar.ply), STEPS (200),
# VAL (50), SEEDS ("0 1").
set -uo pipefail
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
source "${KIT:-.gpukit/b}/install.sh" >/dev/null || exit 1
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site "${WHEELS:-.whl}"/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD:$PYTHONPATH PYTHONUNBUFFERED=1 SGMODEL_CACHE=${SGMODEL_CACHE:-$PWD/.devdata}
here=$PWD base=${BASE:-}; [[ -n $base ]] && base=$(cd "$base" && pwd)
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
rc=0
run() { echo "+ $*"; "$@" || { echo "FAILED ($?): $*"; rc=1; }; }
in_base() { (cd "$base" && "$@"); }
bench=(python3 -m sgmodel.cli bench train --device cuda --warmup 3 --repeats 8)
data=/tmp/sgdata
dataset() {  # the demo rooms and the guitar (orbit), 180 training and 10 validation pairs at 340x256
  [[ -f $data/dataset/val/index.json ]] && return
  mkdir -p $data/teachers/guitar && cp "${GUITAR:-$SGMODEL_CACHE/guitar.ply}" $data/teachers/guitar/point_cloud.ply
  run python3 -m scenesplat_stereo.cli demo-teachers $data/teachers --frames 60 --no-progress
  run python3 -m scenesplat_stereo.cli build --teachers $data/teachers --out $data/dataset --device cuda \
    --val-scenes 1 --min-psnr none --orbit "radius=6,frames=60" --resolution 340x256 --no-progress
}
encoder_cache() {  # the dataset and its encoder cache (/tmp/enc-cache), each made once per machine
  dataset
  [[ -f /tmp/enc-cache/val/index.json ]] || run python3 -m sgmodel.cli encode --data $data/dataset --out /tmp/enc-cache \
    --device cuda --workers 8 --no-progress 2>&1 | tee "$OUT/encode.txt"
}
curves() {  # curves FILE RUN...: the validation PSNR of every run side by side, and its logged median step
  local file=$1; shift
  run python3 - "$@" > "$file" <<'EOF'
import json, sys
from pathlib import Path
runs = {Path(r).name: [json.loads(line) for line in (Path(r) / "metrics.jsonl").read_text().splitlines()]
        for r in sys.argv[1:]}
steps = sorted({m["step"] for ms in runs.values() for m in ms if "val_psnr" in m})
val = {k: {m["step"]: m["val_psnr"] for m in ms if "val_psnr" in m} for k, ms in runs.items()}
ms = {k: sorted(m["step_ms"] for m in v if "step_ms" in m) for k, v in runs.items()}
print("| step | " + " | ".join(runs) + " |\n|---|" + "---:|" * len(runs))
for s in steps:
    print(f"| {s} | " + " | ".join(f"{val[k].get(s, float('nan')):.3f}" for k in runs) + " |")
print("| median step ms (logged) | " + " | ".join(f"{v[len(v) // 2]:.0f}" if v else "n/a" for v in ms.values()) + " |")
EOF
  cat "$file"
}
train=(python3 -m sgmodel.cli train --data $data/dataset --device cuda --steps ${STEPS:-200} --val-every ${VAL:-50}
       --workers 8 --no-progress)
compiled_and_eager() {  # compiled_and_eager FILE NAME EAGER_FLAG [TRAIN FLAGS...]: SEEDS runs of each, side by side
  local file=$1 name=$2 eager=$3; shift 3
  dataset
  local runs=() s mode flags
  for s in ${SEEDS:-0 1}; do
    for mode in compiled eager; do
      flags=(); [[ $mode == eager ]] && flags=("$eager")
      run "${train[@]}" --seed $s "$@" "${flags[@]}" --out /tmp/runs/$name-$mode-seed$s > /tmp/runs-$name-$mode-$s.log 2>&1
      runs+=(/tmp/runs/$name-$mode-seed$s)
    done
  done
  curves "$file" "${runs[@]}"
}

for what in "$@"; do case $what in
tests)
  run python3 -m pytest -q -p no:cacheprovider tests/sgmodel/model/test_layers.py tests/sgmodel/kernels/test_ssim_kernels.py tests/sgmodel/model/test_model.py \
    tests/sgmodel/kernels/test_concat_kernels.py tests/sgmodel/kernels/test_lpips_kernels.py tests/sgmodel/kernels/test_composer_kernels.py \
    tests/sgmodel/metrics/test_lpips.py tests/sgmodel/kernels/test_soft_argmin.py tests/scenesplat_stereo/raster/test_raster_backward.py tests/scenesplat_stereo/raster/test_raster_forward.py \
    tests/scenesplat_stereo/raster/test_raster_variants.py tests/scenesplat_stereo/raster/test_raster_batch.py tests/scenesplat_stereo/raster/test_raster_stability.py -k "cuda or kernels" 2>&1 \
    | tee "$OUT/tests.txt" | tail -5 ;;
bench)
  run "${bench[@]}" --lpips-random-vgg --out /tmp/bench_new.md && cat /tmp/bench_new.md >> "$OUT/bench.md"
  if [[ -n $base ]]; then  # the code before: its bench times one loss per call; random VGG16 in torchvision's format
    run python3 -c "import torch; from sgmodel.metrics.lpips import VGG16Trunk
torch.save(VGG16Trunk().state_dict(), '/tmp/vgg16-random.pth')"
    run in_base "${bench[@]}" --out /tmp/bench_base.md \
      && { echo "## before"; cat /tmp/bench_base.md; } >> "$OUT/bench.md"
    run in_base "${bench[@]}" --lpips-vgg /tmp/vgg16-random.pth --out /tmp/bench_base.md \
      && { echo "## before, LPIPS"; cat /tmp/bench_base.md; } >> "$OUT/bench.md"
    run "${bench[@]}" --lpips-random-vgg --out /tmp/bench_new.md \
      && { echo "## again"; cat /tmp/bench_new.md; } >> "$OUT/bench.md"
  fi ;;
profile)
  run python3 scripts/profile/gpu_train_profile.py --out /tmp/profile.md && cat /tmp/profile.md >> "$OUT/profile.md"
  run python3 scripts/profile/gpu_train_profile.py --lpips-random-vgg --top 25 --out /tmp/profile.md \
    && cat /tmp/profile.md >> "$OUT/profile.md" ;;
big)
  for b in 32 24 16 12; do
    if "${bench[@]}" --resolution 512 --padding 32 --batch-size $b --warmup 1 --repeats 3 --lpips-random-vgg \
        --out /tmp/big.md > /tmp/big.log 2>&1; then cat /tmp/big.md >> "$OUT/big.md"; break; fi
    { echo "batch $b at 512x512:"; grep -m1 -i "out of memory" /tmp/big.log || tail -3 /tmp/big.log; echo; } \
      >> "$OUT/big.md"
  done ;;
curve)
  dataset
  runs=()
  for s in ${SEEDS:-0 1}; do
    run "${train[@]}" --seed $s --out /tmp/runs/new-seed$s > /tmp/runs-new-$s.log 2>&1; runs+=(/tmp/runs/new-seed$s)
    if [[ -n $base ]]; then
      run in_base "${train[@]}" --seed $s --out /tmp/runs/before-seed$s > /tmp/runs-before-$s.log 2>&1
      runs+=(/tmp/runs/before-seed$s)
    fi
  done
  curves "$OUT/curves.md" "${runs[@]}" ;;
lpips)  # the LPIPS term's VGG16 compiled (the default) and eager: the step, then training runs of each
  run "${bench[@]}" --lpips-random-vgg --no-compile-lpips --out /tmp/bench_eager.md \
    && { echo "## the LPIPS term's VGG16 eager (--no-compile-lpips)"; cat /tmp/bench_eager.md; } >> "$OUT/bench.md"
  run python3 -c "import torch; from sgmodel.metrics.lpips import VGG16Trunk
torch.manual_seed(0); torch.save(VGG16Trunk().state_dict(), '/tmp/vgg16-random.pth')"
  compiled_and_eager "$OUT/lpips_curves.md" lpips --no-compile-lpips --lpips-vgg /tmp/vgg16-random.pth ;;
cache)  # the encoder cache: `sgmodel encode` of the small dataset, its outputs against the encoder run live,
        # then the step on real batches with the encoder run and read from the cache ($OUT/cache_bench.md)
  encoder_cache
  run python3 scripts/checks/gpu_cache_check.py --data $data/dataset --cache /tmp/enc-cache --no-search \
    | tee "$OUT/cache_check_no_search.md"
  run python3 scripts/checks/gpu_cache_check.py --data $data/dataset --cache /tmp/enc-cache --save-live /tmp/live.pt
  run python3 scripts/checks/gpu_cache_check.py --data $data/dataset --cache /tmp/enc-cache --against-live /tmp/live.pt \
    | tee "$OUT/cache_check.md"
  for mode in live cache; do
    flags=(); [[ $mode == cache ]] && flags=(--encoder-cache /tmp/enc-cache)
    run "${bench[@]}" --data $data/dataset "${flags[@]}" --lpips-random-vgg --out /tmp/bench_$mode.md \
      && { echo "## real batches, encoder $mode"; cat /tmp/bench_$mode.md; } >> "$OUT/cache_bench.md"
  done ;;
cachestep)  # the step from the encoder cache on real batches, both loss terms; with BASE the code before too,
            # interleaved, twice ($OUT/cache_step.md)
  encoder_cache
  for r in 1 2; do
    run "${bench[@]}" --data $data/dataset --encoder-cache /tmp/enc-cache --lpips-random-vgg --out /tmp/step.md \
      && { echo "## this code ($r)"; cat /tmp/step.md; } >> "$OUT/cache_step.md"
    if [[ -n $base ]]; then
      run in_base "${bench[@]}" --data $data/dataset --encoder-cache /tmp/enc-cache --lpips-random-vgg \
        --out /tmp/step.md && { echo "## before ($r)"; cat /tmp/step.md; } >> "$OUT/cache_step.md"
    fi
  done ;;
cachecurve)  # training runs with the encoder run and read from the cache, SEEDS each ($OUT/cache_curves.md)
  encoder_cache
  runs=()
  for s in ${SEEDS:-0 1}; do
    for mode in live cache; do
      flags=(); [[ $mode == cache ]] && flags=(--encoder-cache /tmp/enc-cache)
      run "${train[@]}" --seed $s "${flags[@]}" --out /tmp/runs/$mode-seed$s > /tmp/runs-$mode-$s.log 2>&1
      runs+=(/tmp/runs/$mode-seed$s)
    done
  done
  curves "$OUT/cache_curves.md" "${runs[@]}" ;;
convs)
  run python3 scripts/profile/gpu_conv_channels.py --out "$OUT/conv_channels.md" ;;
gntiles)
  run python3 scripts/profile/gpu_group_norm_tiles.py ${GN_TILES:+--tiles $GN_TILES} ${GN_WARPS:+--warps $GN_WARPS} \
    --out "$OUT/gn_tiles.md" ;;
*) echo "unknown phase $what"; rc=2 ;;
esac; done
exit $rc
