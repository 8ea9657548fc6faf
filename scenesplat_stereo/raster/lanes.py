"""Cross-thread votes and sums of cooperative compositing blocks (``wp.launch_tiled``): ``block_all`` for
any block, the ``lanes_*`` functions for blocks of exactly one warp (``LANES`` = 32 threads,
``block_dim=LANES``; ``lanes_ballot`` also in larger blocks on CUDA, see there), the compositing kernels'
per-warp reductions and votes; ``highest_bit`` and ``lowest_bit`` walk a vote's bit mask, ``bit_count`` counts it.

On CUDA they are bare warp intrinsics (a vote, register shuffles), with no shared memory and no block
barrier; Warp's tile reductions, by contrast, go through a shared-memory tile and ``__syncthreads`` per
call. On the CPU (Warp's cooperative fibers, ``_warp.launch`` with ``block_dim``) the same functions fall back to Warp's
tile reductions, which sum in lane order, so CPU results are reproducible. Every lane of the block must
call each function (all 32 lanes take part in the shuffles).

``lanes_sum_add`` is a reduce-scatter: instead of summing each of the F components over 32 lanes (5
shuffles each, 5 F in all, as a ``cg::reduce`` per component does), every halving step keeps half the
components and sends the other half to the partner lane, so 16 components take 8 + 4 + 2 + 1 + 1 = 16
shuffles and leave component k's total in lanes 2k and 2k + 1; lane 2k then adds it with one atomic, so
one warp adds a Gaussian's F floats with one atomic instruction issued by F lanes at once (consecutive
addresses) instead of F atomics in a row from lane 0.
"""

# No ``from __future__ import annotations``: Warp evaluates the annotations of the native stubs.
import functools

import warp as wp

from scenesplat_stereo.raster._warp import vector_type

LANES = 32

_ANY = """
#if defined(__CUDA_ARCH__)
return __any_sync(0xffffffffu, flag != 0) ? 1 : 0;
#else
auto t = wp::tile<wp::int32>(flag);
return wp::tile_max(t).data[0] != 0 ? 1 : 0;
#endif
"""

_ALL = """
#if defined(__CUDA_ARCH__)
return __syncthreads_and(flag != 0) ? 1 : 0;
#else
auto t = wp::tile<wp::int32>(flag != 0 ? 1 : 0);
return wp::tile_min(t).data[0];
#endif
"""

_MAX = """
#if defined(__CUDA_ARCH__)
int m = x;
for (int off = 16; off > 0; off >>= 1)
    m = max(m, __shfl_xor_sync(0xffffffffu, m, off));
return m;
#else
auto t = wp::tile<wp::int32>(x);
return wp::tile_max(t).data[0];
#endif
"""

_BALLOT = """
#if defined(__CUDA_ARCH__)
return (int)__ballot_sync(0xffffffffu, flag != 0);
#elif WP_TILE_BLOCK_DIM == 32
auto t = wp::tile<wp::uint32>(flag != 0 ? (1u << lane) : 0u);
return (int)wp::tile_sum(t).data[0];
#else
auto t = wp::tile<wp::int32>(flag != 0 ? 1 : 0);
return wp::tile_max(t).data[0] != 0 ? -1 : 0;
#endif
"""

_HIGHEST = """
if (r < 0)
    return -1;
const unsigned m = ((unsigned)mask) & (0xffffffffu >> (31 - (r > 31 ? 31 : r)));
#if defined(__CUDA_ARCH__)
return m != 0u ? 31 - __clz(m) : -1;
#else
for (int k = 31; k >= 0; --k)
    if ((m >> k) & 1u)
        return k;
return -1;
#endif
"""

_LOWEST = """
if (r > 31)
    return -1;
const unsigned m = ((unsigned)mask) & (0xffffffffu << (r < 0 ? 0 : r));
#if defined(__CUDA_ARCH__)
return m != 0u ? __ffs(m) - 1 : -1;
#else
for (int k = 0; k < 32; ++k)
    if ((m >> k) & 1u)
        return k;
return -1;
#endif
"""

