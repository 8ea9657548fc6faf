"""Measuring one method on one split of one dataset (``evaluate``) and its report folder; the command that
runs it, and what it writes, is ``sgmodel.evaluation.command``."""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from scenesplat_stereo.common.commandline import Interrupted
from scenesplat_stereo.common.ownership import StagedFolder, check_apart, check_replaceable
from scenesplat_stereo.common.text import markdown_table, value_cell, whole_number
from sgmodel.args import add_precision_argument
from sgmodel.config import EncoderParams
from sgmodel.data.loader import check_valid_pixels, eval_batches, to_device
from sgmodel.encoders import DEFAULT_ENCODER
from sgmodel.encoders.flags import add_encoder_arguments, build_encoder, encoder_params
from sgmodel.metrics import image as metrics
from sgmodel.metrics.lpips import create_lpips
from sgmodel.metrics.sheets import target_sheet
from sgmodel.model.network import load_predictor
from sgmodel.model.render import render_views
from sgmodel.predict.inference import Reconstructor
from sgmodel.weights import SHIPPED, checkpoint_path, describe_checkpoint

METHODS = ("naive-gs", "forward-splat")
METRICS = ("psnr", "ssim", "lpips")
LABELS = ("key", "scene", "target", "group")  # the columns of a target's row that are not numbers
SHEET_TARGETS = 4  # worst and best targets shown in sheet.png
OWNER = "sgmodel eval"  # recorded in REPORT (ownership.OWNER_FILE): a later evaluation may replace it


@dataclass
class Method:
    """What renders a batch's targets: name, encoder name, resolution S, ``render(batch) -> [B,T,3,S,S]``, and
    what the trained model's convolutions compute in ("bf16 autocast" or "float32"; the baselines: float32)."""

    name: str
    encoder: str
    resolution: int
    render: object
    precision: str = "float32"


def checkpoint_method(checkpoint: str | Path | None, device: str, encoder_weights: str | None = None,
                      encoder_repo: str | None = None, encoder: str | None = None, amp: bool = False
                      ) -> Method:
    """The trained model (``--checkpoint``; the shipped one for None or its name), its encoder rebuilt as
    ``load_predictor`` does (the flags over the checkpoint's; ``amp``: bf16 autocast on CUDA)."""
    predictor = load_predictor(checkpoint_path(checkpoint), device, encoder_weights, encoder_repo, encoder, amp)

    def render(batch: dict) -> torch.Tensor:
        gaussians = predictor.predict(batch["left"], batch["right"], batch["K"], batch["baseline"]).gaussians
        S = batch["targets"].shape[-1]
        return render_views(gaussians, batch["target_viewmats"], batch["target_Ks"], S, S)[0]

    return Method(describe_checkpoint(checkpoint), predictor.model.encoder.name, predictor.resolution, render,
                  predictor.precision(device))


def baseline_method(name: str, encoder_params: EncoderParams, resolution: int, device: str) -> Method:
    """A baseline without learned prediction on the encoder ``encoder_params`` describes."""
    reconstructor = Reconstructor(method=name, encoder=build_encoder(encoder_params, device))

    def render(batch: dict) -> torch.Tensor:
        scenes = reconstructor(batch["left"], batch["right"], batch["K"], batch["baseline"])
        S = batch["targets"].shape[-1]
        return scenes.render(batch["target_viewmats"], batch["target_Ks"], S, S)

    return Method(name, encoder_params.name, resolution, render)


def measure(method: Method, loader, device: str, lpips_net, progress: bool = True) -> tuple[list[dict], list[dict]]:
    """Per-target rows, and the worst and best targets' images for the sheet."""
    rows, kept = [], []
    bar = tqdm(loader, disable=not progress, unit="pair", desc=f"eval {method.name}")
    for batch in bar:
        batch = to_device(batch, device)
        renders = method.render(batch).float().clamp(0, 1)
        B, T = renders.shape[:2]
        pred, gt, mask = renders.flatten(0, 1), batch["targets"].flatten(0, 1), batch["masks"].flatten(0, 1)
        values = {"psnr": metrics.psnr(pred, gt), "ssim": metrics.ssim(pred, gt),
                  "psnr_masked": metrics.psnr(pred, gt, mask), "ssim_masked": metrics.ssim(pred, gt, mask)}
        if lpips_net is not None:
            values["lpips"] = metrics.lpips(lpips_net, pred, gt)
            values["lpips_masked"] = metrics.lpips(lpips_net, pred, gt, mask)
        valid = mask.float().flatten(1).mean(1)
        groups = batch.get("target_groups")
        for i in range(B * T):
            b, t = divmod(i, T)
            row = {"key": batch["keys"][b], "scene": batch["scenes"][b], "target": int(batch["target_ids"][b, t])}
            if groups is not None:
                row["group"] = groups[b][t] if groups[b] is not None else ""
            row["valid_fraction"] = round(valid[i].item(), 6)
            row.update({k: v[i].item() for k, v in values.items()})
            rows.append(row)
            kept.append({"psnr": row["psnr"], "target": gt[i].cpu(), "render": pred[i].cpu(),
                         "caption": f"{row['key']} target {row['target']}: {row['psnr']:.2f} dB"})
        kept = sorted(kept, key=lambda e: e["psnr"])
        kept = kept[:SHEET_TARGETS] + kept[-SHEET_TARGETS:] if len(kept) > 2 * SHEET_TARGETS else kept
        bar.set_postfix(psnr=f"{sum(r['psnr'] for r in rows) / len(rows):.2f}")
    if not rows:
        raise ValueError("the split has no targets to evaluate")
    return rows, kept


