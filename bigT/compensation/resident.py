"""X held in memory for real-time compensation: one pass over RAM per batch of frames.

Streaming X from disk costs a read and a decode of every tile per batch; a projector
showing 30-60 frames per second needs a frame in ~16 ms, far less than that. When X's
arrays fit a memory budget they are loaded once into one CSR-like layout and every
frame (or batch of frames) is one pass over it. That pass is bound by memory bandwidth:
each entry is read once per batch, so the bytes per entry set the frame rate.

Layout (:class:`ResidentMatrix`): the columns are cut into panels of 65536, so a column
index inside its panel fits 16 bits (``uint16``); within each row the entries are
sorted by column, so one panel's entries are contiguous: a *segment*. Only the segments
that hold entries are kept (``seg_panel``, ``seg_start``, and ``row_seg`` where each
row's segments start): a row of a local transport touches a few panels of the 32 of
full HD (127 at 4K), and a pointer per row and panel would cost 132 bytes a row at full
HD (more than a row's entries in float16 at 4K) and a loop over every panel. The
values are

* ``float32`` (6 bytes per entry with the 16-bit indices, against 8 for float32 values
  with int32 indices), the same numbers as the store: the products agree with the
  streamed path to float32 rounding; or
* ``float16`` (4 bytes per entry): IEEE binary16 of ``x / s_i * 2**15``, with ``s_i``
  the smallest power of two >= the row's largest magnitude, so every row uses
  binary16's normal range (relative rounding <= 2**-11) down to ``2**-29 * s_i``
  whatever its magnitude (binary16 alone overflows at 65504 and loses relative
  precision below 6e-5); each entry is off by at most ``2**-11 |x| + 2**-40 s_i``.
  The kernels decode a value by a table of the 65536 binary16 values (numba has no
  float16 arithmetic) and multiply the row's sum by ``s_i * 2**-15`` once.

The products run on ``nogil`` numba kernels over row ranges of equal entries on a
thread pool (as :mod:`bigT.kernels` does, so ``cache=True`` works and no numba
threading layer is involved); matrices with little work use scipy and compile nothing.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import BigTError, MemoryLimitError, ShapeMismatchError
from ..kernels.threads import run_on_threads, thread_count
from ..schedule.memory import available_memory
from ..storage.channel_mixing import ChannelMixing, mixed_product, mixed_rows

#: Columns per panel: an index inside a panel fits uint16.
PANEL_BITS = 16
PRECISIONS = ("float32", "float16")
#: float16 encoding: a row's values are scaled into [-2**15, 2**15] (see the docstring).
_F16_SHIFT = 2.0 ** 15


@dataclass(frozen=True, eq=False)  # identity: arrays do not compare
class ResidentMatrix:
    """A sparse matrix held in memory in the panel layout of the module docstring.

    Attributes
    ----------
    shape : (n_rows, n_cols)
    row_seg : ndarray, shape (n_rows + 1,), int32 or int64
        Row i's segments are ``row_seg[i]:row_seg[i + 1]``.
    seg_panel : ndarray, shape (n_segments,), uint16
        The panel of each segment (its columns are 65536 * panel + indices).
    seg_start : ndarray, shape (n_segments + 1,), int32 or int64
        Segment s's entries are ``seg_start[s]:seg_start[s + 1]``.
    indices : ndarray, shape (nnz,), uint16; column - 65536 * panel.
    values : ndarray, shape (nnz,); float32, or uint16 (binary16 bits) for float16.
    row_scale : ndarray, shape (n_rows,), float32 or None
        What each row's sum is multiplied by (float16 only).
    precision : {"float32", "float16"}
    pixel_order : PixelOrder or None, the store's.
    path : str, the store it was loaded from.
    mixing : ChannelMixing or None
        The store's factored channel mixing: this holds S, the matrix is L S R
        (:mod:`bigT.storage.channel_mixing`); products and ``to_scipy`` apply it.
    """

    shape: tuple
    row_seg: np.ndarray
    seg_panel: np.ndarray
    seg_start: np.ndarray
    indices: np.ndarray
    values: np.ndarray
    row_scale: np.ndarray | None
    precision: str
    pixel_order: object
    path: str
    mixing: ChannelMixing | None = None

    @property
    def nnz(self) -> int:
        return int(self.indices.size)

    @property
    def n_panels(self) -> int:
        """Panels of 65536 columns the columns are cut into."""
        return _panel_count(self.shape[1])

    @property
    def n_segments(self) -> int:
        """Runs of a row's entries in one panel (at most nnz)."""
        return int(self.seg_panel.size)

    @property
    def row_start(self) -> np.ndarray:
        """(n_rows + 1,) int64: where each row's entries start (a CSR indptr)."""
        return np.asarray(self.seg_start, np.int64)[np.asarray(self.row_seg, np.int64)]

    @property
    def nbytes(self) -> int:
        """Bytes held, which are also the bytes read by one product (one pass)."""
        scale = 0 if self.row_scale is None else self.row_scale.nbytes
        return (self.row_seg.nbytes + self.seg_panel.nbytes + self.seg_start.nbytes
                + self.indices.nbytes + self.values.nbytes + scale)

    @property
    def dtype(self) -> np.dtype:
        """Dtype of the products (float32)."""
        return np.dtype(np.float32)

    def to_scipy(self) -> sp.csr_array:
        """The decoded matrix as a float32 csr_array (reference and small products)."""
        S = _scipy_of(self)
        return mixed_rows(self.mixing, S, 0) if self.mixing is not None else S

    def matmul(self, V: np.ndarray, out: np.ndarray | None = None,
               n_threads: int | None = None) -> np.ndarray:
        """X @ V.

        Parameters
        ----------
        V : ndarray, shape (n_cols,) or (n_cols, K); converted to C-contiguous float32.
        out : ndarray, shape (n_rows, K), float32, C-contiguous, optional
        n_threads : int, optional (default: one per core)

        Returns
        -------
        ndarray, shape (n_rows,) or (n_rows, K), float32
        """
        if self.mixing is None:
            return _matmul(self, V, out, n_threads)
        Y = mixed_product(self.mixing, lambda W: _matmul(self, W, None, n_threads),
                          np.ascontiguousarray(V, dtype=np.float32))
        if out is None:
            return Y
        out[...] = Y.reshape(out.shape)
        return out

    def __matmul__(self, V):
        return self.matmul(V)


