#!/usr/bin/env bash
# Builds, checks and times everything on the lent GPU in one call (see docs/benchmarks.md).
# Here, once (all three folders are git-ignored):
#   bash ../shared/tools/warp-gpu-kit .gpukit
#   pip download --no-deps -d .whl gsplat==1.5.3
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 -d .whl OpenImageIO
#   mkdir -p .devdata && cp ../shared/data/teachers/playcanvas-guitar/point_cloud.ply .devdata/guitar.ply
# Device call 1 (carry .gpukit/a):          bash .gpukit/a/stash.sh
# Device call 2 (carry .gpukit/b, .whl and .devdata with guitar.ply): bash scripts/gpu/bench.sh [parity|tests|profile|render|backward|vs|build|all]
# (all = parity, tests, profile, backward (which includes the forward tables), vs (interleaved against gsplat,
# and host time against GPU time) and build)
set -uo pipefail
what=${1:-all}
out=${OUT:-/tmp/out}; mkdir -p "$out"
source .gpukit/b/install.sh || exit 1
python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD:$PYTHONPATH
export PYTHONUNBUFFERED=1 SCENESPLAT_GUITAR_PLY=$PWD/.devdata/guitar.ply
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 -c "import gsplat, torch; print('gsplat', gsplat.__version__, 'torch', torch.__version__)"
rc=0
if [[ $what == parity || $what == all ]]; then
  python3 scripts/checks/gpu_parity.py 2>&1 | tee "$out/parity.txt" || rc=1
fi
if [[ $what == tests || $what == all ]]; then
  python3 -m pytest -q -p no:cacheprovider tests/scenesplat_stereo/raster/test_raster_backward.py tests/scenesplat_stereo/raster/test_raster_batch.py \
    tests/scenesplat_stereo/raster/test_raster_binning.py tests/scenesplat_stereo/raster/test_warp_glue.py tests/scenesplat_stereo/build/test_build.py tests/scenesplat_stereo/shards/test_encode.py -k cuda 2>&1 \
    | tee "$out/tests.txt" | tail -15 || rc=1
fi
if [[ $what == profile || $what == all ]]; then
  python3 scripts/profile/gpu_profile.py 2>&1 | tee "$out/profile.txt" || rc=1
fi
if [[ $what == render ]]; then
  python3 -m scenesplat_stereo.bench.render --device cuda --out "$out/bench_render.md" || rc=1
fi
if [[ $what == backward || $what == all ]]; then  # the forward tables, then forward + backward
  python3 -m scenesplat_stereo.bench.render --device cuda --backward --out "$out/bench_render_backward.md" || rc=1
fi
if [[ $what == vs || $what == all ]]; then
  python3 scripts/profile/gpu_vs_gsplat.py --repeats 25 --out "$out/vs_gsplat.md" || rc=1
  python3 scripts/profile/gpu_host_time.py --out "$out/host_time.md" || rc=1
fi
if [[ $what == build || $what == all ]]; then
  # host encoding alone (threads against processes, per-image cost), then the whole build, rows repeated
  python3 -m scenesplat_stereo.bench.encode --sizes 616x456,1752x1168 --workers 4,8,12,16 \
    --modes threads,processes,threads-oiio1 --repeats 3 --samples 32 --out "$out/bench_encode.md" || rc=1
  python3 -m scenesplat_stereo.cli bench build --device cuda --gsplat --pairs 64 --sizes 616x456,1752x1168 \
    --repeats 5 --jpeg-encoders cpu,nvjpeg --out "$out/bench_build.md" || rc=1
fi
exit $rc