def summarise(rows: list[dict]) -> dict:
    """Means over targets; a masked metric of a target without a valid pixel (NaN) is left out of its mean
    (``without_valid_pixels`` counts them), which is None (JSON null) when no target has one."""
    keys = [k for k in rows[0] if k not in LABELS]
    values = {k: [r[k] for r in rows if not math.isnan(r[k])] for k in keys}
    return {k: sum(v) / len(v) if v else None for k, v in values.items()}


def without_valid_pixels(rows: list[dict]) -> int:
    """How many targets have no valid pixel (their masked metrics are NaN, left out of the masked means)."""
    return sum(math.isnan(r["psnr_masked"]) for r in rows)


def group_means(rows: list[dict]) -> dict[str, dict]:
    """``summarise`` per target group (the samples' ``target_groups`` labels, e.g. "between" and "beside"),
    in order of appearance; empty when the targets carry no labels."""
    groups = dict.fromkeys(r["group"] for r in rows if r.get("group"))
    return {g: summarise([r for r in rows if r.get("group") == g]) for g in groups}


def scene_table(rows: list[dict]) -> str:
    """Means per scene and over all targets; with target groups, a line per scene and group and one per group
    over all scenes after each scene's (and the overall) line."""
    scenes = sorted({r["scene"] for r in rows})
    groups = list(dict.fromkeys(r["group"] for r in rows if r.get("group")))
    cols = [k for k in ("psnr", "ssim", "lpips", "psnr_masked", "ssim_masked", "lpips_masked") if k in rows[0]]
    body = []
    for s in scenes + ["all"]:
        for g in [None] + groups:
            sel = [r for r in rows if (s == "all" or r["scene"] == s) and (g is None or r.get("group") == g)]
            if not sel:
                continue
            mean = summarise(sel)
            body.append([s if g is None else f"{s} ({g})", len(sel)]
                        + [value_cell(mean[c], 2 if "psnr" in c else 4) for c in cols])
    return markdown_table(["scene", "targets"] + cols, body)


def _csv(rows: list[dict]) -> bytes:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue().encode()


def evaluate(method: Method, data: Path, split: str, out: Path, device: str, lpips_vgg: str | None,
             batch_size: int = 4, progress: bool = True) -> dict:
    """Run the evaluation and write the report; returns metrics.json's content."""
    loader = eval_batches(data, split, batch_size, method.resolution)
    lpips_net = create_lpips(lpips_vgg, device=device)
    rows, kept = measure(method, loader, device, lpips_net, progress)
    result = {"method": method.name, "encoder": method.encoder, "split": split, "data": str(Path(data).resolve()),
              "resolution": method.resolution, "precision": method.precision, "targets": len(rows),
              "lpips": "LPIPS-VGG v0.1" if lpips_net is not None else "not computed (no VGG16 ImageNet weights)",
              "mean": summarise(rows), "targets_without_valid_pixels": without_valid_pixels(rows)}
    if group_means(rows):
        result["groups"] = group_means(rows)
        result["group_targets"] = {g: sum(r.get("group") == g for r in rows) for g in result["groups"]}
    with StagedFolder(out, OWNER) as tmp:
        (tmp / "metrics.json").write_text(json.dumps(result, indent=2) + "\n")
        (tmp / "targets.csv").write_bytes(_csv(rows))
        (tmp / "scenes.md").write_text(scene_table(rows) + "\n")
        (tmp / "sheet.png").write_bytes(target_sheet(kept))
    return result


