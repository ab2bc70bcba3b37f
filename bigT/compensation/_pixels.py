"""Frames <-> matrix-ordered batches in one pass (numba), clipping fused in.

``PixelOrder.to_matrix`` / ``to_images`` do the same with three numpy passes each
(gather, transpose, cast); at 384x512 and 64 frames those cost as much as a pass over X,
so the hot path uses these kernels and keeps ``PixelOrder`` as the reference (tests
compare the two). Batches of at most ``config.KERNEL_NUMPY_MAX_WORK`` values take the
numpy path, so compensating a small image never compiles a kernel.
"""

from __future__ import annotations

import numpy as np

from .. import config


def _kernels():
    """The compiled gather and scatter (numba imported here, on first use)."""
    global _KERNELS
    if _KERNELS is None:
        from numba import njit

        _KERNELS = (njit(nogil=True, cache=True)(_gather_py),
                    njit(nogil=True, cache=True)(_scatter_py))
    return _KERNELS


_KERNELS = None

#: Matrix rows handled per block: the (block, K) slab of the batch stays in L2.
_BLOCK = 256


def _gather_py(frames, perm, out):
    n, k = out.shape
    for b0 in range(0, n, _BLOCK):
        b1 = min(b0 + _BLOCK, n)
        for c in range(k):
            src = frames[c]
            for i in range(b0, b1):
                out[i, c] = src[perm[i]]


def _scatter_py(Y, perm, lo, hi, do_lo, do_hi, out):
    n, k = Y.shape
    below = 0
    above = 0
    for b0 in range(0, n, _BLOCK):
        b1 = min(b0 + _BLOCK, n)
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
                dst[perm[i]] = v
    return below, above


def _row_ranges(n: int, threads: int) -> list[tuple[int, int]]:
    """``threads`` contiguous ranges of [0, n) in whole blocks."""
    blocks = -(-n // _BLOCK)
    cuts = [min(n, _BLOCK * (blocks * t // threads)) for t in range(threads + 1)]
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]


def _parallel(kernel, ranges, make_args):
    """Run ``kernel(*make_args(a, b))`` over the row ranges, on threads when several
    (the kernels release the GIL); the results in order."""
    if len(ranges) == 1:
        return [kernel(*make_args(*ranges[0]))]
    from .resident import thread_pool

    futures = [thread_pool(len(ranges)).submit(kernel, *make_args(a, b)) for a, b in ranges]
    return [f.result() for f in futures]


def frames_to_matrix(frames: np.ndarray, order, dtype, n_threads: int = 1) -> np.ndarray:
    """(K, H, W) frames -> (n, K) C-contiguous batch in the store's pixel order
    (``n_threads`` threads over row ranges of the batch)."""
    K = frames.shape[0]
    src = np.ascontiguousarray(frames.reshape(K, -1))
    out = np.empty((order.n, K), dtype=dtype)
    if out.size <= config.KERNEL_NUMPY_MAX_WORK:
        out[...] = order.to_matrix(frames).reshape(order.n, K)  # the numpy reference
    else:
        perm = order.permutation
        _parallel(_kernels()[0], _row_ranges(order.n, max(1, n_threads)),
                  lambda a, b: (src, perm[a:b], out[a:b]))
    return out


def matrix_to_frames(Y: np.ndarray, order, clip=None, *, dtype=np.float64,
                     n_threads: int = 1) -> tuple[np.ndarray, int, int]:
    """(n, K) batch -> (K, H, W) frames of ``dtype``, clipped to ``clip`` = (lo, hi)
    (either may be None); returns the frames and the counts of values below lo and
    above hi. ``n_threads`` threads over row ranges of the batch (their pixels are
    disjoint)."""
    Y = np.ascontiguousarray(Y.reshape(order.n, -1))
    K = Y.shape[1]
    lo, hi = (None, None) if clip is None else clip
    out = np.empty((K, order.n), dtype=dtype)
    if out.size <= config.KERNEL_NUMPY_MAX_WORK:
        V = Y.astype(np.float64)
        below = 0 if lo is None else int(np.count_nonzero(V < lo))
        above = 0 if hi is None else int(np.count_nonzero(V > hi))
        if lo is not None or hi is not None:
            V = np.clip(V, lo, hi)
        out[...] = order.to_images(V).reshape(K, order.n)  # the numpy reference
    else:
        perm = order.permutation
        bounds = (0.0 if lo is None else float(lo), 0.0 if hi is None else float(hi),
                  lo is not None, hi is not None)
        counts = _parallel(_kernels()[1], _row_ranges(order.n, max(1, n_threads)),
                           lambda a, b: (Y[a:b], perm[a:b], *bounds, out))
        below, above = (sum(c[0] for c in counts), sum(c[1] for c in counts))
    return out.reshape(K, *order.image_shape), int(below), int(above)
