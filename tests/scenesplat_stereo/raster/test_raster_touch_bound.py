"""The compositing kernels skip list entries whose touch box (``projection.touch_extent``, which the projection
writes per pair) misses a warp's pixels (``composite.may_touch_box``); that is exact only if the bound never
rules out a splat that touches one of them. Checked here against a float64 evaluation of the touch test (SPEC
section 2, step 6: sigma >= 0 and o exp(-sigma) >= 1/255) and against the same test in float32, on every pixel
centre of the box, for splats built to sit on the bound's edge: ellipses whose bounding box ends within a few
hundredths of a pixel of the box, opacities at the 1/255 threshold, elongated and near-singular conics, NaNs.
The bound must also rule out most far splats (else skipping buys nothing and the test below it could not
fail)."""

from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp

from scenesplat_stereo.raster._warp import ALPHA_MIN, to_wp
from scenesplat_stereo.raster.composite import lanes_box, may_touch_box
from scenesplat_stereo.raster.projection import touch_extent


@wp.kernel
def _bound_kernel(xy: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3), opacity: wp.array(dtype=float),
                  box: wp.array(dtype=wp.vec4), out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    b = box[i]
    out[i] = may_touch_box(xy[i], touch_extent(conic[i], opacity[i]), b[0], b[1], b[2], b[3])


@wp.kernel
def _box_kernel(tiles: wp.array(dtype=wp.int32), firsts: wp.array(dtype=wp.int32), tile_size: int, tiles_x: int,
                tiles_per_camera: int, out: wp.array(dtype=wp.vec4)):
    i = wp.tid()
    x0, x1, y0, y1 = lanes_box(tiles[i], firsts[i], 32, tile_size, tiles_x, tiles_per_camera)
    out[i] = wp.vec4(x0, x1, y0, y1)


