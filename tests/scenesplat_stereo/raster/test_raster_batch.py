"""``rasterization`` with batch dimensions (gsplat 1.5's ``[..., N, 3]`` / ``[..., C, 4, 4]`` convention).

A batch is a set of independent scenes rendered in one call: every stage runs once for all of them, and
each scene's outputs and gradients must equal, bit for bit on the CPU, those of rendering the scene alone
(the same float32 operations in the same order: the per-Gaussian walks over cameras stay within a scene,
the sort keeps each tile's list in the same order, and the CPU's serial atomics add in the same order).
Truth for the batched values is therefore the unbatched call, which tests/scenesplat_stereo/raster/test_raster_forward.py and
tests/scenesplat_stereo/raster/test_raster_backward.py hold to the float64 reference; the last tests here also hold a batched call
to that reference directly.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.raster.reference import reference_rasterization
from tests.support.scenes import assert_matches_reference, camera_rig, knife_edge_pixels, random_scene

W, H = 24, 16
TILE = 8
PARAMS = ("means", "quats", "scales", "opacities", "colors")


def stack_scenes(scenes: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.stack([s[k] for s in scenes]) for k in PARAMS}


def batch_inputs(batch: tuple[int, ...], n: int, C: int, sh_degree: int | None, seed: int = 0):
    """(scenes [..., N, ...], viewmats [..., C, 4, 4], Ks [..., C, 3, 3], backgrounds [..., C, 3]) with a
    different scene, camera rig and background per batch index."""
    B = math.prod(batch)
    scenes = stack_scenes([random_scene(n, seed + 10 * b, sh_degree=sh_degree) for b in range(B)])
    rigs = [camera_rig(C, W, H, seed=seed + b) for b in range(B)]
    viewmats = torch.stack([r[0] for r in rigs])
    Ks = torch.stack([r[1] for r in rigs])
    bgs = torch.rand(B, C, 3, generator=torch.Generator().manual_seed(seed))
    shape = lambda t: t.reshape(*batch, *t.shape[1:])  # noqa: E731
    return ({k: shape(v) for k, v in scenes.items()}, shape(viewmats), shape(Ks), shape(bgs))


def render_with_grads(scene, viewmats, Ks, backgrounds, **kwargs):
    """(render, alphas, grads of sum(w_c render) + sum(w_a alphas) for every parameter and the background,
    meta, (w_c, w_a)), random weights w at the outputs' shapes."""
    leaves = {k: v.detach().clone().requires_grad_() for k, v in scene.items()}
    bg = None if backgrounds is None else backgrounds.detach().clone().requires_grad_()
    render, alphas, meta = rasterization(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                         leaves["colors"], viewmats, Ks, W, H, backgrounds=bg, tile_size=TILE,
                                         **kwargs)
    g = torch.Generator().manual_seed(0)
    w_c = torch.randn(render.shape, generator=g)
    w_a = torch.randn(alphas.shape, generator=g)
    ((render * w_c).sum() + (alphas * w_a).sum()).backward()
    grads = {k: leaves[k].grad for k in PARAMS}
    if bg is not None:
        grads["backgrounds"] = bg.grad
    return render.detach(), alphas.detach(), grads, meta, (w_c, w_a)


def assert_batch_equals_scenes(scene, viewmats, Ks, backgrounds, batch: tuple[int, ...], **kwargs) -> dict:
    """Render the batch once and every scene alone with the same cotangents; assert equality bit for bit."""
    B = math.prod(batch)
    flat = lambda t: None if t is None else t.reshape(B, *t.shape[len(batch):])  # noqa: E731
    render, alphas, grads, meta, (w_c, w_a) = render_with_grads(scene, viewmats, Ks, backgrounds, **kwargs)
    C = viewmats.shape[-3]
    assert render.shape == (*batch, C, H, W, render.shape[-1]) and alphas.shape == (*batch, C, H, W, 1)
    w_c, w_a = flat(w_c), flat(w_a)  # each scene alone gets its slice of the batch's loss weights
    for b in range(B):
        leaves = {k: flat(v)[b].detach().clone().requires_grad_() for k, v in scene.items()}
        bg = None if backgrounds is None else flat(backgrounds)[b].detach().clone().requires_grad_()
        r, a, m = rasterization(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                leaves["colors"], flat(viewmats)[b], flat(Ks)[b], W, H, backgrounds=bg,
                                tile_size=TILE, **kwargs)
        ((r * w_c[b]).sum() + (a * w_a[b]).sum()).backward()
        assert torch.equal(flat(render)[b], r.detach()), f"scene {b}: image differs from its own render"
        assert torch.equal(flat(alphas)[b], a.detach()), f"scene {b}: alphas differ from its own render"
        for key in ("means2d", "conics", "depths", "radii"):
            assert torch.equal(flat(meta[key])[b], m[key]), f"scene {b}: meta[{key!r}] differs"
        mine = {k: leaves[k].grad for k in PARAMS} | ({} if bg is None else {"backgrounds": bg.grad})
        for k, v in mine.items():
            batched = None if grads[k] is None else flat(grads[k])[b]
            assert (v is None) == (batched is None), f"scene {b}: gradient of {k} present in one call only"
            if v is not None:
                assert torch.equal(batched, v), (
                    f"scene {b}: gradient of {k} differs, max |diff| {float((batched - v).abs().max())}")
    return dict(render=render, alphas=alphas, grads=grads, meta=meta)


