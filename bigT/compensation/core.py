"""Compensation (paper eqs. 44-45), relighting and bounce separation (Seitz et al. 2005).

All three only stream the stored matrices against dense batches of frames; nothing is
ever inverted or multiplied matrix-by-matrix here.

Images are (H, W) or (K, H, W) float arrays, (H, W, 3) or (K, H, W, 3) for a colour store
(``channels == 3``, index 3 p + c); the store's :class:`PixelOrder` maps them to the
matrix's numbering and back, so a tile-major store takes and returns ordinary row-major
images. The arrays are linear light: the products are linear in light, not in an
encoding's values (:func:`bigT.colour.decode` turns sRGB-encoded values into light;
:mod:`bigT.compensation.files` does that for files, ``--encoding``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .. import config
from ..errors import UNSET, BigTError, InvalidMatrixError, Option, ShapeMismatchError
from ..kernels import BlockDiagonal
from ..schedule.stream import (
    cache_budget,
    compute_dtype,
    forget_tiles,
    scheduler_runner,
    stream_matmul,
)
from ..schedule.runner import worker_path
from ..storage import as_store, store_identity
from ..storage.frames import (as_frames, matrix_to_frames, pixel_order_of,
                              to_frames, to_vectors)

PATHS = ("explicit", "matrix-free", "auto")
#: The transport of the matrix-free path, as errors name it (the command line takes it
#: with --matrix-free).
_MATRIX_FREE_T = Option("T", UNSET, cli="--matrix-free T.zarr")


# --- matrix-free stratified inverse ---------------------------------------------------

_FINV: dict[tuple, np.ndarray] = {}


def first_bounce_diag(T) -> np.ndarray:
    """F^-1 for F = diag(T) (the Jacobi preconditioner of paper §4.4), shape (n,), in T's
    stored order (it scales stored vectors, as the matrix-free path does); for a colour
    T (3 channels), F = T's 3x3 diagonal blocks and this is their inverses, shape
    (n/3, 3, 3), pixel by pixel in T's stored order (apply them with
    :class:`bigT.kernels.BlockDiagonal`): the
    algorithms layer's :func:`~bigT.algorithms.resolve_first_bounce`, with its policy
    for zero diagonals (a pixel whose row and column are empty is left out: 0 here;
    any other zero or negative entry is an InvalidMatrixError). Kept per store
    version: with zero diagonals it is a pass over T, not to be paid per batch."""
    from ..algorithms.first_bounce import resolve_first_bounce  # the algorithms package
    # imports the engine and dask (~0.5 s): only the matrix-free path needs F here

    key = (str(worker_path(T.path)), *store_identity(T.path))
    if key not in _FINV:
        _FINV.clear()  # one store at a time: a vector of n per store is enough
        _FINV[key] = resolve_first_bounce(T, "diag").finv
    return _FINV[key]


def matrix_free_apply(T, B: np.ndarray, terms: int, *, F: np.ndarray | None = None,
                      progress: bool = False, cache_bytes: int | None = None,
                      runner=None) -> np.ndarray:
    """T_n^-1 B without forming T_n^-1: ``terms`` streaming products with T.

    Paper eq. 13: T_n^-1 = F^-1 S_n with S_n = sum_{k=0..n} M^k, M = I - T F^-1. Horner on
    the vectors: s_0 = b, s_j = b + M s_{j-1} = b + s_{j-1} - T (F^-1 s_{j-1}); after n steps
    s_n = S_n b, and T_n^-1 b = F^-1 s_n.

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
    B : ndarray, shape (n, K), in T's pixel order
    terms : int, n >= 0
    F : ndarray, shape (n,), optional; diag(T) by default. For a colour T, (n/3, 3, 3):
        F's per-pixel blocks (T's diagonal blocks by default), in T's stored order.
    cache_bytes : int, optional; T's tiles kept between the passes (tile cache budget).
    runner : optional, where the passes run (default: local threads).

    Returns
    -------
    ndarray, shape (n, K), ``compute_dtype(T)``
    """
    terms = int(terms)
    if terms < 0:
        raise BigTError(f"terms must be >= 0, got {terms}")
    dtype = compute_dtype(T)
    finv = BlockDiagonal(_inverse_first_bounce(T, F).astype(dtype))
    B = np.asarray(B, dtype=dtype).reshape(T.shape[0], -1)
    s = B.copy()
    for j in range(terms):
        s = B + s - stream_matmul(T, finv.apply(s), progress=progress,
                                  cache_bytes=cache_bytes, runner=runner,
                                  desc=f"matrix-free term {j + 1}/{terms}")
    return finv.apply(s)


def _inverse_first_bounce(T, F) -> np.ndarray:
    """F^-1 of the matrix-free path: diag(T)'s (blocks') by default, else 1 / F for a
    vector, each block inverted for (n/3, 3, 3) blocks."""
    if F is None:
        return first_bounce_diag(T)
    F = np.asarray(F, np.float64)
    return np.linalg.inv(F) if F.ndim == 3 else 1.0 / F


@dataclass
class PathChoice:
    """Which way compensation goes, and why.

    ``cost_*`` are multiply-adds per frame: nnz(X) for the explicit inverse (one pass
    over X), terms * nnz(T) for the matrix-free path (one pass over T per term).
    """

    path: str
    reason: str
    terms: int | None = None
    cost_explicit: int | None = None
    cost_matrix_free: int | None = None


def inverse_terms(X) -> int | None:
    """The n of T_n^-1 that X holds, from the engine's ``metadata["inverse"]["term"]``."""
    meta = getattr(X, "metadata", None) or {}
    term = (meta.get("inverse") or {}).get("term", meta.get("terms"))
    return None if term is None else int(term)