def _bound(xy: torch.Tensor, conic: torch.Tensor, opacity: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    out = torch.zeros(len(xy), dtype=torch.int32)
    wp.launch(_bound_kernel, len(xy), [to_wp(xy.float(), wp.vec2), to_wp(conic.float(), wp.vec3),
                                       to_wp(opacity.float()), to_wp(box.float(), wp.vec4), to_wp(out)],
              device="cpu")
    return out.bool()


def _touched(xy, conic, opacity, box, dtype) -> torch.Tensor:
    """Whether each splat touches any pixel centre of its box, evaluated in ``dtype`` (the kernels' float32
    expression of ``composite.conic_sigma``, or float64)."""
    xy, conic, opacity = xy.to(dtype), conic.to(dtype), opacity.to(dtype)
    hits = torch.zeros(len(xy), dtype=torch.bool)
    for i in range(len(xy)):
        x0, x1, y0, y1 = box[i].tolist()
        px = torch.arange(x0, x1 + 0.5, 1.0, dtype=dtype)
        py = torch.arange(y0, y1 + 0.5, 1.0, dtype=dtype)
        dx = (xy[i, 0] - px)[None, :]
        dy = (xy[i, 1] - py)[:, None]
        a, b, c = conic[i]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = opacity[i] * torch.exp(-sigma)
        hits[i] = bool(((sigma >= 0) & (alpha >= ALPHA_MIN)).any())
    return hits


def _edge_splats(n: int, seed: int):
    """Splats whose touch ellipse reaches to within 3% + 0.05 px of a pixel centre on the edge of a 16 x 2 box
    (two rows of a 16-pixel tile, as one warp holds) at its extreme point on a random side; covariances
    with condition numbers up to 1e6 (most with the renderer's 0.3 px^2 blur, as projected splats have)."""
    g = torch.Generator().manual_seed(seed)
    box = torch.tensor([0.5, 15.5, 4.5, 5.5], dtype=torch.float64).repeat(n, 1)
    angle = torch.rand(n, generator=g, dtype=torch.float64) * math.pi
    major = torch.exp(torch.empty(n, dtype=torch.float64).uniform_(math.log(0.3), math.log(40.0), generator=g))
    ratio = torch.exp(torch.empty(n, dtype=torch.float64).uniform_(0.0, math.log(1e3), generator=g))
    cos, sin = torch.cos(angle), torch.sin(angle)
    blur = torch.where(torch.rand(n, generator=g) < 0.8, 0.3, 0.0)  # the renderer's eps2d, on most
    l1, l2 = major ** 2 + blur, (major / ratio) ** 2 + blur  # covariance eigenvalues, px^2
    cov = torch.stack([l1 * cos ** 2 + l2 * sin ** 2, (l1 - l2) * cos * sin, l1 * sin ** 2 + l2 * cos ** 2], -1)
    det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
    conic = torch.stack([cov[:, 2] / det, -cov[:, 1] / det, cov[:, 0] / det], -1)
    opacity = torch.where(torch.rand(n, generator=g) < 0.2,
                          ALPHA_MIN * (1 + torch.empty(n, dtype=torch.float64).uniform_(-1e-3, 1e-2, generator=g)),
                          torch.rand(n, generator=g, dtype=torch.float64) * 0.99 + 0.01)
    t = 2 * torch.log(torch.clamp(opacity / ALPHA_MIN, min=1.0))
    rx, ry = torch.sqrt(t * cov[:, 0]), torch.sqrt(t * cov[:, 2])
    side = torch.randint(0, 4, (n,), generator=g)
    reach = torch.where((side == 0) | (side == 1), rx, ry)
    jitter = torch.empty(n, dtype=torch.float64).uniform_(-1, 1, generator=g) * (0.03 * reach + 0.05)
    # the ellipse's extreme point on that side put on a pixel centre of the box's edge row or column
    row = box[:, 2] + torch.randint(0, 2, (n,), generator=g)
    col = box[:, 0] + torch.randint(0, 16, (n,), generator=g)
    lean_x, lean_y = cov[:, 1] / cov[:, 0] * rx, cov[:, 1] / cov[:, 2] * ry
    x = torch.where(side == 0, box[:, 0] - rx + jitter, torch.where(side == 1, box[:, 1] + rx + jitter,
                                                                    torch.where(side == 2, col - lean_y, col + lean_y)))
    y = torch.where(side == 2, box[:, 2] - ry + jitter, torch.where(side == 3, box[:, 3] + ry + jitter,
                                                                    torch.where(side == 0, row - lean_x, row + lean_x)))
    return torch.stack([x, y], -1), conic, opacity, box


def test_the_bound_never_rules_out_a_touching_splat() -> None:
    xy, conic, opacity, box = _edge_splats(4000, seed=0)
    near = _bound(xy, conic, opacity, box)
    for dtype in (torch.float64, torch.float32):
        touched = _touched(xy, conic, opacity, box, dtype)
        assert touched.sum() > 1000  # many edge splats really touch the box ...
        assert not (touched & ~near).any(), f"ruled out a splat that touches the box ({dtype})"
    assert (~near).sum() > 1000  # ... and many are ruled out


def test_the_bound_rules_out_far_splats_and_keeps_doubtful_ones() -> None:
    n = 6
    box = torch.tensor([0.5, 15.5, 4.5, 5.5]).repeat(n, 1)
    xy = torch.tensor([[8.0, 20.0], [40.0, 5.0], [8.0, 5.0], [8.0, 20.0], [8.0, 20.0], [float("nan"), 5.0]])
    round_conic = [1.0, 0.0, 1.0]  # unit covariance: touches within sqrt(2 ln 255) = 3.3 px of its mean
    conic = torch.tensor([round_conic, round_conic, round_conic,
                          [1.0, 0.999999, 1.0],  # near-singular: never ruled out
                          [1.0, 0.0, -1.0],  # indefinite: never ruled out
                          round_conic])
    opacity = torch.tensor([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    assert _bound(xy, conic, opacity, box).tolist() == [False, False, True, True, True, True]
    # below 1/255 nothing is touched, anywhere
    assert not _bound(xy[2:3], conic[2:3], torch.tensor([ALPHA_MIN * 0.99]), box[:1]).any()


def test_lanes_box_covers_exactly_the_warps_pixels() -> None:
    """The box of 32 consecutive pixels of a tile (one warp of the backward) for tile sizes 8, 16 and 64 and
    an edge tile of a second camera: every pixel centre the warp takes lies in it, and for whole rows the
    box is those rows."""
    for tile_size, tiles_x, tiles_y in ((8, 3, 2), (16, 3, 2), (64, 2, 1)):
        per_camera = tiles_x * tiles_y
        area = tile_size * tile_size
        cases = [(tile, first) for tile in (0, per_camera + per_camera - 1) for first in range(0, area, 32)]
        tiles = torch.tensor([c[0] for c in cases], dtype=torch.int32)
        firsts = torch.tensor([c[1] for c in cases], dtype=torch.int32)
        out = torch.zeros(len(cases), 4)
        wp.launch(_box_kernel, len(cases), [to_wp(tiles), to_wp(firsts), tile_size, tiles_x, per_camera,
                                             to_wp(out, wp.vec4)], device="cpu")
        for (tile, first), (x0, x1, y0, y1) in zip(cases, out.tolist()):
            t = tile % per_camera
            ox, oy = (t % tiles_x) * tile_size, (t // tiles_x) * tile_size
            local = np.arange(first, min(first + 32, area))
            px, py = ox + local % tile_size + 0.5, oy + local // tile_size + 0.5
            assert (x0, x1, y0, y1) == (px.min(), px.max(), py.min(), py.max())


def test_the_projection_writes_each_pairs_touch_box() -> None:
    """``Projection.touch_extents``, the boxes the compositing kernels vote on, are ``touch_extent`` of the pair's
    own conic and opacity (here its formula in float64) and (-inf, -inf), a box holding no pixel, for culled
    pairs (behind the camera, below 1/255 opacity)."""
    from scenesplat_stereo.raster.projection import NEAR_CONDITION, project_gaussians

    g = torch.Generator().manual_seed(5)
    n = 3000
    means = torch.cat([torch.rand(n, 2, generator=g) * 4 - 2, torch.rand(n, 1, generator=g) * 6 - 1], 1)  # z < 0 too
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 1.5 - 4)
    opacities = torch.rand(n, generator=g)
    opacities[:200] = ALPHA_MIN * 0.5
    Ks = torch.tensor([[[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]]])
    proj = project_gaussians(means, quats, scales, opacities, torch.eye(4)[None], Ks, 320, 240, 0.01, 1e10, 0.3,
                             True, 16)
    ext, visible = proj.touch_extents[0].double(), proj.tiles_touched[0] > 0
    assert 1000 < int(visible.sum()) < n - 500  # many of each
    assert torch.isneginf(ext[~visible]).all()
    a, b, c = proj.conics[0, visible].double().unbind(-1)
    o = proj.opacities[0, visible].double()
    det = a * c - b * b
    t = 2 * (torch.log(o / ALPHA_MIN).clamp(min=0) + 1e-3)
    expected = torch.stack([torch.sqrt(t * c / det), torch.sqrt(t * a / det)], -1) * 1.01 + 0.01
    condition = (a + c) ** 2 / det
    expected[condition > NEAR_CONDITION] = math.inf
    assert torch.equal(torch.isinf(ext[visible]), torch.isinf(expected))
    finite = torch.isfinite(expected)
    # float32's det = a c - b^2 loses digits with the conic's condition (4e-5 relative at 6,000 here)
    tolerance = (1e-5 + 2e-7 * condition[:, None]) * expected + 1e-6
    assert ((ext[visible] - expected).abs() <= tolerance)[finite].all()
