"""A video's integer codes in and out of the products, without float frames between.

A full-HD grey frame is 2 MB of 8-bit codes but 8 MB as float32. The float path
(:class:`~bigT.compensation.video.VideoSource` frames, the pixel gather, the product,
the pixel scatter, :meth:`~bigT.compensation.video.VideoSink.write`) passes over the
frame some eight times between the decoder and the encoder: convert and scale, stack a
batch, gather, scatter, clip, scale, round, cast, copy to bytes. With linear light in and
out and X in memory, two passes do it all:

* :func:`gather_codes`: the (K, H, W) codes straight into the (n, K) float32 batch in
  the store's pixel order, each code looked up in a table of its value (``code / top``,
  computed as the float path computes it);
* :func:`scatter_codes`: the (n, K) products back into (K, H, W) codes, clipped to the
  compensation's range and quantised as the video sink quantises (so the codes written
  are the float path's, bit for bit; a test compares them).

A folder of 8- or 16-bit PNG frames takes the same two passes (``images=True``), with
the image files' own arithmetic: a code's value divided in float32 as
:meth:`bigT.images.ImageSource.read` divides it, the result quantised in float64 as
:func:`bigT.images.write_image` quantises it.
"""

from __future__ import annotations

import numpy as np

from ..kernels.threads import run_on_threads

#: Largest code of each integer dtype a video frame is read or written in.
CODE_TOPS = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}


def code_values(dtype, images: bool = False) -> np.ndarray:
    """(top + 1,) float32: the light of each code of ``dtype`` (uint8 or uint16), as
    :meth:`~bigT.compensation.video.VideoSource.frames` computes it (code * (1 / top) in
    float32), or with ``images`` as :meth:`bigT.images.ImageSource.read` does (code / top
    in float32: the two differ by an ulp for some codes)."""
    top = CODE_TOPS[np.dtype(dtype)]
    codes = np.arange(top + 1, dtype=np.float32)
    return codes / np.float32(top) if images else codes * np.float32(1.0 / top)


def _row_ranges(n: int, threads: int, block: int) -> list[tuple[int, int]]:
    """``threads`` contiguous ranges of [0, n) in whole blocks."""
    blocks = -(-n // block)
    cuts = [min(n, block * (blocks * t // threads)) for t in range(threads + 1)]
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]


def gather_codes(codes: np.ndarray, perm: np.ndarray, n_threads: int = 1,
                 out: np.ndarray | None = None, images: bool = False) -> np.ndarray:
    """(K, *frame_shape) integer codes -> the (n, K) float32 batch in matrix order.

    Parameters
    ----------
    codes : ndarray, shape (K, *frame_shape), uint8 or uint16, C-contiguous
    perm : ndarray, shape (n,), the store's pixel order (row i holds value perm[i] of
        a flattened frame)
    n_threads : int, threads over row ranges of the batch
    out : ndarray, shape (n, K), float32, C-contiguous, optional: filled and returned
    images : bool, the codes of image files (their reader's values, :func:`code_values`)
    """
    from . import _code_kernels as kernels  # numba: ~0.5 s, only for a video's codes

    K = codes.shape[0]
    src = np.ascontiguousarray(codes.reshape(K, -1))
    table = code_values(src.dtype, images)
    if out is None:
        out = np.empty((perm.size, K), np.float32)
    threads = max(1, int(n_threads))
    run_on_threads(lambda a, b: kernels.gather(src, perm[a:b], table, out[a:b]),
                   _row_ranges(perm.size, threads, kernels.BLOCK), threads)
    return out


def scatter_codes(Y: np.ndarray, perm: np.ndarray, clip, frame_shape, dtype,
                  n_threads: int = 1, images: bool = False) -> tuple[np.ndarray, int, int]:
    """The (n, K) products -> (K, *frame_shape) codes of ``dtype``, clipped to ``clip``
    then quantised (values outside [0, 1] to the end codes).

    Parameters
    ----------
    Y : ndarray, shape (n, K), float32, C-contiguous
    perm : ndarray, shape (n,)
    clip : (lo, hi) or None; either bound may be None
    frame_shape : (H, W) or (H, W, 3)
    dtype : uint8 or uint16
    n_threads : int
    images : bool, quantised as the image files' writer does (float64) instead of as
        the video sink does (float32): each the codes of its own float path

    Returns
    -------
    codes : ndarray, shape (K, *frame_shape), ``dtype``
    below, above : int, the values clipped at lo and at hi
    """
    from . import _code_kernels as kernels  # numba: ~0.5 s, only for a video's codes

    K = Y.shape[1]
    lo, hi = (None, None) if clip is None else clip
    top = CODE_TOPS[np.dtype(dtype)]
    bounds = (0.0 if lo is None else float(lo), 0.0 if hi is None else float(hi),
              lo is not None, hi is not None, float(top) if images else np.float32(top))
    kernel = kernels.scatter_image if images else kernels.scatter
    out = np.empty((K, perm.size), dtype)
    threads = max(1, int(n_threads))
    counts = run_on_threads(lambda a, b: kernel(Y[a:b], perm[a:b], *bounds, out),
                            _row_ranges(perm.size, threads, kernels.BLOCK), threads)
    return (out.reshape(K, *frame_shape), sum(int(c[0]) for c in counts),
            sum(int(c[1]) for c in counts))
