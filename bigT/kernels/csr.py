"""Checked wrappers over the CSR kernels: scipy.sparse in, ``csr_array`` out.

Every wrapper validates its inputs (shapes, index ranges, finite values: one pass,
always on), converts them to one index dtype and one float dtype, and calls the
unchecked kernels of :mod:`bigT.kernels._csr_kernels`, or, below
``config.KERNEL_NUMPY_MAX_WORK`` multiply-adds (entries), their numpy/scipy twins in
:mod:`bigT.kernels._small`: numba is imported and its kernels compiled only when a run
has work big enough to gain from them. Results are ``scipy.sparse.csr_array`` with
sorted, duplicate-free indices.

Dtypes: the result dtype is numpy's promotion of the inputs (float32 with float32 is
float32; anything with float64 is float64; integers and bools are promoted to a float).
Sparse products accumulate in float64 and round once to the result dtype: the
accumulator is one row (or 8 rows) long and lives in cache, and the scatter loop is
bound by its loads and stores, not by the width of the adds, so float64 costs nothing
measurable there, and a float32 result is the rounded value of a float64 sum instead
of ~400 float32 roundings. ``spmm_dense`` with k > 1 is the exception (see there).

Threads: products split the rows into ranges of equal work (multiply-adds) and run the
``nogil`` kernels on the process's shared thread pool (:mod:`bigT.kernels.threads`;
one thread per core by default, ``bigT.config.KERNEL_THREADS``). A thread pool rather than numba's ``prange``
because (1) each range writes its pruned rows into its own growable buffers, which
``prange`` cannot express without a symbolic pass; (2) the schedule layer calls these
kernels from dask's worker threads, and numba's default ``workqueue`` threading layer
is not thread-safe under concurrent callers (and nested parallelism would
oversubscribe the cores); with plain threads, a caller that already parallelises over
tiles passes ``n_threads=1``; (3) no ``parallel=True`` compile, so ``cache=True``
works for every kernel.
"""

from __future__ import annotations

import contextlib
import threading
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import BigTError, InvalidMatrixError, ShapeMismatchError
from . import _small
from ._constants import CSR_BAD_INDPTR, CSR_INDEX_OUT_OF_RANGE, CSR_NOT_FINITE, CSR_OK, GROUP
from .threads import run_on_threads, thread_count

INT32_MAX = np.iinfo(np.int32).max

__all__ = [
    "spgemm",
    "add_diag_scaled",
    "scale_rows",
    "scale_cols",
    "diagonal",
    "prune",
    "spmm_dense",
    "choose_index_dtype",
    "release_workspaces",
    "workspace_bytes",
]


# --- helpers -----------------------------------------------------------------------


class _WorkspacePool:
    """Workspaces of the grouped product kernel, lent one per kernel call in flight
    and reused: each spans B's columns (~100 bytes per column: 200 MB at full HD),
    and allocating and zeroing one per tile row cost more than that row's product.

    A workspace is only ever lent to one call at a time; one whose call raised is
    dropped (it may be dirty). At most ``config.KERNEL_WORKSPACES_KEPT`` are kept idle,
    those of other sizes first let go.
    """

    def __init__(self):
        self._idle: list = []
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def lend(self, n_cols: int, n_rows_b: int):
        ws = None
        with self._lock:
            for k, (shape, held) in enumerate(self._idle):
                if shape == (n_cols, n_rows_b):
                    ws = self._idle.pop(k)[1]
                    break
        if ws is None:
            ws = _numba().grouped_workspace(n_cols, n_rows_b)
        yield ws  # an exception here leaves ws out of the pool
        with self._lock:
            self._idle.insert(0, ((n_cols, n_rows_b), ws))
            del self._idle[config.KERNEL_WORKSPACES_KEPT:]

    def clear(self) -> None:
        """Let every idle workspace go (their memory back to the system)."""
        with self._lock:
            self._idle.clear()


_WORKSPACES = _WorkspacePool()


def workspace_bytes(n_cols: int, n_rows_b: int) -> int:
    """Bytes of one workspace of the grouped product kernel for a right factor of
    shape (n_rows_b, n_cols): (GROUP + 1) float64 accumulators, a mark and a list per
    column, a stamp and a slot per row, block marks (at most 1/8 byte per column)."""
    return (GROUP + 1) * 8 * n_cols + 16 * n_cols + 16 * n_rows_b + n_cols // 8 + 64