def choose_path(X=None, T=None, terms: int | None = None, path: str = "auto") -> PathChoice:
    """Pick the explicit or the matrix-free path (cost model in :class:`PathChoice`)."""
    if path not in PATHS:
        raise BigTError(f"path must be one of {PATHS}, got {path!r}")
    if terms is None and X is not None:
        terms = inverse_terms(X)
    terms = int(config.DEFAULT_COMPENSATION_TERMS if terms is None else terms)
    if X is None and T is None:
        raise BigTError("compensation needs the inverse X (explicit path) or the transport T "
                        "(matrix-free path, {option})", option=_MATRIX_FREE_T)
    c_x = None if X is None else int(X.nnz)
    c_t = None if T is None else int(terms * T.nnz)
    if path == "explicit" or (path == "auto" and T is None):
        if X is None:
            raise BigTError("the explicit path needs the inverse X")
        why = "asked for" if path == "explicit" else "no T given for the matrix-free path"
        return PathChoice("explicit", f"{why}: one pass over X, nnz(X) = {c_x:,} per frame",
                          None, c_x, c_t)
    if path == "matrix-free" or X is None:
        if T is None:
            raise BigTError("the matrix-free path needs the transport T ({option})",
                            option=_MATRIX_FREE_T)
        why = "asked for" if path == "matrix-free" else "no inverse X given"
        return PathChoice("matrix-free", f"{why}: {terms} passes over T, {terms} x nnz(T) = "
                          f"{c_t:,} per frame", terms, c_x, c_t)
    if c_x <= c_t:
        return PathChoice("explicit", f"cheaper: nnz(X) = {c_x:,} <= {terms} x nnz(T) = {c_t:,} "
                          "multiply-adds per frame", None, c_x, c_t)
    return PathChoice("matrix-free", f"cheaper: {terms} x nnz(T) = {c_t:,} < nnz(X) = {c_x:,} "
                      "multiply-adds per frame", terms, c_x, c_t)


# --- compensation ---------------------------------------------------------------------

#: Names of the channels of a colour image, in index order (c of 3 p + c).
CHANNEL_NAMES = ("R", "G", "B")


def clipped_by_channel(Y: np.ndarray, clip, channels: int) -> tuple[np.ndarray, np.ndarray]:
    """Values of a matrix-ordered batch outside the clip range, per channel.

    Parameters
    ----------
    Y : ndarray, shape (n, K), matrix order: row 3 p + c holds channel c (colour)
    clip : (lo, hi) or None; either may be None
    channels : int, 1 or 3

    Returns
    -------
    (low, high) : two int64 ndarrays of shape (channels,), the values below lo and above
    hi of each channel (zeros where that side is not clipped).
    """
    Yc = Y.reshape(-1, channels, Y.shape[-1])
    lo, hi = (None, None) if clip is None else clip
    if Y.size > _COUNT_KERNEL_MIN_VALUES and Y.ndim == 2 and Y.flags.c_contiguous:
        return _count_on_threads(Y, lo, hi, channels)
    low = np.zeros(channels, np.int64)
    high = np.zeros(channels, np.int64)
    for c in range(channels):
        # float64 bounds, as the pixel scatter compares (a float32 Y is promoted)
        if lo is not None:
            low[c] = np.count_nonzero(Yc[:, c] < np.float64(lo))
        if hi is not None:
            high[c] = np.count_nonzero(Yc[:, c] > np.float64(hi))
    return low, high


