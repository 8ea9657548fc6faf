"""What storing a model's weights in bf16 costs, measured without the float32 original: the shipped file holds
bf16 weights (8 significant bits), which differ from the training run's float32 ones by at most half a bf16
unit in the last place (ulp). This script moves every weight of the checkpoint by another such rounding error
(uniform within +-half an ulp of its bf16 value, float32 kept, ``--seeds`` draws), evaluates each moved copy
with ``sgmodel eval`` on the same data, and reports how far PSNR and SSIM move from the checkpoint's own. A
score that does not move under a second rounding of that size did not depend on the first.

    python scripts/checks/weight_rounding.py --data .devdata/multiview --split test [--checkpoint default]
                                             [--seeds 0 1 2] [--device cpu] [--out report.md]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import markdown_table
from sgmodel.bench import report
from sgmodel.model.checkpoint import checkpoint_bytes, load_checkpoint
from sgmodel.weights import checkpoint_path


def bf16_ulp(w: torch.Tensor) -> torch.Tensor:
    """The spacing of bf16 values at each element of ``w`` (float32): 2^(exponent - 7); zero maps to the
    smallest normal's spacing."""
    _, exponent = torch.frexp(w.float().abs().clamp_min(torch.finfo(torch.bfloat16).tiny))
    return torch.ldexp(torch.ones_like(w, dtype=torch.float32), exponent - 8)


def moved(ckpt: dict, seed: int) -> dict:
    """``ckpt`` with every floating-point weight moved by uniform(-1/2, 1/2) bf16 ulps, in float32."""
    g = torch.Generator().manual_seed(seed)
    model = {}
    for k, v in ckpt["model"].items():
        if torch.is_tensor(v) and v.is_floating_point():
            noise = torch.rand(v.shape, generator=g) - 0.5
            v = v.float() + noise * bf16_ulp(v)
        model[k] = v
    return {**ckpt, "model": model}


def evaluate(checkpoint: Path, data: Path, split: str, device: str, out: Path) -> dict:
    """``sgmodel eval`` of ``checkpoint`` on ``data``: its metrics.json."""
    subprocess.run([sys.executable, "-m", "sgmodel.cli", "eval", "--data", str(data), "--split", split,
                    "--checkpoint", str(checkpoint), "--device", device, "--out", str(out), "--no-progress"],
                   check=True, cwd=REPO, stdout=subprocess.DEVNULL)
    return json.loads((out / "metrics.json").read_text())


def signed(x: float, digits: int) -> str:
    """``x`` with its sign at ``digits`` decimals; a change that rounds to zero is +0 (not -0)."""
    return f"{round(x, digits) or 0.0:+.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="a dataset folder (`import multiview` or `build`)")
    p.add_argument("--split", default="test")
    p.add_argument("--checkpoint", default="default", help="a checkpoint, or 'default': the shipped model")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", type=Path, help="also write the markdown report here")
    args = p.parse_args(argv)
    out = OwnedFile(args.out, "--out", "scripts/checks/weight_rounding.py")
    source = checkpoint_path(args.checkpoint)
    ckpt = load_checkpoint(source)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        base = evaluate(source, args.data, args.split, args.device, Path(tmp) / "base")["mean"]
        rows.append(["as stored", f"{base['psnr']:.3f}", f"{base['ssim']:.4f}", "", ""])
        for seed in args.seeds:
            path = Path(tmp) / f"moved{seed}.pt"
            path.write_bytes(checkpoint_bytes(moved(ckpt, seed)))
            m = evaluate(path, args.data, args.split, args.device, Path(tmp) / f"eval{seed}")["mean"]
            rows.append([f"moved by half a bf16 ulp at most, seed {seed}", f"{m['psnr']:.3f}", f"{m['ssim']:.4f}",
                         signed(m["psnr"] - base["psnr"], 3), signed(m["ssim"] - base["ssim"], 4)])
            print(rows[-1], flush=True)
    text = (f"`{args.checkpoint}` on `{args.data}` (split {args.split}, {args.device}), every weight moved by a "
            f"second bf16 rounding error:\n\n" + markdown_table(["weights", "PSNR", "SSIM", "PSNR change",
                                                                "SSIM change"], rows) + "\n")
    report(text, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
