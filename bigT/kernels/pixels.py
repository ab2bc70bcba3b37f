"""Frames <-> matrix-ordered batches in one pass: numba gather and scatter kernels.

A pixel order is a permutation ``perm`` (matrix row i holds image pixel ``perm[i]``).
``gather`` reads (K, n) frames into an (n, K) batch, ``scatter`` writes an (n, K) batch
back into (K, n) frames with clipping fused in (and counts what it clipped). Doing it
in numpy takes three passes each (gather, transpose, cast): at 384x512 and 64 frames
those cost as much as a pass over X. The numpy reference is
:class:`bigT.storage.PixelOrder` (``to_matrix``/``to_images``); :mod:`bigT.storage.frames`
picks between the two by size and tests compare them.
"""

from __future__ import annotations

import numpy as np

from .threads import run_on_threads


def _kernels():
    """The compiled gather and scatter (numba imported here, on first use)."""
    global _KERNELS
    if _KERNELS is None:
        from numba import njit  # numba: ~0.5 s, only for batches past the numpy path

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


def gather(src: np.ndarray, perm: np.ndarray, out: np.ndarray, n_threads: int = 1) -> None:
    """``out[i, c] = src[c, perm[i]]``: (K, n) frames into the (n, K) batch ``out``
    (``n_threads`` threads over row ranges)."""
    run_on_threads(lambda a, b: _kernels()[0](src, perm[a:b], out[a:b]),
                   _row_ranges(out.shape[0], max(1, n_threads)), max(1, n_threads))


def scatter(Y: np.ndarray, perm: np.ndarray, clip: tuple, out: np.ndarray,
            n_threads: int = 1) -> tuple[int, int]:
    """``out[c, perm[i]] = clip(Y[i, c])``: the (n, K) batch ``Y`` into (K, n) frames.

    Parameters
    ----------
    Y : ndarray, shape (n, K), C-contiguous
    perm : ndarray, shape (n,)
    clip : (lo, hi), either None for no bound
    out : ndarray, shape (K, n)

    Returns
    -------
    (below, above) : the counts of values clipped at lo and at hi.
    """
    lo, hi = clip
    bounds = (0.0 if lo is None else float(lo), 0.0 if hi is None else float(hi),
              lo is not None, hi is not None)
    counts = run_on_threads(lambda a, b: _kernels()[1](Y[a:b], perm[a:b], *bounds, out),
                            _row_ranges(Y.shape[0], max(1, n_threads)), max(1, n_threads))
    return sum(c[0] for c in counts), sum(c[1] for c in counts)