@pytest.mark.parametrize("deterministic", [False, True])
@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
@pytest.mark.parametrize("sh_degree", [2, None])
def test_batch_equals_per_scene_calls(sh_degree, rasterize_mode, render_mode, deterministic) -> None:
    """Three scenes of different content, cameras and backgrounds in one call equal three calls."""
    n = 40 if deterministic else 120
    scene, viewmats, Ks, bgs = batch_inputs((3,), n, 2, sh_degree, seed=1)
    out = assert_batch_equals_scenes(scene, viewmats, Ks, bgs, (3,), sh_degree=sh_degree,
                                     rasterize_mode=rasterize_mode, render_mode=render_mode,
                                     deterministic=deterministic)
    # The scenes differ, so a mix-up of scenes or cameras could not pass the comparison above unnoticed.
    assert not torch.equal(out["render"][0], out["render"][1])
    assert float(out["alphas"].amax()) > 0.5
    assert out["meta"]["batch_dims"] == (3,) and out["meta"]["means2d"].shape == (3, 2, n, 2)
    assert out["meta"]["flatten_ids"].numel() > 0 and int(out["meta"]["flatten_ids"].max()) >= 2 * 2 * n


def test_batch_of_one_equals_the_unbatched_call() -> None:
    scene, viewmats, Ks, bgs = batch_inputs((1,), 150, 3, 2, seed=4)
    out = assert_batch_equals_scenes(scene, viewmats, Ks, bgs, (1,), sh_degree=2, rasterize_mode="antialiased",
                                     render_mode="RGB+ED")
    assert out["render"].shape == (1, 3, H, W, 4)


def test_two_leading_dims() -> None:
    """[2, 3] scenes: the leading shape is kept on the outputs, meta and gradients."""
    scene, viewmats, Ks, bgs = batch_inputs((2, 3), 60, 2, None, seed=7)
    out = assert_batch_equals_scenes(scene, viewmats, Ks, bgs, (2, 3), render_mode="RGB+ED")
    assert out["grads"]["means"].shape == (2, 3, 60, 3) and out["grads"]["backgrounds"].shape == (2, 3, 2, 3)
    assert out["meta"]["radii"].shape == (2, 3, 2, 60, 2) and out["meta"]["batch_dims"] == (2, 3)


@pytest.mark.parametrize("deterministic", [False, True])
def test_empty_scenes_inside_a_batch(deterministic: bool) -> None:
    """Scenes whose Gaussians are all transparent, all behind the cameras, or all culled by a zero
    quaternion, between two ordinary scenes: background only, zero gradients, and the ordinary scenes are
    rendered as if alone."""
    n = 40
    scene, viewmats, Ks, bgs = batch_inputs((5,), n, 2, 2, seed=11)
    scene["opacities"][1] = 0.0
    scene["means"][2, :, 2] = -scene["means"][2, :, 2] - 5.0  # behind every camera (rig within 1 unit of 0)
    scene["quats"][3] = 0.0
    out = assert_batch_equals_scenes(scene, viewmats, Ks, bgs, (5,), sh_degree=2, render_mode="RGB+ED",
                                     deterministic=deterministic)
    for b in (1, 2, 3):
        assert bool((out["alphas"][b] == 0).all()), f"empty scene {b} has alpha > 0"
        assert torch.equal(out["render"][b, ..., :3], bgs[b][:, None, None, :].expand(2, H, W, 3))
        assert bool((out["render"][b, ..., 3] == 0).all())
        for k in ("means", "quats", "scales", "opacities", "colors"):
            assert bool((out["grads"][k][b] == 0).all()), f"empty scene {b}: nonzero gradient of {k}"
    for b in (0, 4):
        assert float(out["alphas"][b].amax()) > 0.5


def test_no_gaussians_at_all() -> None:
    scene, viewmats, Ks, bgs = batch_inputs((2,), 0, 2, None)
    render, alphas, meta = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                         scene["colors"], viewmats, Ks, W, H, backgrounds=bgs)
    assert render.shape == (2, 2, H, W, 3) and bool((alphas == 0).all())
    assert torch.equal(render, bgs[:, :, None, None, :].expand_as(render))


def test_empty_batch() -> None:
    """A batch of zero scenes renders zero images and back-propagates zero-size gradients."""
    scene, viewmats, Ks, bgs = batch_inputs((2,), 10, 2, 2)
    out = render_with_grads({k: v[:0] for k, v in scene.items()}, viewmats[:0], Ks[:0], bgs[:0], sh_degree=2)
    assert out[0].shape == (0, 2, H, W, 3) and out[2]["colors"].shape == (0, 10, 9, 3)


