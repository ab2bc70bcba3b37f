"""Operands of the tile-row products: stored matrices and M = D - T F^-1, read tile by
tile from the stores through a byte-bounded cache shared by the worker threads."""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
import scipy.sparse as sp

from . import blocks
from ._backend import scale_rows, spmm_dense


def nbytes(A) -> int:
    if sp.issparse(A):
        return int(A.data.nbytes + A.indices.nbytes + A.indptr.nbytes)
    return int(getattr(A, "nbytes", 64))


class TileCache:
    """Least-recently-used cache of tiles / tile rows, bounded in bytes.

    Reading a tile row of P_{k-1} is needed by every output tile row whose M tiles
    touch it; tiles of M are needed at every term. Both are kept while they fit.
    ``budget`` 0 disables caching.
    """

    def __init__(self, budget: int):
        self.budget = int(budget)
        self.used = 0
        self._d: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get(self, key, compute):
        with self._lock:
            if key in self._d:
                self._d.move_to_end(key)
                self.hits += 1
                return self._d[key]
            self.misses += 1
        value = compute()
        size = nbytes(value)
        if size <= self.budget:
            with self._lock:
                if key not in self._d:
                    self._d[key] = value
                    self.used += size
                    while self.used > self.budget and self._d:
                        _, old = self._d.popitem(last=False)
                        self.used -= nbytes(old)
        return value

    def drop(self, prefix):
        """Forget every entry whose key starts with ``prefix`` (a store path)."""
        with self._lock:
            for k in [k for k in self._d if k[0] == prefix]:
                self.used -= nbytes(self._d.pop(k))


class StoreOperand:
    """A stored matrix B, optionally read as diag(row_scale) @ B (S = F X).

    Parameters
    ----------
    store : BlockCSR
    row_scale : (n,) ndarray, optional
    cache : TileCache, optional
        Tile rows read through it (only for operands read more than once).
    """

    def __init__(self, store, row_scale=None, cache: TileCache | None = None):
        self.store = store
        self.row_scale = row_scale
        self.cache = cache
        self.shape = tuple(store.shape)
        self.dtype = np.dtype(store.dtype)
        self.nonempty = np.diff(np.asarray(store.tile_indptr)) > 0

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

    def tiles(self, i, js) -> list[sp.csr_array]:
        out = []
        for j in js:
            t = sp.csr_array(self.store.get_tile(i, int(j)))
            if self.row_scale is not None:
                a, b = self.store.tile_row_range(i)
                t = scale_rows(t, np.asarray(self.row_scale[a:b], dtype=t.dtype))
            out.append(t)
        return out


class MOperand:
    """M = D - T F^-1 (paper eq. 13 with the preconditioner F), never stored: its tiles
    are made from T's tiles when first needed and cached.

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
        self._key = (T.path, "M", bool(zero_diagonal), id(finv))
        self.row_range = T.tile_row_range

    def col_range(self, j):
        return self.T.tile_row_range(j)  # square tiles, square matrix

    def tile_columns(self, i) -> np.ndarray:
        js = np.asarray(self.T.tile_columns(i), dtype=np.int64)
        a, b = self.T.tile_row_range(i)
        if not self.zero_diagonal and self.active[a:b].any() and i not in set(js.tolist()):
            js = np.sort(np.append(js, i))
        return js

    def _make_tile(self, i, j):
        a, b = self.T.tile_row_range(i)
        c, d = self.col_range(j)
        Tij = sp.csr_array(self.T.get_tile(i, j)) if self.T.has_tile(i, j) else \
            blocks.empty((b - a, d - c), self.dtype)
        return blocks.m_tile(Tij, self.finv[c:d], i == j, self.active[a:b], self.zero_diagonal)

    def tile(self, i, j) -> sp.csr_array:
        return self.cache.get(self._key + (int(i), int(j)), lambda: self._make_tile(int(i), int(j)))

    def tiles(self, i, js) -> list[sp.csr_array]:
        return [self.tile(i, j) for j in js]

    def row(self, i) -> sp.csr_array:
        """Tile row i of M, shape (rows_i, n), global columns."""
        a, b = self.T.tile_row_range(i)
        n = self.shape[1]
        js = self.tile_columns(i)
        if len(js) == 0:
            return blocks.empty((b - a, n), self.dtype)
        parts = []
        for j in js:
            t = self.tile(i, j).tocoo()
            c, _ = self.col_range(j)
            parts.append((t.row, t.col + c, t.data))
        r = np.concatenate([p[0] for p in parts])
        c = np.concatenate([p[1] for p in parts])
        v = np.concatenate([p[2] for p in parts])
        out = sp.csr_array((v, (r, c)), shape=(b - a, n))
        out.sort_indices()
        return out

    def matvec_row(self, i, V) -> np.ndarray:
        """Rows i of M @ V, V of shape (n, k)."""
        a, b = self.T.tile_row_range(i)
        out = np.zeros((b - a, V.shape[1]), dtype=np.result_type(V.dtype, self.dtype))
        for j in self.tile_columns(i):
            c, d = self.col_range(j)
            spmm_dense(self.tile(i, j), V[c:d], out=out, n_threads=1)
        return out