# --- building -----------------------------------------------------------------------

def _panel_count(n_cols: int) -> int:
    return max(1, -(-int(n_cols) >> PANEL_BITS))


def resident_bytes_needed(X, precision: str = "float32") -> int:
    """Bytes a :class:`ResidentMatrix` of the store ``X`` will hold at most (without
    loading): the entries exactly, the segments bounded from the tile index (per tile
    row, its rows times the panels its stored tiles reach, and at most its entries)."""
    _check_precision(precision)
    n_rows = X.shape[0]
    per_entry = 2 + (4 if precision == "float32" else 2)
    scale = 4 * n_rows if precision == "float16" else 0
    segments = _segment_bound(X)
    seg_item = 2 + (4 if X.nnz < 2**31 else 8)  # uint16 panel + its start
    row_item = 4 if segments < 2**31 else 8
    return X.nnz * per_entry + segments * seg_item + (n_rows + 1) * row_item + scale


def _segment_bound(X) -> int:
    """At most how many segments (runs of a row's entries in one panel) ``X`` has."""
    total = 0
    for i in range(X.grid[0]):
        lo, hi = int(X.tile_indptr[i]), int(X.tile_indptr[i + 1])
        full = X.tile_nnz[lo:hi] > 0
        if not full.any():
            continue
        first = np.asarray(X.tile_indices[lo:hi][full], np.int64) * X.tile_size
        last = np.minimum(first + X.tile_size, X.shape[1]) - 1
        panels = np.zeros(_panel_count(X.shape[1]), bool)
        for a, b in zip(first >> PANEL_BITS, last >> PANEL_BITS):
            panels[a:b + 1] = True
        r0, r1 = X.tile_row_range(i)
        total += min(int(X.tile_nnz[lo:hi].sum()), (r1 - r0) * int(panels.sum()))
    return total


def load_bytes_needed(X, precision: str = "float32") -> int:
    """Peak bytes while loading: the result plus the largest decoded tile row (its
    scipy CSR with int32/64 indices, twice over while it is split into panels)."""
    widest = 0
    for i in range(X.grid[0]):
        lo, hi = X.tile_indptr[i], X.tile_indptr[i + 1]
        widest = max(widest, int(X.tile_nnz[lo:hi].sum()))
    per_entry = np.dtype(X.dtype).itemsize + 8
    return resident_bytes_needed(X, precision) + 2 * widest * per_entry


