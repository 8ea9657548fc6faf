#!/usr/bin/env bash
# Packs Ray (`scenesplat-stereo build --backend ray`) for the lent GPU machine, whose image has no Ray and
# reaches no package index. Ray's wheel (about 80 MB) is more than one call carries (64 MiB); without Java
# (ray/jars) and the libraries the build does not use (rllib, serve, tune, train, data, llm, workflow),
# xz-compressed, it is about 30 MB. Ray's dependencies the image lacks (jsonschema and its own) come along.
#   bash scripts/inputs/ray_kit.sh [DIR=.raykit] [VERSION=2.60.0]     here, once (DIR is git-ignored)
#   a call carrying DIR:  source DIR/install.sh                (Ray importable, `ray` on PATH)
set -euo pipefail
dir=${1:-.raykit}; ver=${2:-2.60.0}
rm -rf "$dir"; mkdir -p "$dir"; work=$(mktemp -d)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux2014_x86_64 -d "$work" "ray==$ver" jsonschema jsonschema-specifications referencing rpds-py
(cd "$work" && for w in ./*.whl; do unzip -q -o "$w"; done && rm -f ./*.whl \
  && rm -rf ray/jars ray/rllib ray/serve ray/tune ray/train ray/data ray/llm ray/workflow \
  && tar -cf - ./* | xz -T0 -6 > /tmp/raykit.$$.tar.xz && rm -rf ./* && mv /tmp/raykit.$$.tar.xz kit.tar.xz)
mv "$work/kit.tar.xz" "$dir/kit.tar.xz"
cat > "$dir/install.sh" <<'SH'
# sourced: unpacks Ray once per machine, puts it on PYTHONPATH and its `ray` command on PATH
_kit=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
if [[ ! -d /root/raykit/site/ray ]]; then
  mkdir -p /root/raykit/site /root/raykit/bin
  xz -dc "$_kit/kit.tar.xz" | tar -xf - -C /root/raykit/site || return 1
  printf '#!/usr/bin/env python3\nimport sys\nfrom ray.scripts.scripts import main\nsys.exit(main())\n' \
    > /root/raykit/bin/ray && chmod +x /root/raykit/bin/ray
  chmod +x /root/raykit/site/ray/core/src/ray/*/* 2>/dev/null || true
fi
export PYTHONPATH=/root/raykit/site${PYTHONPATH:+:$PYTHONPATH} PATH=/root/raykit/bin:$PATH
python3 -c "import ray; print('ray', ray.__version__)"
SH
rm -rf "$work"; ls -la "$dir"