def release_workspaces() -> None:
    """Free the product kernel's idle workspaces (see :class:`_WorkspacePool`)."""
    _WORKSPACES.clear()

def _numba():
    """The numba kernels, imported (and their cache loaded) on first use."""
    from . import _csr_kernels  # numba and its cache: ~0.5 s, only for products past
    # the numpy twins

    return _csr_kernels


def _small_enough(work: int) -> bool:
    """Below this many multiply-adds (or entries) numpy/scipy do the work."""
    return work <= config.KERNEL_NUMPY_MAX_WORK


def row_work(a_indptr, a_indices, b_indptr) -> np.ndarray:
    """Multiply-adds of each row of A @ B (an upper bound on that row's nnz).

    Returns
    -------
    (n_rows,) int64
    """
    if not _small_enough(len(a_indices)):
        from ._row_kernels import row_work_internal  # numba: as _numba()

        return row_work_internal(a_indptr, a_indices, b_indptr)
    b_len = np.diff(b_indptr).astype(np.int64)
    cum = np.zeros(len(a_indices) + 1, np.int64)
    np.cumsum(b_len[a_indices], out=cum[1:])
    return cum[a_indptr[1:]] - cum[a_indptr[:-1]]


def _split_rows(work, n_chunks):
    """Row boundaries cutting ``work`` (per-row cost) into ``n_chunks`` equal parts."""
    n_rows = work.shape[0]
    if n_rows == 0:
        return np.zeros(1, np.int64)
    cum = np.cumsum(work, dtype=np.int64)
    targets = cum[-1] * np.arange(1, n_chunks, dtype=np.float64) / n_chunks
    cuts = np.searchsorted(cum, targets, side="left") + 1
    bounds = np.unique(np.concatenate(([0], np.minimum(cuts, n_rows), [n_rows])))
    return bounds.astype(np.int64)


def _run_ranges(func, bounds, n_threads):
    """``func(r0, r1)`` over consecutive ranges, results in range order."""
    ranges = [(int(bounds[t]), int(bounds[t + 1])) for t in range(len(bounds) - 1)]
    return run_on_threads(func, ranges, n_threads)


def choose_index_dtype(max_index, nnz, index_dtype=None):
    """int32 when both the largest index and nnz fit in it, else int64.

    Parameters
    ----------
    max_index : int
        Largest index value to store (e.g. columns - 1, rows).
    nnz : int
        Number of stored entries (the last ``indptr`` value).
    index_dtype : dtype-like, optional
        Force a dtype; int32 is refused when it cannot hold the values.
    """
    fits32 = max(int(max_index), int(nnz)) <= INT32_MAX
    if index_dtype is None:
        return np.dtype(np.int32) if fits32 else np.dtype(np.int64)
    index_dtype = np.dtype(index_dtype)
    if index_dtype == np.int64:
        return index_dtype
    if index_dtype == np.int32:
        if not fits32:
            raise InvalidMatrixError(
                f"index_dtype=int32 cannot hold max index {max_index} / nnz {nnz}"
            )
        return index_dtype
    raise BigTError(f"index_dtype must be int32 or int64, got {index_dtype}")


def _float_dtype(*dtypes, name="inputs"):
    dt = np.result_type(*dtypes)
    if dt.kind == "c":
        raise InvalidMatrixError(f"{name}: complex values are not supported ({dt})")
    if dt.kind in "biu" or dt == np.float16:
        dt = np.result_type(dt, np.float32)
    if dt not in (np.float32, np.float64):
        raise InvalidMatrixError(f"{name}: dtype {dt} is not supported (float32/float64)")
    return np.dtype(dt)


_CSR_MESSAGES = {
    CSR_BAD_INDPTR: "malformed CSR indptr (not starting at 0, decreasing, or not "
    "ending at nnz) near row {where}",
    CSR_INDEX_OUT_OF_RANGE: "column index out of range at position {where}",
    CSR_NOT_FINITE: "NaN or Inf value at position {where}",
}


class _CSR:
    """Validated raw arrays of one CSR operand."""

    __slots__ = ("shape", "indptr", "indices", "data")

    def __init__(self, shape, indptr, indices, data):
        self.shape = shape
        self.indptr = indptr
        self.indices = indices
        self.data = data

    @property
    def nnz(self):
        return int(self.indptr[-1])