def default_memory_limit() -> int:
    """The default budget of a resident X: ``config.COMPENSATE_RESIDENT_FRACTION`` of
    the available memory (``config.COMPENSATE_RESIDENT_FALLBACK_BYTES`` where unknown)."""
    avail = available_memory()
    if avail is None:
        return config.COMPENSATE_RESIDENT_FALLBACK_BYTES
    return int(avail * config.COMPENSATE_RESIDENT_FRACTION)


def _check_precision(precision: str) -> None:
    if precision not in PRECISIONS:
        raise BigTError(f"precision must be one of {PRECISIONS}, got {precision!r}")


def load_resident(X, precision: str = "float32", *, memory_limit: int | None = None
                  ) -> ResidentMatrix:
    """Read every tile row of the store ``X`` once into a :class:`ResidentMatrix`.

    Parameters
    ----------
    X : BlockCSR, shape (n_rows, n_cols)
    precision : {"float32", "float16"}
    memory_limit : int, optional
        Refuse (MemoryLimitError) when loading would need more bytes
        (:func:`load_bytes_needed`); default :func:`default_memory_limit`.
    """
    _check_precision(precision)
    limit = default_memory_limit() if memory_limit is None else int(memory_limit)
    need = load_bytes_needed(X, precision)
    if need > limit:
        raise MemoryLimitError(f"holding X in memory needs {need / 2**20:.0f} MiB, over the "
                               f"limit of {limit / 2**20:.0f} MiB", getattr(X, "path", None))
    n_rows, n_cols = X.shape
    indices = np.empty(X.nnz, np.uint16)
    values = np.empty(X.nnz, np.float32 if precision == "float32" else np.uint16)
    row_scale = np.empty(n_rows, np.float32) if precision == "float16" else None
    seg_counts = np.zeros(n_rows, np.int64)
    panels: list[np.ndarray] = []
    starts: list[np.ndarray] = []
    fill = 0
    for i in range(X.grid[0]):
        r0, _ = X.tile_row_range(i)
        rows = X.get_tile_row(i)
        if precision == "float16":
            rows, row_scale[r0:r0 + rows.shape[0]] = _encode_f16(rows)
        k = rows.nnz
        indices[fill:fill + k] = rows.indices & ((1 << PANEL_BITS) - 1)
        values[fill:fill + k] = rows.data
        panel, start, per_row = _segments(rows)
        panels.append(panel)
        starts.append(start + fill)
        seg_counts[r0:r0 + rows.shape[0]] = per_row
        fill += k
    entry_dtype = np.int32 if X.nnz < 2**31 else np.int64
    seg_start = np.concatenate([*starts, [X.nnz]]).astype(entry_dtype)
    seg_dtype = np.int32 if seg_start.size <= 2**31 else np.int64
    row_seg = np.zeros(n_rows + 1, seg_dtype)
    np.cumsum(seg_counts, out=row_seg[1:])
    seg_panel = np.concatenate(panels).astype(np.uint16) if panels else np.zeros(0, np.uint16)
    return ResidentMatrix((n_rows, n_cols), row_seg, seg_panel, seg_start, indices, values,
                          row_scale, precision, getattr(X, "pixel_order", None),
                          str(getattr(X, "path", "")), getattr(X, "mixing", None))


def _segments(rows: sp.csr_array) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The segments of ``rows`` (columns sorted within rows, so a row's entries of one
    panel are contiguous): (panel of each, its first entry, segments per row)."""
    m = rows.shape[0]
    if rows.nnz == 0:
        return np.zeros(0, np.uint16), np.zeros(0, np.int64), np.zeros(m, np.int64)
    row_of = np.repeat(np.arange(m, dtype=np.int64), np.diff(rows.indptr))
    panel = rows.indices.astype(np.int64) >> PANEL_BITS
    new = np.empty(rows.nnz, bool)
    new[0] = True
    new[1:] = (row_of[1:] != row_of[:-1]) | (panel[1:] != panel[:-1])
    start = np.flatnonzero(new)
    return panel[start], start, np.bincount(row_of[start], minlength=m)


def _encode_f16(rows: sp.csr_array):
    """float32 rows -> (rows with binary16 bits as data, (m,) float32 row scales).

    Scale s_i = 2**ceil(log2 max|row i|); stored: binary16 of x / s_i * 2**15, in
    [-2**15, 2**15]; the decoded sum is multiplied by s_i * 2**-15 (powers of two: no
    rounding but binary16's)."""
    m = rows.shape[0]
    data = np.asarray(rows.data, np.float64)
    top = np.zeros(m)
    nz = np.diff(rows.indptr) > 0
    if rows.nnz:
        top[nz] = np.maximum.reduceat(np.abs(data), rows.indptr[:-1][nz])
    scale = np.exp2(np.ceil(np.log2(np.where(top > 0, top, 1.0))))
    scaled = data / np.repeat(scale, np.diff(rows.indptr)) * _F16_SHIFT
    bits = scaled.astype(np.float16).view(np.uint16)
    out = sp.csr_array((bits, rows.indices, rows.indptr), shape=rows.shape)
    return out, (scale / _F16_SHIFT).astype(np.float32)


#: float32 value of each binary16 bit pattern: the kernels' decoding table.
F16_TABLE = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.float16).astype(
    np.float32)


