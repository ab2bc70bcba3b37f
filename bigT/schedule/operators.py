"""Operands of the tile-row products: stored matrices and M = D - T F^-1, read tile by
tile from the stores through a byte-bounded cache shared by the worker threads."""

from __future__ import annotations

import threading
import numpy as np
import scipy.sparse as sp

from . import blocks
from ._backend import scale_rows, spmm_dense
from .memory import stored_bytes


def nbytes(A) -> int:
    if sp.issparse(A):
        return int(A.data.nbytes + A.indices.nbytes + A.indptr.nbytes)
    return int(getattr(A, "nbytes", 64))


class TileCache:
    """Tiles / tile rows kept in memory, bounded in bytes, thread safe.

    Entries are admitted while they fit and kept until dropped: the passes of a run
    scan tile rows in the same order every time, and a least-recently-used policy
    smaller than the scan would evict every row just before it is needed again (no
    hit at all); keeping the first rows that fit gives hits on that share of every
    scan. ``budget`` 0 disables caching.
    """

    def __init__(self, budget: int):
        self.budget = int(budget)
        self.used = 0
        self._d: dict = {}
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get(self, key, compute):
        with self._lock:
            if key in self._d:
                self.hits += 1
                return self._d[key]
            self.misses += 1
        value = compute()
        size = nbytes(value)
        with self._lock:
            if key not in self._d and self.used + size <= self.budget:
                self._d[key] = value
                self.used += size
        return value

    def lookup(self, key):
        """The entry under ``key``, or None (nothing is computed or admitted)."""
        with self._lock:
            value = self._d.get(key)
            if value is not None:
                self.hits += 1
            return value

    def has_room(self, size: int) -> bool:
        """Whether an entry of ``size`` bytes would be admitted now."""
        with self._lock:
            return self.used + int(size) <= self.budget

    def resize(self, budget: int) -> None:
        """Set the budget; entries admitted last are forgotten until it holds."""
        with self._lock:
            self.budget = int(budget)
            while self.used > self.budget and self._d:
                self.used -= nbytes(self._d.pop(next(reversed(self._d))))

    def drop(self, prefix):
        """Forget every entry whose key starts with ``prefix`` (a store path)."""
        self.drop_where(lambda path: path == prefix)

    def drop_where(self, predicate):
        """Forget every entry whose key's first element (a store path) satisfies
        ``predicate``."""
        with self._lock:
            for k in [k for k in self._d if predicate(k[0])]:
                self.used -= nbytes(self._d.pop(k))


class StoreOperand:
    """A stored matrix B, optionally read as diag(row_scale) @ B (S = F X).

    Parameters
    ----------
    store : BlockCSR
    row_scale : (n,) ndarray, optional
    cache : TileCache, optional
        Tile rows (and the assembled matrix) are kept there when it is given.
    """

    def __init__(self, store, row_scale=None, cache: TileCache | None = None):
        self.store = store
        self.row_scale = row_scale
        self.cache = cache
        self.shape = tuple(store.shape)
        self.dtype = np.dtype(store.dtype)
        indptr = np.asarray(store.tile_indptr)
        self.nonempty = np.diff(indptr) > 0
        self.nnz = int(store.nnz)
        self._whole = None
        self._row_len = None
        self._lock = threading.Lock()
        self._row_nnz = np.add.reduceat(np.append(np.asarray(store.tile_nnz), 0),
                                        indptr[:-1]) * self.nonempty

    def row_nnz(self, j) -> int:
        return int(self._row_nnz[j])

    @property
    def nbytes(self) -> int:
        """Bytes of the whole matrix in memory (CSR)."""
        return stored_bytes(self.nnz, self.shape[0], self.dtype.itemsize)

    def row_bytes(self, j) -> int:
        a, b = self.store.tile_row_range(j)
        return stored_bytes(self.row_nnz(j), b - a, self.dtype.itemsize)

    def work_per_row(self, left: sp.csr_array) -> np.ndarray:
        """Estimated multiply-adds of each row of ``left @ self``, shape (rows,): the
        tile-row average row length stands for each row of this matrix."""
        if self._row_len is None:
            lens = np.zeros(self.shape[0], dtype=np.float64)
            for j in np.flatnonzero(self.nonempty):
                a, b = self.store.tile_row_range(j)
                lens[a:b] = self._row_nnz[j] / (b - a)
            self._row_len = lens
        c = np.concatenate([[0.0], np.cumsum(self._row_len[left.indices])])
        return c[left.indptr[1:]] - c[left.indptr[:-1]]

    def tile_columns(self, i) -> np.ndarray:
        return np.asarray(self.store.tile_columns(i), dtype=np.int64)

    def _read_row(self, j):
        r = sp.csr_array(self.store.get_tile_row(j))
        if self.row_scale is not None:
            a, b = self.store.tile_row_range(j)
            r = scale_rows(r, np.asarray(self.row_scale[a:b], dtype=r.dtype))
        return r

    def row(self, j) -> sp.csr_array:
        """Tile row j, shape (rows_j, n), global columns."""
        if self.cache is None:
            return self._read_row(j)
        return self.cache.get((self.store.path, "row", int(j)), lambda: self._read_row(j))

    def assembled(self, js, cached: bool = True) -> sp.csr_array:
        """The (n, n) matrix restricted to tile rows ``js`` (others empty); tile rows
        come through the cache when there is one and ``cached``, and are read one at
        a time into arrays of the final size."""
        read = self.row if cached else self._read_row
        return blocks.assemble_rows(
            ((self.store.tile_row_range(j)[0], read(j)) for j in js),
            self.shape[0], self.shape[1], self.dtype,
            nnz=int(sum(self._row_nnz[j] for j in js)))

    def whole(self) -> sp.csr_array:
        """The whole matrix in memory, read once per pass by the first task that needs
        it and shared by the others (held by this operand, outside the tile cache, so
        tile rows of M cannot evict it mid-pass; :meth:`release` lets it go)."""
        with self._lock:
            if self._whole is None:
                self._whole = self.assembled(np.flatnonzero(self.nonempty), cached=False)
            return self._whole

    def release(self) -> None:
        """Drop the whole matrix read by :meth:`whole` (end of a pass)."""
        with self._lock:
            self._whole = None

    def matvec_row(self, i, V) -> np.ndarray:
        a, b = self.store.tile_row_range(i)
        out = np.zeros((b - a, V.shape[1]), dtype=np.result_type(V.dtype, self.dtype))
        if self.nonempty[i]:
            spmm_dense(self._read_row(i), V, out=out, n_threads=1)
        return out


