"""``sgmodel eval``: render every stored target of a split and measure it as the paper does.

Methods: a trained checkpoint (``--checkpoint``), or a baseline without learned prediction
(``--method naive-gs|forward-splat``, sgmodel.model.baselines through sgmodel.predict.inference: pixels without a valid
stereo depth make no Gaussian and splat nothing) on any encoder's disparity. Several methods or several
``--data`` folders make one table in the layout of the paper's Table 2 (sgmodel.evaluation.table2). Metrics (SPEC
section 7, sgmodel.metrics.image): PSNR on images clipped to [0, 1], skimage-style SSIM, LPIPS-VGG on [-1, 1]
when the VGG16 weights are available; each over the full image and over the valid mask.

Writes REPORT/ after every input is checked (the data split, the checkpoint or encoder, the LPIPS weights,
and REPORT itself: absent, empty or an earlier report, apart from the data; a split in which no target has
a valid pixel is refused): ``metrics.json`` (means, target count, encoder, method or checkpoint, its precision,
split; per target group too when the samples label their targets, as ``scenesplat-stereo import multiview`` does:
"between" and "beside"; a target without a valid pixel is left out of the masked means and counted,
``targets_without_valid_pixels``, and a mean over no target is null), ``targets.csv`` (one row per target),
``scenes.md`` (a table per scene), and ``sheet.png`` (the worst and the best targets by PSNR: target |
render). The report is built in a staging folder that replaces REPORT as a whole
(``scenesplat_stereo.common.ownership.StagedFolder``); Ctrl-C leaves REPORT as it was (a table keeps the reports
it finished), with one line saying so (exit 130).
"""

from __future__ import annotations

import argparse

from sgmodel.args import add_device_argument, device_from_flag
from sgmodel.evaluation import evaluate, table2


def add_arguments(p: argparse.ArgumentParser) -> None:
    evaluate.add_arguments(p)
    add_device_argument(p)


def run(args: argparse.Namespace) -> int:
    methods = evaluate.methods_of(args)
    if len(args.data) > 1 or len(methods) > 1:  # a table in the layout of the paper's Table 2
        return table2.run_table(args, methods, device_from_flag(args.device))
    return evaluate.report(args, methods[0], device_from_flag(args.device))