#: Values of a batch past which the clipped values are counted by a numba kernel on the
#: kernel threads (numpy's six strided comparisons took 1/6 of a 64-frame batch).
_COUNT_KERNEL_MIN_VALUES = 1 << 18


def _count_on_threads(Y, lo, hi, channels):
    """:func:`clipped_by_channel` of a large C-contiguous batch, by row ranges."""
    from ..kernels.threads import run_on_threads, thread_count
    from ._resident_kernels import count_clipped  # numba: ~0.5 s, only for large batches

    threads = thread_count()
    n = Y.shape[0]
    step = -(-n // (threads * config.KERNEL_CHUNKS_PER_THREAD))
    step += -step % channels  # whole pixels per range (any split counts right; this reads well)
    ranges = [(a, min(a + step, n)) for a in range(0, n, step)]
    bounds = (0.0 if lo is None else float(lo), 0.0 if hi is None else float(hi),
              lo is not None, hi is not None, channels)
    counts = run_on_threads(lambda a, b: count_clipped(Y, *bounds, a, b), ranges, threads)
    return (np.sum([c[0] for c in counts], axis=0), np.sum([c[1] for c in counts], axis=0))


class ClippedFrames:
    """The rates every compensation report derives from its counts (``frames``,
    ``seconds``, ``clipped_low``, ``clipped_high``, ``pixels``, and per channel
    ``clipped_low_by_channel``, ``clipped_high_by_channel``)."""

    @property
    def clipped_fraction(self) -> float:
        """Projector values outside the clip range / all projector values."""
        return (self.clipped_low + self.clipped_high) / max(self.pixels, 1)

    @property
    def clipped_shares_by_channel(self) -> tuple[tuple[float, float], ...]:
        """(share below lo, share above hi) of each channel's values, (R, G, B) for
        colour, one pair for grey."""
        per = max(self.pixels // max(len(self.clipped_low_by_channel), 1), 1)
        return tuple((low / per, high / per) for low, high in
                     zip(self.clipped_low_by_channel, self.clipped_high_by_channel))

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("inf")


@dataclass
class CompensationReport(ClippedFrames):
    """What :func:`compensate` did.

    Attributes
    ----------
    choice : PathChoice
    frames : int
    clipped_low, clipped_high : int, values of X l_desired below / above the clip range
    pixels : int, all the values of X l_desired (H W per grey frame, 3 H W per colour one)
    clipped_fraction : float, values outside the clip range / all values
    clipped_low_by_channel, clipped_high_by_channel : tuple of int, the same per channel
        (R, G, B for colour; one for grey)
    seconds : float, wall time of the products (reading included)
    """

    choice: PathChoice
    frames: int = 0
    clipped_low: int = 0
    clipped_high: int = 0
    pixels: int = 0
    seconds: float = 0.0
    clipped_low_by_channel: tuple = ()
    clipped_high_by_channel: tuple = ()

    def add_clipped(self, Y: np.ndarray, clip, channels: int, below: int, above: int,
                    values: int) -> None:
        """Count one batch: ``below``/``above`` its totals (from the pixel scatter),
        ``Y`` its (n, K) matrix-ordered values before clipping, counted per channel for
        colour (grey: the totals are the channel's)."""
        self.clipped_low += below
        self.clipped_high += above
        self.pixels += values
        if channels == 1:
            low, high = np.array([below]), np.array([above])
        else:
            low, high = clipped_by_channel(Y, clip, channels)
        if self.clipped_low_by_channel:
            low = low + np.asarray(self.clipped_low_by_channel)
            high = high + np.asarray(self.clipped_high_by_channel)
        self.clipped_low_by_channel = tuple(int(v) for v in low)
        self.clipped_high_by_channel = tuple(int(v) for v in high)


def compensate_frames(frames: np.ndarray, *, X=None, T=None, choice: PathChoice, clip=(0, 1),
                      report: CompensationReport | None = None, progress: bool = False,
                      cache_bytes: int | None = None, runner=None):
    """One batch: (K, *frame_shape) desired frames (linear light) -> projector inputs of
    the same shape, clipped."""
    store = X if choice.path == "explicit" else T
    order = pixel_order_of(store, frames.shape[1:])
    B = to_vectors(frames, order, compute_dtype(store))
    if choice.path == "explicit":
        Y = stream_matmul(X, B, progress=progress, desc="X pass", cache_bytes=cache_bytes,
                          runner=runner)
    else:
        Y = matrix_free_apply(T, B, choice.terms, progress=progress, cache_bytes=cache_bytes,
                              runner=runner)
    frames_out, below, above = matrix_to_frames(Y, order, clip)
    if report is not None:
        report.add_clipped(Y, clip, order.channels, below, above, frames_out.size)
    return frames_out


def compensate(X, images, clip=(0, 1), batch: int = config.DEFAULT_BATCH, *, T=None,
               terms: int | None = None, path: str = "explicit", progress: bool = False,
               cache_bytes: int | None = None, return_report: bool = False, scheduler=None):
    """Projector inputs that make the camera see ``images``: l_in = clip(X l_desired).

    Paper eqs. 44-45. X is streamed from disk one tile row at a time against ``batch``
    frames, so the batch costs one pass over X whatever K is.

    Parameters
    ----------
    X : BlockCSR or path, shape (n, n), the (stratified) inverse of T; may be None for
        ``path="matrix-free"``.
    images : ndarray, shape (H, W) or (K, H, W), desired camera images in [0, 1], linear
        light; (H, W, 3) or (K, H, W, 3) for a colour X (``X.channels == 3``).
    clip : (lo, hi) or None
        Projector range; ``(0, None)`` is the paper's f_+ = max(., 0); None: no clipping.
    batch : int, frames per pass.
    T : BlockCSR or path, optional, the transport (matrix-free path).
    terms : int, optional, n of T_n^-1 for the matrix-free path (default: X's metadata,
        else ``config.DEFAULT_COMPENSATION_TERMS``).
    path : {"explicit", "matrix-free", "auto"}
        "auto" takes the cheaper of nnz(X) and terms * nnz(T) (see :func:`choose_path`).
    cache_bytes : int, optional
        Decoded tiles kept between batches (default ``config.COMPENSATE_CACHE_BYTES``;
        0: every batch re-reads the matrix from disk).
    return_report : bool
        Also return a :class:`CompensationReport`.
    scheduler : None, "local:N", an address or a distributed.Client
        Where the tile rows run (:func:`bigT.schedule.runner.open_runner`); default:
        local threads.

    Returns
    -------
    ndarray, the shape of ``images``, float64 (and the report when asked).
    """
    X = None if X is None else as_store(X, "X")
    T = None if T is None else as_store(T, "T")
    choice = choose_path(X, T, terms, path)
    store = X if choice.path == "explicit" else T
    frames, single, _ = as_frames(images, store)
    report = CompensationReport(choice)
    out = np.empty_like(frames)
    batch = max(1, int(batch))
    t0 = time.perf_counter()
    with scheduler_runner(scheduler) as runner:
        try:
            for s in range(0, len(frames), batch):
                out[s:s + batch] = compensate_frames(
                    frames[s:s + batch], X=X, T=T, choice=choice, clip=clip, report=report,
                    progress=progress, cache_bytes=cache_budget(cache_bytes), runner=runner)
        finally:
            forget_tiles(runner, X, T)
    report.seconds = time.perf_counter() - t0
    report.frames = len(frames)
    result = out[0] if single else out
    return (result, report) if return_report else result


def relight(T, images, batch: int = config.DEFAULT_BATCH, *, progress: bool = False,
            cache_bytes: int | None = None, scheduler=None) -> np.ndarray:
    """What the camera sees for projector images: T l (forward transport).

    Parameters
    ----------
    T : BlockCSR or path, shape (n, n)
    images : ndarray, shape (H, W) or (K, H, W); (H, W, 3) or (K, H, W, 3) for a colour
        T. Linear light.
    scheduler : as :func:`compensate`'s

    Returns
    -------
    ndarray, the shape of ``images``, float64
    """
    T = as_store(T, "T")
    frames, single, order = as_frames(images, T)
    out = np.empty_like(frames)
    batch = max(1, int(batch))
    with scheduler_runner(scheduler) as runner:
        try:
            for s in range(0, len(frames), batch):
                B = to_vectors(frames[s:s + batch], order, compute_dtype(T))
                out[s:s + batch] = to_frames(stream_matmul(
                    T, B, progress=progress, desc="T pass",
                    cache_bytes=cache_budget(cache_bytes), runner=runner), order)
        finally:
            forget_tiles(runner, T)
    return out[0] if single else out


# --- bounce separation ------------------------------------------------------------------

def first_bounce_from_inverse(X) -> np.ndarray:
    """True F of a diffuse scene from its inverse (paper eq. 33): F_ii = 1 / X_ii, (n,), in
    X's stored order, since bounce separation multiplies stored vectors with it (the
    algorithms layer's :func:`~bigT.algorithms.recover_first_bounce`, which gives it
    as an image by default; 0 on pixels left out of the inverse, X_ii = 0); a negative
    X_ii is an InvalidMatrixError. For a colour X (3 channels): the inverses of X's
    3x3 diagonal blocks, shape (n/3, 3, 3), pixel by pixel in X's stored order (apply
    them with :class:`bigT.kernels.BlockDiagonal`; their entries may be negative)."""
    from ..algorithms.first_bounce import recover_first_bounce  # dask via the engine:
    # only bounce separation needs it

    F = recover_first_bounce(X, output_order="matrix")  # multiplied with stored vectors
    if F.ndim == 3:
        return F
    bad = np.flatnonzero(F < 0)
    if bad.size:
        raise InvalidMatrixError(f"diag(X) must not be negative to recover F_ii = 1/X_ii; "
                                 f"{bad.size} entries are (first at index {bad[0]})",
                                 getattr(X, "path", None))
    return F


def separate_bounces(T, X, image, bounces: int = 4, *, progress: bool = False) -> np.ndarray:
    """Split the camera image T l into light bounces (Seitz et al. 2005, docs/DESIGN.md).

    F is recovered from X (F_ii = 1/X_ii, paper eq. 33; for colour the inverse of each
    pixel's 3x3 diagonal block of X), A = I - F X, and bounce k is
    b_k = A^k F l, computed with mat-vecs only: A v = v - F (X v). Since
    sum_k A^k F = (I - A)^-1 F = X^-1, the parts sum to T l when X is the exact inverse;
    the last part is the remainder T l - sum_{k<=K} b_k, so the returned parts always sum
    to T l exactly.

    Parameters
    ----------
    T, X : BlockCSR or path, shape (n, n)
    image : ndarray, shape (H, W) or (B, H, W); (H, W, 3) or (B, H, W, 3) for colour
    bounces : int, K >= 0

    Returns
    -------
    ndarray, shape (K + 2, *image.shape), float64: b_0 (direct), b_1, ..., b_K,
    remainder.
    """
    T = as_store(T, "T")
    X = as_store(X, "X")
    bounces = int(bounces)
    if bounces < 0:
        raise BigTError(f"bounces must be >= 0, got {bounces}")
    if tuple(T.shape) != tuple(X.shape):
        raise ShapeMismatchError(f"X is {X.shape} but T ({T.path}) is {T.shape}: not the "
                                 "inverse of this T", X.path)
    frames, single, order_t = as_frames(image, T)
    order_x = pixel_order_of(X, frames.shape[1:])
    if order_x.image_shape != order_t.image_shape:
        raise ShapeMismatchError(f"X maps {order_x.image_shape} images but T ({T.path}) "
                                 f"maps {order_t.image_shape}", X.path)
    F = BlockDiagonal(first_bounce_from_inverse(X))  # in X's pixel order; 3x3 blocks for colour
    # Work in float64 for the dense vectors so the parts sum to T l to rounding.
    v = F.apply(to_vectors(frames, order_x, np.float64))
    parts = [v]
    try:
        for k in range(bounces):
            v = v - F.apply(stream_matmul(X, v, progress=progress,
                                          desc=f"bounce {k + 1}/{bounces}",
                                          cache_bytes=cache_budget(None)))
            parts.append(v)
    finally:
        forget_tiles(None, X)
    seen = to_frames(stream_matmul(T, to_vectors(frames, order_t, np.float64),
                                   progress=progress, desc="T pass"), order_t)
    out = [to_frames(p, order_x) for p in parts]
    out.append(seen - np.sum(out, axis=0))
    result = np.stack(out)
    return result[:, 0] if single else result


def bounce_shares(parts: np.ndarray) -> np.ndarray:
    """Each part's share of the total (sum of the parts = T l), shape (K + 2,)."""
    totals = parts.reshape(parts.shape[0], -1).sum(axis=1)
    whole = totals.sum()
    return totals / whole if whole != 0 else np.full_like(totals, np.nan)


# --- metrics ----------------------------------------------------------------------------

def relative_error(seen: np.ndarray, desired: np.ndarray) -> float:
    """||seen - desired|| / ||desired|| (Frobenius over all frames)."""
    den = np.linalg.norm(desired)
    return float(np.linalg.norm(seen - desired) / den) if den > 0 else float("nan")


def fluctuation(values: np.ndarray) -> float:
    """(max - min) / mean, the paper's flatness measure for a constant target (§6.1.3)."""
    values = np.asarray(values, dtype=np.float64)
    mean = values.mean()
    return float((values.max() - values.min()) / mean) if mean != 0 else float("nan")


def scan_line(image: np.ndarray) -> np.ndarray:
    """The centre horizontal scan line of an (H, W) image."""
    return np.asarray(image)[image.shape[0] // 2]
