"""Rendering of stereo samples: all cameras of several pairs (left, right, targets) in one rasteriser call,
and the images' trip to host memory overlapped with the next call.

On CUDA, a batch's uint8 images, masks and depth are copied to pinned host memory on a separate copy
stream while the compute stream already renders the next batch (``stream_samples``), so a build is
bound by the slower of rendering and copying, not by their sum. On the CPU everything is synchronous.
Images: ``round(clip(x, 0, 1) * 255)`` as uint8; masks: rendered alpha >= ``MASK_ALPHA_THRESHOLD``;
depth (optional): the left camera's expected depth in world units. With an ``NvJpegEncoder``
(``--jpeg-encoder nvjpeg``) the colour images are JPEG-encoded on the GPU (by the encoder's own thread
and stream, while the next batch renders) instead of copied, and only their bytes reach the host.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np
import torch

from scenesplat_stereo.build.protocol import MASK_ALPHA_THRESHOLD, SamplePlan
from scenesplat_stereo.raster import rasterization, tile_size_for
from scenesplat_stereo.scene.cameras import viewmats_from_c2w
from scenesplat_stereo.shards.encode import SampleImages, jpeg_members
from scenesplat_stereo.shards.nvjpeg import NvJpegEncoder
from scenesplat_stereo.shards.sample import SampleMeta

_copy_streams: dict[torch.device, torch.cuda.Stream] = {}


@dataclass
class RenderedBatch:
    """A rendered batch on its way to host memory; ``samples()`` waits for the copy and unpacks it."""

    plans: list[SamplePlan]
    rgb8: torch.Tensor | None  # [B, 2 + T, H, W, 3] uint8, host (None when ``jpegs`` holds them)
    masks: torch.Tensor  # [B, T, H, W] bool, host
    depth: torch.Tensor | None  # [B, H, W] float32, host
    copied: torch.cuda.Event | None
    jpegs: Future | None = None  # list of the B * (2 + T) images' JPEG bytes, encoded on the device

    def samples(self) -> list[SampleImages]:
        if self.copied is not None:
            self.copied.synchronize()
        masks = self.masks.numpy()
        rgb8 = None if self.rgb8 is None else self.rgb8.numpy()
        depth = None if self.depth is None else self.depth.numpy()
        blobs = None if self.jpegs is None else iter(self.jpegs.result())
        out = []
        for i, p in enumerate(self.plans):
            ids = tuple(p.target_ids)
            images = (None, None, None) if rgb8 is None else (rgb8[i, 0], rgb8[i, 1], rgb8[i, 2:])
            out.append(SampleImages(
                p.key, *images, masks=masks[i], target_ids=ids, meta=SampleMeta.from_plan(p).to_json(),
                depth=None if depth is None else depth[i],
                jpegs=None if blobs is None else {name: next(blobs) for name in jpeg_members(ids)}))
        return out


def _to_host(tensors: list[torch.Tensor | None]) -> tuple[list[torch.Tensor | None], torch.cuda.Event | None]:
    """Start copying device tensors to pinned host memory on the device's copy stream."""
    first = next(t for t in tensors if t is not None)
    if first.device.type != "cuda":
        return tensors, None
    stream = _copy_streams.setdefault(first.device, torch.cuda.Stream(first.device))
    stream.wait_stream(torch.cuda.current_stream(first.device))
    out = []
    with torch.cuda.stream(stream):
        for t in tensors:
            if t is None:
                out.append(None)
                continue
            host = torch.empty(t.shape, dtype=t.dtype, pin_memory=True)
            host.copy_(t, non_blocking=True)
            t.record_stream(stream)  # keep the device buffer alive until the copy has run
            out.append(host)
        event = torch.cuda.Event()
        event.record(stream)
    return out, event


def start_render(gaussians: dict, sh_degree: int, plans: list[SamplePlan], device: str, with_depth: bool = False,
                 effects=None, rasterize=rasterization, jpeg: NvJpegEncoder | None = None) -> RenderedBatch:
    """Render the cameras of ``plans`` (one teacher, one image size; left, right, targets each) in ONE
    ``rasterize`` call (ours, or gsplat's for ``bench build --gsplat``; antialiased, the teacher's SH degree,
    black background) and start their copy to host memory (with ``jpeg``: their JPEG encoding on the
    device, and the copy of the bytes only)."""
    p0 = plans[0]
    width, height, per = p0.width, p0.height, 2 + len(p0.target_ids)
    c2w = np.stack([np.concatenate([p.c2w_left[None], p.c2w_right[None], p.c2w_targets]) for p in plans])
    viewmats = torch.from_numpy(viewmats_from_c2w(c2w.reshape(-1, 4, 4))).float().to(device)
    Ks_pair = torch.from_numpy(np.stack([p.K for p in plans])).float().to(device)
    with torch.no_grad():
        colors, alphas, _ = rasterize(
            **gaussians, viewmats=viewmats, Ks=Ks_pair.repeat_interleave(per, dim=0), width=width, height=height,
            sh_degree=sh_degree, render_mode="RGB+ED" if with_depth else "RGB", rasterize_mode="antialiased",
            tile_size=tile_size_for(device))
        colors = colors.reshape(len(plans), per, height, width, -1)
        rgb = colors[..., :3]
        if effects is not None:
            stereo = effects.apply(rgb[:, :2], [p.key for p in plans], Ks_pair)
            rgb = torch.cat([stereo, rgb[:, 2:]], dim=1)
        rgb8 = (rgb.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
        masks = alphas.reshape(len(plans), per, height, width)[:, 2:] >= MASK_ALPHA_THRESHOLD
        depth = colors[:, 0, :, :, 3].contiguous() if with_depth else None
    if jpeg is not None:
        jpegs = jpeg.encode(rgb8.reshape(-1, height, width, 3))
        (masks, depth), event = _to_host([masks, depth])
        return RenderedBatch(plans, None, masks, depth, event, jpegs)
    (rgb8, masks, depth), event = _to_host([rgb8, masks, depth])
    return RenderedBatch(plans, rgb8, masks, depth, event)


def stream_samples(batches: Iterable[list[SamplePlan]], render) -> Iterator[list[SampleImages]]:
    """The samples of each batch, in order; ``render(batch)`` (a ``start_render`` call) for batch k+1 is
    issued before batch k's images are waited for, so the GPU renders while the copy engine copies."""
    pending = None
    for batch in batches:
        started = render(batch)
        if pending is not None:
            yield pending.samples()
        pending = started
    if pending is not None:
        yield pending.samples()
