"""numba kernels of :mod:`bigT.compensation.codes` (imported on first use).

``gather`` reads a batch of integer frames (a video's 8- or 16-bit codes) straight into
the product's (n, K) float32 batch through a table of the codes' values; ``scatter``
writes the (n, K) products back into integer frames, clipped and quantised in the same
pass. Both go row by row of the batch: its (n, K) array is read or written in order,
and a pixel's K codes are together.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Matrix rows a thread's range is a multiple of.
BLOCK = 256


@njit(nogil=True, cache=True)
def gather(codes, perm, table, out):
    """``out[i, c] = table[codes[c, perm[i]]]`` for the rows of ``out`` (a slice of the
    batch; ``perm`` the same slice of the pixel order): row by row, so ``out`` is
    written in order and each pixel's K codes are read together (measured 2x faster
    than frame by frame over blocks of rows)."""
    n, k = out.shape
    for i in range(n):
        p = perm[i]
        for c in range(k):
            out[i, c] = table[codes[c, p]]


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
    for i in range(n):  # row by row, as gather (1.7x faster measured)
        p = perm[i]
        for c in range(k):
            v = np.float64(Y[i, c])
            if do_lo and v < lo:
                v = lo
                below += 1
            elif do_hi and v > hi:
                v = hi
                above += 1
            f = np.float32(v)
            f = min(max(f, zero), one) * top
            out[c, p] = np.rint(f)
    return below, above


@njit(nogil=True, cache=True)
def scatter_image(Y, perm, lo, hi, do_lo, do_hi, top, out):
    """:func:`scatter` quantised as :mod:`bigT.images` writes a PNG instead of as the
    video sink does: the clipped value (float64, stored float32, as the float frames
    hold it), then in float64 NaN and values <= 0 to 0, values above 1 to ``top``, the
    others ``rint(value * top)`` (:func:`bigT.images.quantise`), so the codes are
    those of the float frames written by :func:`bigT.images.write_image`, bit for bit."""
    n, k = Y.shape
    below = 0
    above = 0
    for i in range(n):
        p = perm[i]
        for c in range(k):
            v = np.float64(Y[i, c])
            if do_lo and v < lo:
                v = lo
                below += 1
            elif do_hi and v > hi:
                v = hi
                above += 1
            g = np.float64(np.float32(v))
            if not g > 0.0:  # NaN too, as np.fmax(NaN, 0)
                g = 0.0
            elif g > 1.0:
                g = 1.0
            out[c, p] = np.rint(g * top)
    return below, above
