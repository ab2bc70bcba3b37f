"""numba kernels of :mod:`bigT.compensation.codes` (imported on first use).

``gather`` reads a batch of integer frames (a video's 8- or 16-bit codes) straight into
the product's (n, K) float32 batch through a table of the codes' values; ``scatter``
writes the (n, K) products back into integer frames, clipped and quantised in the same
pass. Both work on blocks of matrix rows so the (block, K) slab stays in cache, as
:mod:`bigT.kernels.pixels` does for float frames.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Matrix rows handled per block (the :mod:`bigT.kernels.pixels` block).
BLOCK = 256


@njit(nogil=True, cache=True)
def gather(codes, perm, table, out):
    """``out[i, c] = table[codes[c, perm[i]]]`` for the rows of ``out`` (a slice of the
    batch; ``perm`` the same slice of the pixel order)."""
    n, k = out.shape
    for b0 in range(0, n, BLOCK):
        b1 = min(b0 + BLOCK, n)
        for c in range(k):
            src = codes[c]
            for i in range(b0, b1):
                out[i, c] = table[src[perm[i]]]


@njit(nogil=True, cache=True)
def scatter(Y, perm, lo, hi, do_lo, do_hi, top, out):
    """``out[c, perm[i]] = rint(min(max(clip(Y[i, c]), 0), 1) * top)``; returns the
    counts clipped below ``lo`` and above ``hi``.

    The arithmetic is :func:`bigT.kernels.pixels.scatter`'s clip (float64, stored
    float32) followed by :meth:`bigT.compensation.video.VideoSink.write`'s quantisation
    (float32), so the codes are the float path's, bit for bit."""
    n, k = Y.shape
    below = 0
    above = 0
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for b0 in range(0, n, BLOCK):
        b1 = min(b0 + BLOCK, n)
        for c in range(k):
            dst = out[c]
            for i in range(b0, b1):
                v = np.float64(Y[i, c])
                if do_lo and v < lo:
                    v = lo
                    below += 1
                elif do_hi and v > hi:
                    v = hi
                    above += 1
                f = np.float32(v)
                f = min(max(f, zero), one) * top
                dst[perm[i]] = np.rint(f)
    return below, above
