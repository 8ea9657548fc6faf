"""The rasteriser's Warp glue (scenesplat_stereo/raster/_warp.py): array descriptors and recorded launches.

``to_wp`` builds Warp's array descriptor by hand and ``launch`` replays a launch command recorded once per
kernel, device and thread, so these tests hold both to what plain Warp does: the same elements read (also
through strided views), clear errors for tensors that cannot be viewed as asked, every argument and the grid
of a replayed launch taken from the new call, no tensor kept alive by a recorded command, and threads that
launch the same kernel at once.
"""

from __future__ import annotations

import gc
import threading
import weakref

import pytest
import torch
import warp as wp

from scenesplat_stereo.raster._warp import launch, to_wp

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@wp.kernel(enable_backward=False)
def _affine(x: wp.array2d(dtype=wp.vec2), scale: float, shift: int, out: wp.array2d(dtype=wp.vec2)):
    i, j = wp.tid()
    out[i, j] = x[i, j] * scale + wp.vec2(float(shift), float(shift))


@wp.kernel(enable_backward=False)
def _matrix_trace(m: wp.array(dtype=wp.mat33), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = wp.trace(m[i])


def affine(x: torch.Tensor, scale: float, shift: int) -> torch.Tensor:
    out = torch.empty(x.shape, dtype=torch.float32, device=x.device)
    launch(_affine, tuple(x.shape[:2]), [to_wp(x, wp.vec2), scale, shift, to_wp(out, wp.vec2)], x)
    return out


@pytest.mark.parametrize("device", DEVICES)
def test_strided_views_are_read_in_place(device):
    """One field of a packed [A, B, 9] tensor (the compositing backward's gradients) read without a copy:
    the descriptor points at the view's first element with the view's strides, and the kernel reads the
    same values as from a contiguous copy."""
    packed = torch.randn(5, 7, 9, generator=torch.Generator().manual_seed(0)).to(device)
    for first in (0, 3, 7):
        view = packed[..., first:first + 2]
        assert not view.is_contiguous()
        desc = to_wp(view, wp.vec2)
        assert desc.data == view.data_ptr() and desc.ndim == 2
        assert list(desc.shape)[:2] == [5, 7] and list(desc.strides)[:2] == [7 * 9 * 4, 9 * 4]
        assert torch.equal(affine(view, 2.0, 1), view * 2.0 + 1.0)
    transposed = packed[..., :2].transpose(0, 1)  # leading axes in any order
    assert torch.equal(affine(transposed, -1.0, 0), -transposed)


@pytest.mark.parametrize("device", DEVICES)
def test_matrices_and_explicit_shapes(device):
    m = torch.randn(4, 3, 3, device=device)
    out = torch.empty(4, device=device)
    launch(_matrix_trace, 4, [to_wp(m, wp.mat33), to_wp(out)], m)
    torch.testing.assert_close(out, torch.diagonal(m, dim1=-2, dim2=-1).sum(-1))
    flat = torch.randn(2, 2, 9, device=device)  # four matrices given as [2, 2, 9], viewed through shape=(4,)
    launch(_matrix_trace, 4, [to_wp(flat, wp.mat33, (4,)), to_wp(out)], flat)
    torch.testing.assert_close(out, flat.reshape(4, 3, 3).diagonal(dim1=-2, dim2=-1).sum(-1))
    strided = torch.randn(4, 3, 6, device=device)[..., :3]  # inner rows not dense: copied, same values
    launch(_matrix_trace, 4, [to_wp(strided, wp.mat33), to_wp(out)], strided)
    torch.testing.assert_close(out, torch.diagonal(strided, dim1=-2, dim2=-1).sum(-1))


def test_bad_views_are_refused():
    with pytest.raises(TypeError, match="cannot hold"):
        to_wp(torch.zeros(4, 2, dtype=torch.int32), wp.vec2)  # int32 storage as float vectors
    with pytest.raises(TypeError, match="cannot hold"):
        to_wp(torch.zeros(4, dtype=torch.bool))
    with pytest.raises(ValueError, match="does not end in"):
        to_wp(torch.zeros(4, 3), wp.vec2)
    with pytest.raises(ValueError, match="does not end in"):
        to_wp(torch.zeros(3), wp.mat33)
    with pytest.raises(ValueError, match="is not"):
        to_wp(torch.zeros(4, 3), wp.vec3, (5,))


@pytest.mark.parametrize("device", DEVICES)
def test_replayed_launch_takes_every_argument_and_the_grid_of_the_call(device):
    """The same kernel launched with different sizes, scalars and arrays, in an order that grows and
    shrinks the grid: each result is that call's own (the recorded command keeps nothing of the last).
    Scales are powers of two, so x * scale + shift rounds once with or without a fused multiply-add and
    the results can be compared exactly."""
    g = torch.Generator().manual_seed(1)
    for rows, cols, scale, shift in ((3, 4, 2.0, 2), (1, 1, -4.0, 0), (6, 2, 0.25, -3), (3, 4, 2.0, 2)):
        x = torch.randn(rows, cols, 2, generator=g).to(device)
        assert torch.equal(affine(x, scale, shift), x * scale + shift)
    empty = torch.empty(0, 5, 2, device=device)
    assert affine(empty, 1.0, 1).shape == (0, 5, 2)  # an empty grid launches nothing


@pytest.mark.parametrize("device", DEVICES)
def test_recorded_launch_keeps_no_tensor_alive(device):
    x = torch.randn(64, 3, 2, device=device)
    out = affine(x, 1.0, 0)
    refs = [weakref.ref(x), weakref.ref(out)]
    del x, out
    gc.collect()
    assert all(r() is None for r in refs), "a recorded launch still holds a tensor of its last call"


@pytest.mark.parametrize("device", DEVICES)
def test_threads_launch_the_same_kernel_at_once(device):
    """Recorded launches are per thread: four threads launching the same kernel with their own data each
    get their own results (power-of-two scales: exact, see above)."""
    errors = []

    def work(seed: int) -> None:
        g = torch.Generator().manual_seed(seed)
        try:
            for _ in range(25):
                x = torch.randn(8, 16, 2, generator=g).to(device)
                if not torch.equal(affine(x, 2.0 ** seed, seed), x * 2.0 ** seed + seed):
                    errors.append(seed)
        except Exception as e:  # noqa: BLE001 - reported below with the thread's seed
            errors.append(f"{seed}: {e}")

    threads = [threading.Thread(target=work, args=(s,)) for s in range(1, 5)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