# Per chunk of 16 components: 4 halving steps (partner lane = lane ^ off, off = 16, 8, 4, 2; the lane with
# bit ``off`` set keeps the upper half), then one plain step (off = 1). Component of lane l: (l >> 1) & 15.
_SUM_ADD = r"""
#if defined(__CUDA_ARCH__)
const unsigned full = 0xffffffffu;
#pragma unroll
for (int base = 0; base < {F}; base += 16) {{
    float v[16];
#pragma unroll
    for (int k = 0; k < 16; ++k)
        v[k] = base + k < {F} ? value.c[base + k] : 0.0f;
#define SG_HALVE(n) {{ const bool upper = (lane & (2 * n)) != 0; \
        _Pragma("unroll") for (int k = 0; k < n; ++k) {{ \
            const float keep = upper ? v[k + n] : v[k]; \
            const float send = upper ? v[k] : v[k + n]; \
            v[k] = keep + __shfl_xor_sync(full, send, 2 * n); }} }}
    SG_HALVE(8) SG_HALVE(4) SG_HALVE(2) SG_HALVE(1)
#undef SG_HALVE
    const float total = v[0] + __shfl_xor_sync(full, v[0], 1);
    const int k = base + ((lane >> 1) & 15);
    if ((lane & 1) == 0 && k < {F})
        atomicAdd(&(wp::address(out, index)->c[k]), total);
}}
#else
auto t = wp::tile<wp::vec_t<{F}, wp::float32>>(value);
auto total = wp::tile_sum(t).data[0];
if (lane == 0)
    wp::atomic_add(out, index, total);
#endif
"""


@wp.func_native(_ANY)
def lanes_any(flag: int) -> int:
    """1 when ``flag`` is non-zero in any lane of the warp, else 0 (in every lane)."""
    ...


@wp.func_native(_BALLOT)
def lanes_ballot(flag: int, lane: int) -> int:
    """The warp's vote as a 32-bit mask (an int32; bit k set when ``flag`` is non-zero in lane k), in every
    lane; ``lane`` is this thread's lane 0..31. In a block of several warps each warp votes on its own on
    CUDA; on the CPU such a block gets every bit set when any of its threads votes (a superset of each
    warp's vote: callers use it only to rule entries out)."""
    ...


@wp.func_native(_HIGHEST)
def highest_bit(mask: int, r: int) -> int:
    """The highest set bit of ``mask`` (as 32 bits) at position ``r`` or below, or -1 when there is none (or
    ``r`` < 0)."""
    ...


@wp.func_native(_LOWEST)
def lowest_bit(mask: int, r: int) -> int:
    """The lowest set bit of ``mask`` (as 32 bits) at position ``r`` or above, or -1 when there is none (or
    ``r`` > 31)."""
    ...


_POPC = """
#if defined(__CUDA_ARCH__)
return __popc((unsigned)mask);
#else
int count = 0;
for (int k = 0; k < 32; ++k)
    count += (((unsigned)mask) >> k) & 1u;
return count;
#endif
"""


@wp.func_native(_POPC)
def bit_count(mask: int) -> int:
    """The number of set bits of ``mask`` (as 32 bits)."""
    ...


@wp.func_native(_ALL)
def block_all(flag: int) -> int:
    """1 when ``flag`` is non-zero in every thread of the block, else 0 (in every thread); a block barrier
    (every thread of the block must call it)."""
    ...


@wp.func_native(_MAX)
def lanes_max(x: int) -> int:
    """The largest ``x`` over the warp's lanes (in every lane)."""
    ...


@functools.cache
def lanes_sum_add(length: int):
    """Native function ``(value: vec[length], out: array of vec[length], index, lane)``: adds the sum of
    ``value`` over the warp's lanes to ``out[index]`` (float atomics; ``index`` the same in every lane,
    ``lane`` this thread's lane 0..31)."""
    vec = vector_type(length)

    def stub(value: vec, out: wp.array(dtype=vec), index: int, lane: int):
        ...

    stub.__name__ = stub.__qualname__ = f"lanes_sum_add_{length}"
    return wp.func_native(_SUM_ADD.format(F=length))(stub)
