#!/usr/bin/env bash
# A checkpoint and the baselines without learned prediction on real photographs with ground-truth novel views:
# the three Middlebury 2001 nine-view sets (docs/results.md "Real photographs with ground-truth novel views"),
# the pair (im2, im6) in, the other seven views as targets, reported between / beside the pair and over all.
#
# Here, in the checkout (git-ignored .devdata; 2.6 MB of shards and the 21 MB PSMNet weights, under the carry's 64 MiB;
# the copy is not needed on a machine where gpu_model.sh already put the weights in /root/sgcache):
#   python -m scenesplat_stereo.cli import multiview ../shared/data/multiview --out .devdata/multiview \
#     --focal 450 --baseline 0.065
#   mkdir -p .devdata/sgcache && cp ~/.cache/sgmodel/* .devdata/sgcache/
# One device call (carry .gpukit/b and .devdata; the checkpoint is a path on the device machine, e.g. the
# best.pt a training run there just wrote, or a file inside .devdata):
#   bash scripts/gpu/multiview_eval.sh /tmp/sgrun/run/checkpoints/best.pt [more `sgmodel eval` flags, e.g. --amp]
# Without a checkpoint it measures the baselines only. ENCODER=<name> gives the baselines (and the checkpoint) that
# encoder instead of their defaults (the checkpoint's own; psmnet-kitti for the baselines); LPIPS_VGG=<vgg16 .pth>
# adds LPIPS; DEVICE=cpu runs it on a CPU (how docs/results.md's baseline table was made). Results: $OUT/multiview/
# (table2.md, table2.json and one report per method), about a minute on a GPU.
set -uo pipefail
checkpoint=${1:-}
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
dev=${DEVICE:-cuda}
data=${DATA:-.devdata/multiview}
if [[ ! -f $data/test/index.json ]]; then
  echo "no imported sets in $data: run the import of this script's header first (then carry .devdata)" >&2; exit 2
fi
if [[ $dev == cuda ]]; then
  [[ -f .gpukit/b/install.sh ]] && { source .gpukit/b/install.sh || exit 1; }
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
fi
if [[ -z ${SGMODEL_CACHE:-} ]]; then  # the weights: carried in .devdata/sgcache, or where gpu_model.sh put them
  for c in $PWD/.devdata/sgcache /root/sgcache; do [[ -d $c ]] && { export SGMODEL_CACHE=$c; break; }; done
fi
export PYTHONUNBUFFERED=1
args=(--data "Middlebury2001=$data" --split test --method forward-splat --method naive-gs --resolution 256
      --out "$OUT/multiview" --device "$dev" --no-progress)
[[ -n $checkpoint ]] && args+=(--checkpoint "$checkpoint" "${@:2}")
[[ -n ${ENCODER:-} ]] && args+=(--encoder "$ENCODER")
[[ -n ${LPIPS_VGG:-} ]] && args+=(--lpips-vgg "$LPIPS_VGG")
python3 -m sgmodel.cli eval "${args[@]}"