def test_mismatched_leading_dims_name_the_field() -> None:
    scene, viewmats, Ks, bgs = batch_inputs((2,), 10, 2, None)
    args = [scene[k] for k in PARAMS]
    with pytest.raises(ValueError, match="viewmats must be"):
        rasterization(*args, viewmats[:1], Ks[:1], W, H)
    with pytest.raises(ValueError, match="Ks must be"):
        rasterization(*args, viewmats, Ks[0], W, H)
    with pytest.raises(ValueError, match="opacities must be"):
        rasterization(*args[:3], args[3][0], args[4], viewmats, Ks, W, H)
    with pytest.raises(ValueError, match="backgrounds must be"):
        rasterization(*args, viewmats, Ks, W, H, backgrounds=bgs[0])
    with pytest.raises(ValueError, match="colors must be"):
        rasterization(*args[:4], args[4][0], viewmats, Ks, W, H)


# ----------------------------------------------------------------------------------------------------------
# Against the float64 reference, scene by scene


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_batch_matches_float64_reference(rasterize_mode: str) -> None:
    """Each scene of a batched call, image and gradients, against the float64 reference of that scene
    (relative gradient error <= 1e-3, as tests/scenesplat_stereo/raster/test_raster_backward.py; the scenes are checked free of
    knife-edge pixels so that the comparison is meaningful)."""
    Wr, Hr = 32, 24
    batch = (3,)
    seeds = (20, 21, 22)  # scenes and rigs without knife-edge pixels in either mode
    scenes = [random_scene(60, seed, sh_degree=2) for seed in seeds]
    rigs = [camera_rig(2, Wr, Hr, seed=seed) for seed in seeds]
    stacked = stack_scenes(scenes)
    viewmats, Ks = torch.stack([r[0] for r in rigs]), torch.stack([r[1] for r in rigs])
    bgs = torch.rand(3, 2, 3, generator=torch.Generator().manual_seed(2))
    leaves = {k: v.clone().requires_grad_() for k, v in stacked.items()} | {"backgrounds": bgs.clone().requires_grad_()}
    kw = dict(sh_degree=2, rasterize_mode=rasterize_mode, render_mode="RGB+ED")
    render, alphas, meta = rasterization(*(leaves[k] for k in PARAMS), viewmats, Ks, Wr, Hr,
                                         backgrounds=leaves["backgrounds"], **kw)
    g = torch.Generator().manual_seed(3)
    w_c = torch.randn(render.shape, generator=g, dtype=torch.float64)
    w_a = torch.randn(alphas.shape, generator=g, dtype=torch.float64)
    ((render.double() * w_c).sum() + (alphas.double() * w_a).sum()).backward()
    ref_kw = kw | {"max_alpha": float(np.float32(0.99))}
    for b in range(len(scenes)):
        ref_leaves = {k: v.double().requires_grad_() for k, v in scenes[b].items()}
        ref_leaves["backgrounds"] = bgs[b].double().requires_grad_()
        ref = reference_rasterization(*(ref_leaves[k] for k in PARAMS), viewmats[b], Ks[b], Wr, Hr,
                                      backgrounds=ref_leaves["backgrounds"], **ref_kw)
        ref_meta = {k: v.detach() for k, v in ref[2].items()}
        assert int(knife_edge_pixels(ref_meta).sum()) == 0, f"scene {b} has knife-edge pixels: pick other seeds"
        assert_matches_reference((render[b].detach(), alphas[b].detach(), {}),
                                 (ref[0].detach(), ref[1].detach(), ref_meta), render_mode="RGB+ED")
        ((ref[0] * w_c[b]).sum() + (ref[1] * w_a[b]).sum()).backward()
        for k, leaf in ref_leaves.items():
            ours = leaves[k].grad[b].double()
            err = float((ours - leaf.grad).norm()) / float(leaf.grad.norm())
            assert err <= 1e-3, f"scene {b}: gradient of {k} off the float64 reference by {err:.2e} (relative)"
    assert meta["batch_dims"] == batch


# ----------------------------------------------------------------------------------------------------------
# bench render --batch (the model workload), small and without gsplat


def test_bench_batch_workload_and_table(tmp_path) -> None:
    from scenesplat_stereo.bench.render_batch import workload
    from scenesplat_stereo.cli import main

    data = workload(2, 16, "cpu")
    assert data["means"].shape == (2, 2 * 48 * 48, 3) and data["colors"].shape == (2, 2 * 48 * 48, 9, 3)
    assert data["viewmats"].shape == (2, 4, 4, 4) and data["Ks"].shape == (2, 4, 3, 3)
    z = data["means"][..., 2]
    assert float(z.min()) >= 1.0 and float(z.max()) <= 5.0
    R, t = data["viewmats"][..., :3, :3], data["viewmats"][..., :3, 3:]
    centres = -(R.transpose(-1, -2) @ t)[..., 0]
    assert float(centres.norm(dim=-1).max()) <= 0.3 + 1e-6
    out = tmp_path / "batch.md"
    assert main(["bench", "render", "--batch", "--quick", "--device", "cpu", "--repeats", "1", "--no-gsplat",
                 "--out", str(out)]) == 0
    text = out.read_text()
    for row in ("| ours batched |", "| ours looped |", "| ours batched, deterministic |",
                "max |ours batched - ours looped| = 0."):
        assert row in text, row
