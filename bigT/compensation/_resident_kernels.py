"""numba kernels of :mod:`bigT.compensation.resident` (imported on first use).

Each kernel computes rows [r0, r1) of Y = X V for the segment layout: ``row_seg`` (n + 1)
where each row's segments start, ``seg_panel`` and ``seg_start`` each segment's panel
of 65536 columns and first entry, ``indices`` uint16 inside the panel, ``values`` float32 or
binary16 bits (uint16). ``nogil`` so a thread pool runs row ranges in parallel.
"""

from __future__ import annotations

import numpy as np
from numba import njit, types
from numba.extending import overload

#: Fused multiply-adds only. Reassociation would let LLVM vectorise the k = 1 row sums
#: with gather instructions, which measured 2x slower than scalar loads (AMD EPYC).
_FAST = {"contract"}


def _decode(v, lut):
    """A stored value as float32 (typed below: float32 as is; uint16 binary16 bits
    through ``lut``, the 65536 float32 values of binary16: one load from a table that
    stays in L2, measured 2x faster than decoding the bits with shifts)."""


@overload(_decode, inline="always")
def _decode_typed(v, lut):
    if isinstance(v, types.Float):
        return lambda v, lut: v
    if v == types.uint16:
        return lambda v, lut: lut[v]
    return None


@njit(nogil=True, cache=True, fastmath=_FAST)
def spmv(row_seg, seg_panel, seg_start, indices, values, lut, row_scale, V, Y, r0, r1):
    """Y[r0:r1, 0] = X[r0:r1] V[:, 0] (times row_scale when it is not empty).

    Four partial sums per row: one running sum waits on its previous add (~4 cycles
    each, ~120 entries a row), which bound the loop before memory did. ``V`` is
    C-contiguous (n, 1): read through a 1-D view of C layout, not ``V[:, 0]``, whose
    "any" layout scales every gathered index by a stride held at run time (the
    reshape measured 4 % quicker on one core, the same sums)."""
    scaled = row_scale.size > 0
    x = V.reshape(V.shape[0])
    for i in range(r0, r1):
        a0 = a1 = a2 = a3 = np.float32(0.0)
        for s in range(row_seg[i], row_seg[i + 1]):
            xs = x[np.int64(seg_panel[s]) << 16:]
            k = np.int64(seg_start[s])
            end = np.int64(seg_start[s + 1])
            while k + 4 <= end:
                a0 += _decode(values[k], lut) * xs[indices[k]]
                a1 += _decode(values[k + 1], lut) * xs[indices[k + 1]]
                a2 += _decode(values[k + 2], lut) * xs[indices[k + 2]]
                a3 += _decode(values[k + 3], lut) * xs[indices[k + 3]]
                k += 4
            while k < end:
                a0 += _decode(values[k], lut) * xs[indices[k]]
                k += 1
        acc = (a0 + a1) + (a2 + a3)
        Y[i, 0] = acc * row_scale[i] if scaled else acc


@njit(nogil=True, cache=True, fastmath=_FAST)
def spmm(row_seg, seg_panel, seg_start, indices, values, lut, row_scale, V, Y, r0, r1):
    """Y[r0:r1] = X[r0:r1] V for V (n_cols, K), K contiguous: each entry of X is
    loaded once and multiplies a whole row of V (a vector loop over K).

    The row is summed in a buffer of this call, not in Y: LLVM cannot tell Y's row
    from V's and then vectorises the lanes with overlap checks (2x slower measured)."""
    K = Y.shape[1]
    scaled = row_scale.size > 0
    acc = np.zeros(K, np.float32)
    for i in range(r0, r1):
        acc[:] = 0.0
        for s in range(row_seg[i], row_seg[i + 1]):
            Vp = V[np.int64(seg_panel[s]) << 16:]
            for k in range(seg_start[s], seg_start[s + 1]):
                a = _decode(values[k], lut)
                v = Vp[indices[k]]
                for c in range(K):
                    acc[c] += a * v[c]
        row_factor = row_scale[i] if scaled else np.float32(1.0)
        for c in range(K):
            Y[i, c] = acc[c] * row_factor


#: The batch width of :func:`spmm8`.
UNROLLED_WIDTH = 8


@njit(nogil=True, cache=True, fastmath=_FAST)
def spmm8(row_seg, seg_panel, seg_start, indices, values, lut, row_scale, V, Y, r0, r1):
    """:func:`spmm` for a batch of exactly 8 frames: the width known when compiled, the
    lanes are unrolled and kept in registers (1.4x faster than spmm's loop at full HD,
    measured on one core)."""
    scaled = row_scale.size > 0
    acc = np.zeros(8, np.float32)
    for i in range(r0, r1):
        acc[:] = 0.0
        for s in range(row_seg[i], row_seg[i + 1]):
            Vp = V[np.int64(seg_panel[s]) << 16:]
            for k in range(seg_start[s], seg_start[s + 1]):
                a = _decode(values[k], lut)
                v = Vp[indices[k]]
                for c in range(8):
                    acc[c] += a * v[c]
        row_factor = row_scale[i] if scaled else np.float32(1.0)
        for c in range(8):
            Y[i, c] = acc[c] * row_factor


def kernel_for(width: int):
    """The kernel for a batch of ``width`` columns: a single one, 8 (unrolled), any
    other (any precision: numba specialises on the values' dtype)."""
    return spmv if width == 1 else spmm8 if width == UNROLLED_WIDTH else spmm


@njit(nogil=True, cache=True)
def count_clipped(Y, lo, hi, do_lo, do_hi, channels, r0, r1):
    """(below, above) per channel of rows [r0, r1) of the (n, K) batch Y, row i holding
    channel i % channels; counted as the pixel scatter clips (below lo, else above hi)."""
    low = np.zeros(channels, np.int64)
    high = np.zeros(channels, np.int64)
    for i in range(r0, r1):
        c = i % channels
        for k in range(Y.shape[1]):
            v = np.float64(Y[i, k])
            if do_lo and v < lo:
                low[c] += 1
            elif do_hi and v > hi:
                high[c] += 1
    return low, high