def _as_csr(A, name, *, dtype=None, index_dtype=None, canonical=True, check=True):
    """Validate ``A`` and return its raw arrays in the requested dtypes.

    ``dtype=None`` keeps A's float dtype; ``index_dtype`` defaults to int32 when the
    shape and nnz allow it. With ``canonical``, rows are sorted and duplicates summed
    (on a copy) when they are not already. ``check=False`` trusts A to be valid and
    canonical (read from a bigT store, whose writer checked it): the O(nnz) scan is
    skipped, which matters when one large right factor meets many small left ones.
    """
    if not sp.issparse(A):
        raise InvalidMatrixError(f"{name} must be a scipy.sparse matrix, got {type(A).__name__}")
    if A.ndim != 2:
        raise ShapeMismatchError(f"{name} must be 2-D, got shape {A.shape}")
    if A.format != "csr":
        A = A.tocsr()
    n_rows, n_cols = (int(s) for s in A.shape)
    fdt = _float_dtype(A.dtype, name=name) if dtype is None else np.dtype(dtype)
    idt = choose_index_dtype(max(n_rows, n_cols), A.nnz, index_dtype)
    indptr = np.asarray(A.indptr)
    indices = np.asarray(A.indices)
    data = np.asarray(A.data)
    if indptr.shape != (n_rows + 1,):
        raise InvalidMatrixError(
            f"{name}: indptr has shape {indptr.shape}, expected ({n_rows + 1},)"
        )
    if indices.shape != data.shape or indices.ndim != 1:
        raise InvalidMatrixError(f"{name}: indices and data differ in shape")
    nnz = int(indptr[-1]) if n_rows >= 0 else 0
    indices = indices[:nnz]
    data = data[:nnz]
    if data.dtype.kind == "c":
        raise InvalidMatrixError(f"{name}: complex values are not supported ({data.dtype})")
    indptr = np.ascontiguousarray(indptr, dtype=idt)
    indices = np.ascontiguousarray(indices, dtype=idt)
    data = np.ascontiguousarray(data, dtype=fdt)
    if not check:
        return _CSR((n_rows, n_cols), indptr, indices, data)
    check = _small.check_csr if _small_enough(len(data)) else _numba().check_csr_internal
    status, where, is_canonical = check(indptr, indices, data, n_cols)
    if status != CSR_OK:
        raise InvalidMatrixError(f"{name}: " + _CSR_MESSAGES[status].format(where=where))
    if canonical and not is_canonical:
        C = sp.csr_array((data, indices, indptr), shape=(n_rows, n_cols), copy=True)
        C.sum_duplicates()
        indptr = np.ascontiguousarray(C.indptr, dtype=idt)
        indices = np.ascontiguousarray(C.indices, dtype=idt)
        data = np.ascontiguousarray(C.data, dtype=fdt)
    return _CSR((n_rows, n_cols), indptr, indices, data)


def _used(indptr, indices, data):
    """A kernel's result whose ``indices`` and ``data`` are its whole output buffers:
    their first ``indptr[-1]`` entries, copied out only when the buffers are much
    longer (a view keeps the whole buffer alive; a copy of a result that filled most of
    it would cost a pass over every entry for little memory)."""
    used = int(indptr[-1])
    indices, data = indices[:used], data[:used]
    if indices.base is not None and indices.base.shape[0] > 1.25 * used + 1024:
        indices, data = indices.copy(), data.copy()
    return indptr, indices, data


def _vector(d, n, name, what):
    d = np.asarray(d)
    if d.ndim != 1 or d.shape[0] != n:
        raise ShapeMismatchError(f"{name} must have shape ({n},) ({what}), got {d.shape}")
    if d.dtype.kind not in "biuf":
        raise InvalidMatrixError(f"{name}: dtype {d.dtype} is not supported")
    if not np.isfinite(d).all():
        raise InvalidMatrixError(f"{name} holds NaN or Inf")
    return d


def _check_threshold(threshold, top_k):
    threshold = float(threshold)
    if not np.isfinite(threshold) or threshold < 0:
        raise BigTError(f"threshold must be finite and >= 0, got {threshold}")
    if top_k is None:
        top_k = -1
    else:
        if isinstance(top_k, bool) or int(top_k) != top_k or top_k < 1:
            raise BigTError(f"top_k must be a positive integer or None, got {top_k!r}")
        top_k = int(top_k)
    return threshold, top_k