def decode_values(R: ResidentMatrix) -> np.ndarray:
    """(nnz,) float32 values as the kernels see them (before the row scale)."""
    if R.precision == "float32":
        return R.values
    return F16_TABLE[R.values]


def _scipy_of(R: ResidentMatrix) -> sp.csr_array:
    n_rows, n_cols = R.shape
    seg_start = np.asarray(R.seg_start, np.int64)
    panel_of = np.repeat(R.seg_panel.astype(np.int64), np.diff(seg_start))
    cols = (panel_of << PANEL_BITS) + R.indices
    data = decode_values(R)
    indptr = R.row_start
    if R.row_scale is not None:
        data = data * np.repeat(R.row_scale, np.diff(indptr))
    out = sp.csr_array((data.astype(np.float32), cols, indptr), shape=(n_rows, n_cols))
    out.has_sorted_indices = True
    return out


# --- products -------------------------------------------------------------------------

#: The scipy twin of a small matrix, made once per matrix.
_SMALL: "weakref.WeakKeyDictionary[ResidentMatrix, sp.csr_array]" = weakref.WeakKeyDictionary()


def _ranges(R: ResidentMatrix, parts: int) -> list[tuple[int, int]]:
    """Row ranges of about equal entries (the work of a pass)."""
    n = R.shape[0]
    if parts <= 1 or n < 2 * parts:
        return [(0, n)]
    starts = R.row_start[:-1]
    cuts = np.searchsorted(starts, np.linspace(0, R.nnz, parts + 1)[1:-1])
    bounds = np.unique(np.r_[0, cuts, n])
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def _matmul(R: ResidentMatrix, V, out, n_threads):
    n_rows, n_cols = R.shape
    V = np.asarray(V)
    vector = V.ndim == 1
    if V.ndim not in (1, 2) or V.shape[0] != n_cols:
        raise ShapeMismatchError(f"cannot multiply a {n_rows}x{n_cols} matrix by an array of "
                                 f"shape {V.shape}")
    V2 = np.ascontiguousarray(V.reshape(n_cols, -1), dtype=np.float32)
    K = V2.shape[1]
    if out is None:
        out = np.empty((n_rows, K), np.float32)
    elif out.shape != (n_rows, K) or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ShapeMismatchError(f"out must be a C-contiguous float32 array of shape "
                                 f"{(n_rows, K)}, got {out.dtype} {out.shape}")
    if R.nnz * K <= config.KERNEL_NUMPY_MAX_WORK:
        out[...] = _small_csr(R) @ V2  # no kernel compiled for a small product
    else:
        _run_kernel(R, V2, out, thread_count(n_threads or None))
    return out[:, 0] if vector else out


def _small_csr(R):
    if R not in _SMALL:
        _SMALL[R] = _scipy_of(R)
    return _SMALL[R]


def _run_kernel(R, V, out, threads):
    from ._resident_kernels import kernel_for  # numba: ~0.5 s, only past the scipy twin

    kernel = kernel_for(V.shape[1])
    empty = np.ones(0, np.float32)
    scale = empty if R.row_scale is None else R.row_scale
    lut = F16_TABLE if R.precision == "float16" else empty
    args = (R.row_seg, R.seg_panel, R.seg_start, R.indices, R.values, lut, scale, V, out)
    ranges = _ranges(R, threads * config.KERNEL_CHUNKS_PER_THREAD if threads > 1 else 1)
    run_on_threads(lambda a, b: kernel(*args, a, b), ranges, threads)