def benchmark_flag(text: str) -> tuple[str, Path]:
    """``--data [NAME=]PATH``: a benchmark's name (default: its folder's name) and folder (a path that holds
    '=' needs a NAME)."""
    name, _, path = text.partition("=") if "=" in text else ("", "", text)
    if not path:  # Path("") is the current folder: never evaluate that by accident
        raise argparse.ArgumentTypeError(f"--data {text!r}: no PATH (give [NAME=]PATH)")
    path = Path(path)
    return (name or path.resolve().name), path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=benchmark_flag, action="append", required=True, metavar="[NAME=]PATH",
                   help="dataset folder written by `scenesplat-stereo build` or `import`; repeat it for a table over "
                        "several benchmarks (NAME labels its columns; default: the folder's name)")
    p.add_argument("--split", choices=("val", "test"), default="val", help="split to evaluate (default val)")
    p.add_argument("--checkpoint", help=f"a checkpoint written by `sgmodel train` (best.pt), or {SHIPPED.name!r}: the "
                   "model shipped in the package (the default when neither --checkpoint nor --method is given)")
    p.add_argument("--method", choices=METHODS, action="append",
                   help="a baseline without learned prediction; repeat it (with or without --checkpoint) for a table")
    add_encoder_arguments(p, f"the checkpoint's; {DEFAULT_ENCODER} for --method")
    p.add_argument("--resolution", type=whole_number("--resolution", 16), default=256,
                   help="S for a baseline (a checkpoint uses its own)")
    p.add_argument("--out", type=Path, required=True, help="report folder")
    p.add_argument("--batch-size", type=whole_number("--batch-size"), default=4, help="pairs per batch (default 4)")
    p.add_argument("--lpips-vgg", help="VGG16 ImageNet weights for LPIPS (default: torch's hub cache)")
    add_precision_argument(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def check_report_folder(out: Path, inputs: dict[str, Path | None]) -> None:
    """REPORT may be replaced by a new report: absent, empty or an earlier report, writable, apart from the
    ``inputs`` ({flag: path}: the data, the checkpoint); ValueError naming --out. Reads only."""
    check_apart(out, "--out", inputs, replaced=True)
    check_replaceable(out, "--out", OWNER)


def methods_of(args: argparse.Namespace) -> list[str]:
    """What ``sgmodel eval`` measures: "checkpoint" (``--checkpoint``) and the ``--method`` baselines, in
    order, each once; ValueError when there is none. Several methods or ``--data`` folders make a table
    (``sgmodel.evaluation.table2.run_table``), one of each a report (``report``)."""
    methods = (["checkpoint"] if args.checkpoint or not args.method else []) + list(dict.fromkeys(args.method or []))
    return methods


def eval_inputs(args: argparse.Namespace) -> dict[str, Path | None]:
    """The inputs a report must stay apart from, by flag: each ``--data`` folder (its split checked to exist
    and to have a valid pixel in some target: ``check_valid_pixels``) and ``--checkpoint``."""
    for _, path in args.data:
        check_valid_pixels(path, args.split)
    checkpoint = checkpoint_path(args.checkpoint) if args.checkpoint or not args.method else None
    return {f"--data {name}={path}": path for name, path in args.data} | {"--checkpoint": checkpoint}


def method_of(name: str, args: argparse.Namespace, device: str) -> Method:
    """The Method an ``eval_methods`` name stands for: the ``--checkpoint`` or a baseline with the encoder flags."""
    if name == "checkpoint":
        return checkpoint_method(args.checkpoint, device, args.encoder_weights, args.encoder_repo, args.encoder,
                                 args.amp)
    return baseline_method(name, encoder_params(args), args.resolution, device)


def report(args: argparse.Namespace, method_name: str, device: str) -> int:
    """``sgmodel eval`` with one ``--data`` folder and one method: REPORT is ``--out``."""
    check_report_folder(args.out, eval_inputs(args))
    method = method_of(method_name, args, device)
    try:
        result = evaluate(method, args.data[0][1], args.split, args.out, device, args.lpips_vgg, args.batch_size,
                          not args.no_progress)
    except KeyboardInterrupt:
        raise Interrupted(f"--out {args.out} is as it was (a report replaces it only when complete); rerun the "
                          f"same command") from None
    print((args.out / "scenes.md").read_text())
    left_out = result["targets_without_valid_pixels"]
    note = f" ({left_out} without a valid pixel, left out of the masked means)" if left_out else ""
    print(f"{result['targets']} targets{note}; report in {args.out}")
    return 0