def _csr_result(shape, indptr, indices, data, index_dtype=None):
    """Build the csr_array, widening to int64 when nnz or the shape need it."""
    nnz = int(indptr[-1])
    idt = choose_index_dtype(max(shape), nnz, index_dtype)
    if indices.dtype != idt:
        indices = indices.astype(idt)
    if indptr.dtype != idt:
        indptr = indptr.astype(idt)
    C = sp.csr_array((data, indices, indptr), shape=shape, copy=False)
    C.has_sorted_indices = True
    C.has_canonical_format = True
    return C


# --- products ------------------------------------------------------------------------


def spgemm(
    A, B, *, threshold=0.0, top_k=None, n_threads=None, index_dtype=None, method=None,
    checked=True,
):
    """C = A @ B with pruning fused into the row loop.

    Entries with ``|v| < threshold`` (absolute, tested on the value rounded to the
    result dtype) are never written; with ``top_k`` each row then keeps its ``top_k``
    largest |v| (ties go to the smaller column). Exact zeros are dropped even at
    ``threshold=0``, as scipy's product drops them, so ``threshold=0`` gives scipy's
    pattern.

    One pass (no symbolic pass: it would repeat every multiply-add only to size
    buffers that pruning then mostly leaves empty): each row range writes into its own
    doubling buffers, the ranges run on ``n_threads`` threads with the GIL released,
    and the pieces are concatenated. See ``_csr_kernels.spgemm_rows_internal``.

    Parameters
    ----------
    A : scipy.sparse matrix, shape (m, n), float32/float64 (others promoted)
    B : scipy.sparse matrix, shape (n, p)
    threshold : float, >= 0
    top_k : int or None
    n_threads : int, optional
        Default ``bigT.config.KERNEL_THREADS`` (None: one per core).
    index_dtype : {None, int32, int64}
        Force the index dtype of the result; by default int32 when nnz and the shape
        fit, int64 otherwise (never a silent overflow).
    method : {None, "rows", "grouped"}
        Kernel; both give the same entries. ``"grouped"`` (default) multiplies 8
        neighbouring rows of A per pass over B with vector FMAs
        (``_csr_kernels.spgemm_grouped_internal``), falling back to one row at a
        time in groups whose rows share few columns; ``"rows"`` is one row at a time
        throughout (``_csr_kernels.spgemm_rows_internal``).
    checked : bool
        Check both operands (default). False trusts them to be valid CSR, B with
        sorted duplicate-free rows, all values finite (the engine's operands, read
        from stores whose writers checked them): the check of B costs O(nnz(B)) per
        call, and a term calls it once per tile row with the whole right factor.

    Returns
    -------
    scipy.sparse.csr_array, shape (m, p), dtype = promotion of A's and B's dtypes.

    Raises
    ------
    ShapeMismatchError
        ``A.shape[1] != B.shape[0]``.
    InvalidMatrixError
        Malformed CSR, indices out of range, NaN/Inf values.
    """
    threshold, top_k = _check_threshold(threshold, top_k)
    auto = method is None  # an explicit method asks for that numba kernel
    if auto:
        method = "grouped"
    if method not in ("rows", "grouped"):
        raise BigTError(f"method must be 'rows' or 'grouped', got {method!r}")
    for X, nm in ((A, "A"), (B, "B")):
        if sp.issparse(X) and X.ndim != 2:
            raise ShapeMismatchError(f"{nm} must be 2-D, got shape {X.shape}")
    if sp.issparse(A) and sp.issparse(B) and A.shape[1] != B.shape[0]:
        raise ShapeMismatchError(
            f"B has {B.shape[0]} rows but A has {A.shape[1]} columns "
            f"(A {A.shape} @ B {B.shape})"
        )
    fdt = _float_dtype(
        A.dtype if sp.issparse(A) else np.float64,
        B.dtype if sp.issparse(B) else np.float64,
        name="A, B",
    )
    # One index dtype for both operands, so each kernel is compiled for 2 index x 2
    # float dtypes only; int64 as soon as either operand needs it.
    idt = np.dtype(np.int32)
    if sp.issparse(A) and sp.issparse(B):
        need = max(max(A.shape), max(B.shape), A.nnz, B.nnz)
        idt = choose_index_dtype(need, 0, index_dtype)
    a = _as_csr(A, "A", dtype=fdt, index_dtype=idt, canonical=False, check=checked)
    b = _as_csr(B, "B", dtype=fdt, index_dtype=idt, canonical=True, check=checked)
    m, p = a.shape[0], b.shape[1]
    if a.nnz == 0 or b.nnz == 0 or m == 0 or p == 0:
        return _csr_result(
            (m, p), np.zeros(m + 1, idt), np.zeros(0, idt), np.zeros(0, fdt), index_dtype
        )

    work = row_work(a.indptr, a.indices, b.indptr)
    total_work = int(work.sum())
    if auto and _small_enough(total_work):
        indptr, indices, data = _small.spgemm(a, b, threshold, fdt)
        if top_k >= 0:
            indptr, indices, data = _small.top_k(indptr, indices, data, top_k)
        out_idt = choose_index_dtype(max(m, p), int(indptr[-1]), index_dtype)
        return _csr_result((m, p), indptr, indices, data, out_idt)
    K = _numba()
    n_threads = thread_count(n_threads)
    if total_work < config.KERNEL_MIN_PARALLEL_WORK:
        n_threads = 1
    n_chunks = 1 if n_threads == 1 else n_threads * config.KERNEL_CHUNKS_PER_THREAD
    bounds = _split_rows(work, n_chunks)
    if method == "grouped":
        # Ranges start on multiples of GROUP so groups are the same whatever n_threads.
        bounds = np.unique(np.minimum((bounds + GROUP - 1) // GROUP * GROUP, m))
        kernel = K.spgemm_grouped_internal
        tuning = float(config.SPGEMM_GROUP_MIN_EFFICIENCY)
    else:
        kernel = K.spgemm_rows_internal
        tuning = float(config.SPGEMM_DENSE_SCAN_RATIO)
    # Initial buffers: the rows' nnz(A) (a pruned term is about as dense as its
    # factor), capped by the exact upper bound; they double when short.
    cum_work = np.concatenate(([0], np.cumsum(work)))

    def run(r0, r1):
        cap = min(
            int(cum_work[r1] - cum_work[r0]),
            int(a.indptr[r1] - a.indptr[r0]) + 16 * (r1 - r0),
            (r1 - r0) * p,
        )
        args = (r0, r1, a.indptr, a.indices, a.data, b.indptr, b.indices, b.data, p,
                threshold, tuning, cap)
        if method != "grouped":
            return kernel(*args)
        with _WORKSPACES.lend(p, b.shape[0]) as ws:
            return kernel(*args, *ws)

    pieces = _run_ranges(run, bounds, n_threads)
    row_nnz = np.concatenate([pc[0] for pc in pieces])
    nnz = int(row_nnz.sum())
    out_idt = choose_index_dtype(max(m, p), nnz, index_dtype)
    indptr = np.empty(m + 1, out_idt)
    indptr[0] = 0
    np.cumsum(row_nnz, out=indptr[1:])
    if len(pieces) == 1:
        used = nnz
        indices, data = pieces[0][1][:used], pieces[0][2][:used]
        if pieces[0][1].shape[0] > 1.25 * used + 1024:
            indices, data = indices.copy(), data.copy()
    else:
        sizes = [int(pc[0].sum()) for pc in pieces]
        indices = np.concatenate([pc[1][:s] for pc, s in zip(pieces, sizes)])
        data = np.concatenate([pc[2][:s] for pc, s in zip(pieces, sizes)])
    if top_k >= 0:
        indptr, indices, data = K.top_k_internal(indptr, indices, data, top_k)
    return _csr_result((m, p), indptr, indices, data, out_idt)


def spmm_dense(A, X, out=None, *, n_threads=None, absolute=False):
    """A @ X for a sparse A and a dense batch X (images as columns); |A| @ X (A's
    entries' absolute values, A itself untouched) when ``absolute``.

    Parameters
    ----------
    A : scipy.sparse matrix, shape (m, n)
    X : ndarray, shape (n,) or (n, k)
    out : ndarray, shape (m,) or (m, k), optional
        When given, ``out += A @ X`` in place and ``out`` is returned. Must be a
        writeable float32/float64 array; C-contiguous is fastest.
    n_threads : int, optional
    absolute : bool
        Multiply by |A| instead (the products of the spectral radius's upper bound
        rho(|M|), without a copy of M's values).

    Returns
    -------
    ndarray, shape (m,) or (m, k), dtype = promotion of A's and X's dtypes (or
    ``out``'s dtype). For k = 1 each row is summed in float64; for k > 1 in the
    promoted dtype of A and X (float32 for float32 inputs: ~1e-6 relative over a few
    hundred terms, and twice the vector lanes of float64, which this compute-bound
    loop needs to beat scipy).
    """
    if not sp.issparse(A):
        raise InvalidMatrixError(f"A must be a scipy.sparse matrix, got {type(A).__name__}")
    if A.ndim != 2:
        raise ShapeMismatchError(f"A must be 2-D, got shape {A.shape}")
    X = np.asarray(X)
    if X.ndim not in (1, 2):
        raise ShapeMismatchError(f"X must have shape (n,) or (n, k), got {X.shape}")
    if X.shape[0] != A.shape[1]:
        raise ShapeMismatchError(
            f"X has {X.shape[0]} rows but A has {A.shape[1]} columns (A {A.shape} @ X {X.shape})"
        )
    fdt = _float_dtype(A.dtype, X.dtype, name="A, X")
    if A.format != "csr":
        A = A.tocsr()
    m, n = A.shape
    # The structure and value checks run inside the kernel (see
    # spmm_dense_rows_internal); only the array shapes are checked here.
    idt = choose_index_dtype(max(m, n), A.nnz)
    indptr = np.ascontiguousarray(A.indptr, dtype=idt)
    indices = np.ascontiguousarray(A.indices, dtype=idt)
    # A's values as stored when float32 or float64 (the kernel widens each as it uses
    # it): a cast would copy every entry per product, which for a row block of a colour
    # M (float32, ~10^7 entries) cost a third of a mat-vec with float64 vectors
    data = np.ascontiguousarray(A.data, dtype=A.data.dtype if A.data.dtype in
                                (np.float32, np.float64) else fdt)
    if indptr.shape != (m + 1,) or indices.shape != data.shape or indices.ndim != 1:
        raise InvalidMatrixError("A: malformed CSR arrays (indptr/indices/data shapes)")
    if data.dtype.kind == "c":
        raise InvalidMatrixError(f"A: complex values are not supported ({data.dtype})")
    vector = X.ndim == 1
    X2 = np.ascontiguousarray(X[:, None] if vector else X, dtype=fdt)
    k = X2.shape[1]
    if out is None:
        result = np.zeros((m, k), fdt)
        target = result
    else:
        if not isinstance(out, np.ndarray):
            raise InvalidMatrixError(f"out must be a numpy array, got {type(out).__name__}")
        want = (m,) if vector else (m, k)
        if out.shape != want:
            raise ShapeMismatchError(f"out must have shape {want}, got {out.shape}")
        if out.dtype not in (np.float32, np.float64):
            raise InvalidMatrixError(f"out must be float32 or float64, got {out.dtype}")
        if not out.flags.writeable:
            raise InvalidMatrixError("out is not writeable")
        result = out
        target = out.reshape(m, k)
        if not (target.flags.c_contiguous and np.shares_memory(target, out)):
            target = np.ascontiguousarray(target).copy()
    if m and k and indices.shape[0] and _small_enough(indices.shape[0] * k):
        statuses = [_small.spmm_dense(indptr, indices, data, X2, target, absolute)]
    elif m and k and indices.shape[0]:
        K = _numba()
        n_threads = thread_count(n_threads)
        if indices.shape[0] * k < config.SPMM_MIN_PARALLEL_WORK:
            n_threads = 1
        n_chunks = 1 if n_threads == 1 else n_threads * config.KERNEL_CHUNKS_PER_THREAD
        if n_chunks == 1:
            bounds = np.array([0, m], np.int64)
        else:
            bounds = _split_rows(np.diff(indptr).astype(np.int64) + 1, n_chunks)
        statuses = _run_ranges(
            lambda r0, r1: K.spmm_dense_rows_internal(r0, r1, indptr, indices, data, X2, target,
                                                      bool(absolute)),
            bounds,
            n_threads,
        )
    else:
        statuses = []
    for status, where in statuses:
        if status != CSR_OK:
            what = {
                CSR_BAD_INDPTR: "malformed CSR indptr",
                CSR_INDEX_OUT_OF_RANGE: "column index out of range",
                CSR_NOT_FINITE: "NaN or Inf in A or in the rows of X it uses",
            }[status]
            msg = f"A @ X: {what} at row {where}"
            if out is not None:
                msg += " (out is partly updated)"
            raise InvalidMatrixError(msg)
    if statuses:
        if out is not None and target is not result and not np.shares_memory(target, out):
            out[...] = target.reshape(out.shape)
    if out is None and vector:
        return result.reshape(m)
    return result


# --- element-wise and structural ----------------------------------------------------


def add_diag_scaled(A, d, B):
    """C = A + diag(d) @ B, merging the sorted rows of A and B in one pass.

    Parameters
    ----------
    A, B : scipy.sparse matrices of the same shape (m, n)
    d : array_like, shape (m,)

    Returns
    -------
    scipy.sparse.csr_array, shape (m, n), dtype = promotion of A, d, B. Entries that
    are exactly 0 are not stored (as in scipy's ``A + B``).
    """
    d = _vector(d, A.shape[0] if sp.issparse(A) else -1, "d", "one factor per row")
    if sp.issparse(A) and sp.issparse(B) and A.shape != B.shape:
        raise ShapeMismatchError(f"B has shape {B.shape} but A has shape {A.shape}")
    fdt = _float_dtype(A.dtype, d.dtype, B.dtype, name="A, d, B")
    idt = choose_index_dtype(max(max(A.shape), A.nnz, B.nnz), 0)
    a = _as_csr(A, "A", dtype=fdt, index_dtype=idt)
    b = _as_csr(B, "B", dtype=fdt, index_dtype=idt)
    if _small_enough(a.nnz + b.nnz):
        indptr, indices, data = _small.add_diag_scaled(a, d, b, fdt)
    else:
        indptr, indices, data = _used(*_numba().add_diag_scaled_internal(
            a.indptr, a.indices, a.data, np.ascontiguousarray(d, np.float64),
            b.indptr, b.indices, b.data, np.zeros(0, fdt),
        ))
    return _csr_result(a.shape, indptr, indices, data)


def scale_rows(A, d):
    """diag(d) @ A. d: (m,). Returns csr_array, dtype = promotion of A and d."""
    return _scaled(A, d, axis=0)


def scale_cols(A, d):
    """A @ diag(d). d: (n,). Returns csr_array, dtype = promotion of A and d."""
    return _scaled(A, d, axis=1)


def _scaled(A, d, axis: int):
    """Each stored entry of A times d of its row (axis 0) or column (axis 1)."""
    d = _vector(d, A.shape[axis] if sp.issparse(A) else -1, "d",
                "one factor per row" if axis == 0 else "one factor per column")
    fdt = _float_dtype(A.dtype, d.dtype, name="A, d")
    a = _as_csr(A, "A", dtype=fdt)
    d = np.ascontiguousarray(d, fdt)
    # rows are found through indptr, columns through indices
    where = a.indptr if axis == 0 else a.indices
    if _small_enough(a.nnz):
        out = (_small.scale_rows if axis == 0 else _small.scale_cols)(where, a.data, d)
    else:
        out = np.empty_like(a.data)
        kernel = _numba().scale_rows_internal if axis == 0 else _numba().scale_cols_internal
        kernel(where, a.data, d, out)
    return _csr_result(a.shape, a.indptr.copy(), a.indices.copy(), out)


def scale_cols_off_diagonal(A, d, offset: int, *, checked: bool = True):
    """A @ diag(d) without the entries (i, i + offset): rows ``offset:offset + m`` of
    a matrix with its diagonal left out, each column scaled (M = -T F^-1 off the
    diagonal, from a row block of T). One pass.

    Parameters
    ----------
    A : sparse, shape (m, n)
    d : (n,) array
    offset : int, the global index of A's first row
    checked : bool
        Check A and d (default). False trusts A to be valid CSR with sorted,
        duplicate-free rows and finite values (a tile row of T as the store's reader
        returns it, checked there) and d to be finite of length n (the engine's F^-1,
        checked once): each check is a pass over A or d per call, and the engine
        makes M from every tile row of T (at full HD, 0.6 s of one pass's 2 s).

    Returns
    -------
    csr_array, shape (m, n), sorted indices, dtype = promotion of A and d
    """
    n = A.shape[1] if sp.issparse(A) else -1
    d = _vector(d, n, "d", "one factor per column") if checked else np.asarray(d)
    if d.shape != (n,):
        raise ShapeMismatchError(f"d must have shape ({n},) (one factor per column), "
                                 f"got {d.shape}")
    fdt = _float_dtype(A.dtype, d.dtype, name="A, d")
    a = _as_csr(A, "A", dtype=fdt, check=checked)
    d = np.ascontiguousarray(d, fdt)
    indptr = np.empty(a.shape[0] + 1, np.int64)
    indices = np.empty_like(a.indices)
    data = np.empty_like(a.data)
    args = (a.indptr, a.indices, a.data, d)
    if _small_enough(a.nnz):
        _small.scale_cols_off_diagonal(*args, int(offset), indptr, indices, data)
    else:
        _numba().scale_cols_off_diagonal_internal(*args, np.int64(offset), indptr, indices,
                                                  data)
    nnz = int(indptr[-1])
    return _csr_result(a.shape, indptr, indices[:nnz], data[:nnz])


def diagonal(A):
    """The main diagonal of A, shape (min(m, n),), A's float dtype."""
    a = _as_csr(A, "A", canonical=False)
    out = np.zeros(min(a.shape), a.data.dtype)
    if _small_enough(a.nnz):
        _small.diagonal(a.indptr, a.indices, a.data, out)
    else:
        _numba().diagonal_internal(a.indptr, a.indices, a.data, out)
    return out


def prune(A, threshold=0.0, top_k=None):
    """A without its entries |v| < threshold (and exact zeros), then the top_k
    largest |v| per row (ties to the smaller column).

    Returns csr_array of A's float dtype (sorted, duplicates summed before pruning).
    """
    threshold, top_k = _check_threshold(threshold, top_k)
    a = _as_csr(A, "A")
    if _small_enough(a.nnz):
        indptr, indices, data = _small.prune(a.indptr, a.indices, a.data, threshold, a.shape)
        if top_k >= 0:
            indptr, indices, data = _small.top_k(indptr, indices, data, top_k)
    else:
        K = _numba()
        indptr, indices, data = _used(*K.prune_internal(a.indptr, a.indices, a.data,
                                                        threshold))
        if top_k >= 0:
            indptr, indices, data = K.top_k_internal(indptr, indices, data, top_k)
    return _csr_result(a.shape, indptr, indices, data)


class ColumnTiles(NamedTuple):
    """Rows cut into their non-empty column tiles (:func:`split_column_tiles`).

    Attributes
    ----------
    cols : (k,) int64, the tile columns, ascending
    indptr : (k, n_rows + 1) int64, each tile's row pointer
    indices : (nnz,) int32, columns local to the tile, tile after tile
    data : (nnz,), the values in the same order
    bounds : (k + 1,) int64, tile t holds entries ``bounds[t]:bounds[t + 1]``
    """

    cols: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray
    bounds: np.ndarray


def split_column_tiles(indptr, indices, data, tile_size: int) -> ColumnTiles:
    """Cut CSR rows into their non-empty tiles of ``tile_size`` columns, each tile's
    entries in row-major, column-sorted order (the store's layout).

    Trusts its input (the storage writer has validated it): ``indptr`` (n_rows + 1,),
    ``indices`` (nnz,) global columns sorted within each row, ``data`` (nnz,). One
    counting pass and one scatter in numba; numpy's stable radix sort below
    ``config.KERNEL_NUMPY_MAX_WORK`` entries.
    """
    indptr, indices = np.asarray(indptr), np.asarray(indices)
    if _small_enough(indices.size):
        return ColumnTiles(*_small.split_column_tiles(indptr, indices, np.asarray(data),
                                                      int(tile_size)))
    return ColumnTiles(*_numba().split_column_tiles_internal(
        indptr.astype(np.int64, copy=False), indices, np.asarray(data), np.int64(tile_size)))


def join_column_tiles(tiles: ColumnTiles, tile_size: int, n_cols: int):
    """Rows of global columns from their column tiles: the inverse of
    :func:`split_column_tiles` (the store's tiles of one tile row joined).

    Trusts its input (tiles read and checked by the store): ``tiles.cols`` ascending,
    each tile's rows column-sorted, so the joined rows are too.

    Returns
    -------
    (indptr (n_rows + 1,) int64, indices (nnz,) int32 (int64 when ``n_cols`` or nnz
    reach 2**31), data (nnz,) of ``tiles.data``'s dtype)
    """
    n_rows = tiles.indptr.shape[1] - 1
    nnz = int(tiles.bounds[-1])
    wide = n_cols >= 2**31 or nnz >= 2**31
    indptr = np.empty(n_rows + 1, np.int64)
    indices = np.empty(nnz, np.int64 if wide else np.int32)
    data = np.empty(nnz, tiles.data.dtype)
    args = (tiles.cols.astype(np.int64, copy=False), tiles.indptr.astype(np.int64, copy=False),
            tiles.indices, tiles.data, tiles.bounds.astype(np.int64, copy=False))
    if _small_enough(nnz):
        _small.join_column_tiles(*args, int(tile_size), indptr, indices, data)
    else:
        _numba().join_column_tiles_internal(*args, np.int64(tile_size), indptr, indices, data)
    return indptr, indices, data
