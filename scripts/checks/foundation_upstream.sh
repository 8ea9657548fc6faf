#!/usr/bin/env bash
# The foundation-stereo and fast-foundation-stereo encoders end to end with the real upstream code and random
# weights in their releases' layout, offline (an empty torch hub cache; every Python process below refuses network
# access through an audit hook and records any attempt), on a tiny demo dataset:
#   scripts/checks/foundation_releases.py (FS 23-51-11 configuration, FFS serialised, FFS pruned)
#   scripts/checks/foundation_parity.py (both encoders in one process, both orders, outputs = the upstream modules')
#   sgmodel predict and eval (baselines and checkpoints), bench encoders (all in one process), ablate (train,
#   eval of the checkpoint and both baselines) with each encoder, train with the pruned one, encode (the encoder
#   cache) then train and ablate from it with each encoder, and failures that must be one line with exit status 2. On 2 busy CPU cores this takes hours (FoundationStereo: about a minute
#   per 32x32 forward); on a larger machine far less.
#
# Usage: scripts/checks/foundation_upstream.sh FOUNDATIONSTEREO_CHECKOUT FAST_FOUNDATIONSTEREO_CHECKOUT [WORK]
# Run it in an environment with their requirements and this package installed (docs/encoders.md); PYTHON
# picks the interpreter (default: python). WORK (default: a new temporary folder) receives everything.
set -euo pipefail
[ $# -ge 2 ] || { sed -n '2,15p' "$0"; exit 2; }
FS=$(realpath "$1")
FFS=$(realpath "$2")
WORK=$(realpath -m "${3:-$(mktemp -d)}")
PY=${PYTHON:-python}
cd "$(dirname "$0")/../.."
mkdir -p "$WORK/nonet"
export TORCH_HOME="$WORK/torch_home" PYTHONWARNINGS=ignore PYTHONPATH="$WORK/nonet${PYTHONPATH:+:$PYTHONPATH}"
rm -rf "$TORCH_HOME" "$WORK/network_attempts.txt"
mkdir -p "$TORCH_HOME"
cat > "$WORK/nonet/sitecustomize.py" <<EOF
import sys

def _no_network(event, args):
    if event == "socket.getaddrinfo" or (event == "socket.connect" and isinstance(args[1], tuple)):
        with open("$WORK/network_attempts.txt", "a") as f:
            f.write(f"{event} {args[1:]} in {' '.join(sys.argv)}\n")
        raise OSError(f"network access refused by scripts/checks/foundation_upstream.sh: {event} {args[1:]}")

sys.addaudithook(_no_network)
EOF
sg() { echo "+ sgmodel $*"; "$PY" -m sgmodel.cli "$@"; }
expect_error() {  # PATTERN sgmodel-arguments...: exit status 2 and one line on stderr matching PATTERN
    local pattern=$1; shift
    echo "+ sgmodel $* (must fail)"
    local rc=0
    "$PY" -m sgmodel.cli "$@" > "$WORK/out.txt" 2> "$WORK/err.txt" || rc=$?
    # stderr may also hold third-party warnings (torch's logger); ours is one "sgmodel CMD: error: ..." line
    if [ "$rc" != 2 ] || [ "$(grep -c '^sgmodel [a-z ]*: error: ' "$WORK/err.txt")" != 1 ] \
        || grep -q Traceback "$WORK/err.txt" || ! grep -q -- "$pattern" "$WORK/err.txt"; then
        echo "FAIL: exit $rc, stderr:"; cat "$WORK/err.txt"; exit 1
    fi
    echo "ok: exit 2: $(grep '^sgmodel [a-z ]*: error: ' "$WORK/err.txt")"
}

echo "== checkouts: FoundationStereo $(git -C "$FS" rev-parse HEAD 2>/dev/null || echo '(no git)'), "\
"Fast-FoundationStereo $(git -C "$FFS" rev-parse HEAD 2>/dev/null || echo '(no git)')"
"$PY" -c "import torch, torchvision, timm, omegaconf; print('torch', torch.__version__, 'torchvision', \
torchvision.__version__, 'timm', timm.__version__, 'omegaconf', omegaconf.__version__)"

echo "== releases with random weights"
"$PY" scripts/checks/foundation_releases.py --fs-repo "$FS" --ffs-repo "$FFS" --out "$WORK/releases"
R=$WORK/releases
FSW=$R/FoundationStereo/23-51-11/model_best_bp2.pth
FFSW=$R/Fast-FoundationStereo/23-36-37/model_best_bp2_serialize.pth
PRW=$R/Fast-FoundationStereo/pruned/model_best_bp2_serialize.pth
FSF=(--encoder foundation-stereo --encoder-weights "$FSW" --encoder-repo "$FS")
FFSF=(--encoder fast-foundation-stereo --encoder-weights "$FFSW" --encoder-repo "$FFS")
PRF=(--encoder fast-foundation-stereo --encoder-weights "$PRW" --encoder-repo "$FFS")

echo "== parity with the upstream modules, both encoders in one process"
"$PY" scripts/checks/foundation_parity.py --fs-repo "$FS" --ffs-repo "$FFS" --releases "$R" --size 64x32

echo "== a tiny demo dataset"
"$PY" -m scenesplat_stereo.cli demo-teachers "$WORK/teachers" --scenes 2 --frames 4 --gaussians 3000 --size 64x48 \
    --no-progress
"$PY" -m scenesplat_stereo.cli build --teachers "$WORK/teachers" --out "$WORK/data" --val-scenes 1 --with-depth \
    --workers 1 --no-progress
"$PY" - "$WORK" <<'EOF'
import sys
from pathlib import Path
import numpy as np
from scenesplat_stereo.shards.encode import encode_png
work = Path(sys.argv[1])
img = (np.random.default_rng(0).random((72, 104, 3)) * 255).astype(np.uint8)
(work / "left.png").write_bytes(encode_png(img[:, :96]))  # left(x) = right(x - 8): disparity 8 px
(work / "right.png").write_bytes(encode_png(img[:, 8:]))
# baseline 1 m: the random-weight encoders report 38 to 211 px on this pair, and at the model size (fx = 40 px)
# that is z = fx B / d = 0.19 to 1.05 m, inside the model's range (predict refuses a depth map at the clamp)
(work / "K.txt").write_text("80 0 48 0 80 36 0 0 1\n1.0\n")
EOF
PAIR=(--left "$WORK/left.png" --right "$WORK/right.png" --calib "$WORK/K.txt" --device cpu)
TINY=(--preset cpu-small --resolution 32 --padding 2 --steps 2 --batch-size 2 --targets 2 --val-every 2
      --val-samples 2 --workers 0 --no-progress --device cpu)

echo "== predict and eval with the baselines"
sg predict "${PAIR[@]}" --method naive-gs "${FSF[@]}" --resolution 32 --out "$WORK/predict-fs"
sg predict "${PAIR[@]}" --method forward-splat "${FFSF[@]}" --resolution 32 --out "$WORK/predict-ffs"
sg eval --data "$WORK/data" --method naive-gs "${FSF[@]}" --resolution 32 --out "$WORK/eval-fs-naive-gs" \
    --device cpu --no-progress
sg eval --data "$WORK/data" --method forward-splat "${FFSF[@]}" --resolution 32 --out "$WORK/eval-ffs-forward-splat" \
    --device cpu --no-progress

echo "== bench encoders: four encoders in one process"
sg bench encoders --data "$WORK/data" --resolution 32 --batch-size 2 --device cpu --out "$WORK/bench-encoders.md" \
    --encoders "foundation-stereo,weights=$FSW,repo=$FS" "fast-foundation-stereo,weights=$FFSW,repo=$FFS" \
    "fast-foundation-stereo,weights=$PRW,repo=$FFS" sgbm

echo "== ablate (train, eval of the checkpoint and both baselines) with each encoder; train the pruned one"
sg ablate --data "$WORK/data" --out "$WORK/ablate-fs" --only default "${FSF[@]}" "${TINY[@]}"
sg ablate --data "$WORK/data" --out "$WORK/ablate-ffs" --only default "${FFSF[@]}" "${TINY[@]}"
sg train --data "$WORK/data" --out "$WORK/run-pruned" "${PRF[@]}" "${TINY[@]}"

echo "== the encoder cache: each encoder's outputs cached once, then train and ablate from them"
for enc in fs ffs; do
    if [ $enc = fs ]; then F=("${FSF[@]}"); else F=("${FFSF[@]}"); fi
    sg encode --data "$WORK/data" --out "$WORK/cache-$enc" "${F[@]}" --preset cpu-small --resolution 32 --device cpu \
        --workers 0 --no-progress
    sg train --data "$WORK/data" --out "$WORK/run-cache-$enc" "${F[@]}" "${TINY[@]}" --encoder-cache "$WORK/cache-$enc"
    sg ablate --data "$WORK/data" --out "$WORK/ablate-cache-$enc" --only default "${F[@]}" "${TINY[@]}" \
        --encoder-cache "$WORK/cache-$enc"
done
expect_error "field 'encoder'" train --data "$WORK/data" --out "$WORK/x" "${PRF[@]}" "${TINY[@]}" \
    --encoder-cache "$WORK/cache-ffs"  # the pruned release's encoder: not the one the cache was made with

echo "== eval and predict the checkpoints"
sg eval --data "$WORK/data" --checkpoint "$WORK/ablate-ffs/shared-default/run/checkpoints/best.pt" \
    --out "$WORK/eval-run-ffs" --device cpu --no-progress
for run in ablate-fs/shared-default/run ablate-ffs/shared-default/run run-pruned; do
    sg predict "${PAIR[@]}" --checkpoint "$WORK/$run/checkpoints/best.pt" --out "$WORK/predict-${run%%/*}"
done

echo "== failures are one line with exit status 2"
rm -rf "$WORK/FS-without-dinov2" && cp -r "$FS" "$WORK/FS-without-dinov2" && rm -rf "$WORK/FS-without-dinov2/dinov2"
expect_error "needs your checkout of NVlabs/FoundationStereo" eval --data "$WORK/data" --method naive-gs \
    --encoder foundation-stereo --encoder-weights "$FSW" --out "$WORK/x" --device cpu --no-progress
expect_error "has no dinov2/hubconf.py" eval --data "$WORK/data" --method naive-gs --encoder foundation-stereo \
    --encoder-weights "$FSW" --encoder-repo "$WORK/FS-without-dinov2" --out "$WORK/x" --device cpu --no-progress
expect_error "building FoundationStereo with .*cfg.yaml failed" bench encoders --data "$WORK/data" --device cpu \
    --encoders "foundation-stereo,weights=$FFSW,repo=$FS"  # the cfg.yaml beside it is Fast-FoundationStereo's
expect_error "expected the serialised FastFoundationStereo" bench encoders --data "$WORK/data" --device cpu \
    --encoders "fast-foundation-stereo,weights=$FSW,repo=$FFS"
expect_error "not a serialised Fast-FoundationStereo model" bench encoders --data "$WORK/data" --device cpu \
    --encoders "fast-foundation-stereo,weights=$FFSW,repo=$FS"
expect_error "was trained with encoder 'fast-foundation-stereo'" predict "${PAIR[@]}" \
    --checkpoint "$WORK/ablate-ffs/shared-default/run/checkpoints/best.pt" "${FSF[@]}" --out "$WORK/x"
[ ! -e "$WORK/x" ] || { echo "FAIL: a failed command wrote $WORK/x"; exit 1; }

echo "== offline"
if [ -e "$WORK/network_attempts.txt" ]; then
    echo "FAIL: network access attempted:"; cat "$WORK/network_attempts.txt"; exit 1
fi
[ -z "$(ls -A "$TORCH_HOME")" ] || { echo "FAIL: the torch hub cache $TORCH_HOME is not empty"; exit 1; }
echo "ok: no network access attempted; the torch hub cache is still empty"
cat "$WORK/bench-encoders.md" "$WORK/ablate-fs/table.md" "$WORK/ablate-ffs/table.md"
echo "== all checks passed ($WORK)"