class MOperand:
    """M = D - T F^-1 (paper eq. 13 with the preconditioner F), never stored: its tile
    rows are made from T's when first needed and kept in the cache (every term and
    every mat-vec uses them).

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
    finv : (n,) ndarray, 1/F, 0 on excluded pixels
    active : (n,) bool ndarray, D's diagonal
    zero_diagonal : bool, F = diag T (M's diagonal is exactly 0)
    cache : TileCache
    """

    def __init__(self, T, finv, active, zero_diagonal, cache: TileCache):
        self.T = T
        self.finv = finv
        self.active = active
        self.zero_diagonal = zero_diagonal
        self.cache = cache
        self.shape = tuple(T.shape)
        self.dtype = np.dtype(T.dtype)
        self.grid = tuple(T.grid)
        self.row_range = T.tile_row_range
        self._key = (T.path, "M", bool(zero_diagonal), id(finv))

    def tile_columns(self, i) -> np.ndarray:
        """Tile columns of M's (possibly) nonzero tiles in tile row i: T's, plus the
        diagonal tile when D contributes there."""
        js = np.asarray(self.T.tile_columns(i), dtype=np.int64)
        a, b = self.T.tile_row_range(i)
        if not self.zero_diagonal and self.active[a:b].any() and i not in set(js.tolist()):
            js = np.sort(np.append(js, i))
        return js

    def _make_row(self, i):
        a, b = self.T.tile_row_range(i)
        return blocks.m_rows(sp.csr_array(self.T.get_tile_row(i)), a, self.finv,
                             self.active[a:b], self.zero_diagonal)

    def row(self, i) -> sp.csr_array:
        """Tile row i of M, shape (rows_i, n), global columns."""
        return self.cache.get(self._key + ("row", int(i)), lambda: self._make_row(int(i)))

    def matvec_row(self, i, V, minus_finv_v=None) -> np.ndarray:
        """Rows of tile row i of M @ V, V of shape (n, k).

        When M's tile row is not cached and the cache has no room for it, T's tile row
        is used as read, M V = D V - T F^-1 V (with M's zero diagonal restored when
        F = diag T): building M's row costs more than the product and would not be
        kept. ``minus_finv_v`` (a callable giving -F^-1 V) lets the tasks of one
        mat-vec share that product (see :meth:`row_matvec`).
        """
        a, b = self.T.tile_row_range(i)
        out = np.zeros((b - a, V.shape[1]), dtype=np.result_type(V.dtype, self.dtype))
        key = self._key + ("row", int(i))
        M_row = self.cache.lookup(key)
        if M_row is None and not self.cache.has_room(self._row_bytes(i)):
            T_row = sp.csr_array(self.T.get_tile_row(i))
            scaled = minus_finv_v() if minus_finv_v else -(self.finv[:, None] * V)
            spmm_dense(T_row, scaled, out=out, n_threads=1)
            if self.zero_diagonal:
                out += (T_row.diagonal(k=a) * self.finv[a:b])[:, None] * V[a:b]
            else:
                out += self.active[a:b, None] * V[a:b]
            return out
        spmm_dense(self.row(i) if M_row is None else M_row, V, out=out, n_threads=1)
        return out

    def row_matvec(self, V):
        """``matvec_row`` for the tile-row tasks of one mat-vec with V: -F^-1 V is
        computed at most once, shared, and let go with the returned function."""
        held, lock = [], threading.Lock()

        def minus_finv_v():
            with lock:
                if not held:
                    held.append(-(self.finv[:, None] * V))
                return held[0]

        return lambda i, V_: self.matvec_row(i, V_, minus_finv_v)

    def _row_bytes(self, i) -> int:
        a, b = self.T.tile_row_range(i)
        lo, hi = self.T.tile_indptr[i], self.T.tile_indptr[i + 1]
        nnz = int(np.asarray(self.T.tile_nnz[lo:hi]).sum())
        return stored_bytes(nnz, b - a, self.dtype.itemsize)
