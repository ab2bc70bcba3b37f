"""Operands of the row-block products: stored matrices and M = D - T F^-1, read tile
by tile from the stores through the process's tile cache (:mod:`.cache`)."""

from __future__ import annotations

import threading

import numpy as np
import scipy.sparse as sp

from . import blocks
from ._backend import BlockDiagonal, diagonal_blocks, scale_rows, spmm_dense
from .cache import TileCache
from .costs import SharedRead
from .memory import stored_bytes


def needed_rows(left: sp.csr_array, right) -> tuple[np.ndarray, int]:
    """Tile rows of ``right`` that ``left @ right`` reads: those under a column of
    ``left`` holding an entry and not empty (a pair with a zero factor is never
    read), int64 ascending; and how many such pairs were skipped (the left tile holds
    entries, the right tile row is empty). One counting pass over ``left.indices``
    (a sort of millions of indices per task would cost more than the pairs save)."""
    if not left.nnz:
        return np.zeros(0, dtype=np.int64), 0
    hit = np.bincount(np.asarray(left.indices) // right.tile_size,
                      minlength=right.grid[0]) > 0
    use = np.flatnonzero(hit & right.nonempty)
    return use, int(np.count_nonzero(hit)) - len(use)


class StoreOperand:
    """A stored matrix B, optionally read as diag(row_scale) @ B (S = F X).

    Parameters
    ----------
    store : BlockCSR
    row_scale : (n,) ndarray, optional; or (n/b, b, b) blocks of a block-diagonal F
        (colour), B read as F B
    cache : TileCache, optional
        Tile rows are kept there when it is given.
    version : tuple, optional
        Identifies this version of the store in the cache's keys.
    """

    def __init__(self, store, row_scale=None, cache: TileCache | None = None,
                 version: tuple = ()):
        self.store = store
        self.row_scale = row_scale
        self.cache = cache
        self.shape = tuple(store.shape)
        self.dtype = np.dtype(store.dtype)
        self.grid = tuple(store.grid)
        self.tile_size = int(store.tile_size)
        indptr = np.asarray(store.tile_indptr)
        self.nonempty = np.diff(indptr) > 0
        self.nnz = int(store.nnz)
        self._key = (str(store.path), version, "row", row_scale is not None)
        self._whole = None
        self._row_len = None
        self._lock = threading.Lock()
        # a block-diagonal F (colour, b x b blocks) mixes each pixel's b rows of B, so
        # a row of F B holds up to b times a row's entries (the union of the b rows'):
        # the sizes the memory plan reads are B's counts times that bound
        self.fill = _block_size(row_scale)
        self._row_nnz = np.add.reduceat(np.append(np.asarray(store.tile_nnz), 0),
                                        indptr[:-1]) * self.nonempty * self.fill

    @property
    def nbytes(self) -> int:
        """Bytes of the whole matrix in memory (CSR): for F B with a colour F, the most
        it may hold (``fill`` times B's entries)."""
        return stored_bytes(self.nnz * self.fill, self.shape[0], self.dtype.itemsize)

    def row_bytes(self, j) -> int:
        """Bytes of tile row j in memory (at most, for F B with a colour F)."""
        a, b = self.store.tile_row_range(j)
        return stored_bytes(int(self._row_nnz[j]), b - a, self.dtype.itemsize)

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

    def _scaled(self, r: sp.csr_array, a: int, b: int) -> sp.csr_array:
        if self.row_scale is None:
            return r
        if np.ndim(self.row_scale) == 3:
            return BlockDiagonal(self.row_scale).scale_rows(r, a)
        return scale_rows(r, np.asarray(self.row_scale[a:b], dtype=r.dtype))

    def _read_row(self, j):
        a, b = self.store.tile_row_range(j)
        return self._scaled(sp.csr_array(self.store.get_tile_row(j)), a, b)

    def row(self, j) -> sp.csr_array:
        """Tile row j, shape (rows_j, n), global columns."""
        if self.cache is None:
            return self._read_row(j)
        return self.cache.get(self._key + (int(j),), lambda: self._read_row(j))

    def rows(self, start: int, stop: int, cached: bool = True) -> sp.csr_array:
        """Rows ``start:stop`` (a tile row of this store, or any range); through the
        cache when ``cached`` and they are a tile row."""
        j = start // self.tile_size
        if self.store.tile_row_range(j) == (start, stop):
            return self.row(j) if cached else self._read_row(j)
        return self._scaled(self.store.get_rows(start, stop), start, stop)

    def assembled(self, js, cached: bool = True) -> sp.csr_array:
        """The (n, n) matrix restricted to tile rows ``js`` (others empty); tile rows
        come through the cache when there is one and ``cached``, and are read one at
        a time into arrays of the final size."""
        read = self.row if cached else self._read_row
        row_blocks = ((self.store.tile_row_range(j)[0], read(j)) for j in js)
        if np.ndim(self.row_scale) == 3:
            # F B with a colour F mixes each pixel's rows: its entries are known only
            # once read (the store's counts are B's), so the rows are read first
            row_blocks = list(row_blocks)
            nnz = sum(B.nnz for _, B in row_blocks)
        else:
            nnz = int(sum(self._row_nnz[j] for j in js))
        return blocks.assemble_rows(row_blocks, self.shape[0], self.shape[1], self.dtype,
                                    nnz=nnz)

    def whole(self) -> sp.csr_array:
        """The whole matrix in memory, read once per pass by the first task of this
        process that needs it and shared by the others (held by this operand, outside
        the tile cache, so tile rows of M cannot evict it mid-pass; :meth:`release`
        lets it go)."""
        with self._lock:
            if self._whole is None:
                with SharedRead():  # read once here for the process's tasks: a broadcast
                    self._whole = self.assembled(np.flatnonzero(self.nonempty), cached=False)
            return self._whole

    def release(self) -> None:
        """Drop the whole matrix read by :meth:`whole` (end of a pass)."""
        with self._lock:
            self._whole = None


def _block_size(scale) -> int:
    """b of a block-diagonal scale given as (n/b, b, b) blocks; 1 for a diagonal (n,) or
    none."""
    return int(np.shape(scale)[1]) if np.ndim(scale) == 3 else 1


class MOperand:
    """M = D - T F^-1 (paper eq. 13 with the preconditioner F), never stored: its row
    blocks are made from T's rows when first needed and kept in the cache (every term
    and every mat-vec uses them).

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
    finv : (n,) ndarray, 1/F, 0 on excluded pixels; or (n/b, b, b), the inverses of a
        block-diagonal F's blocks (colour)
    active : (n,) bool ndarray, D's diagonal
    zero_diagonal : bool, F = diag T (M's diagonal is exactly 0), or its diagonal
        blocks (M's diagonal blocks are 0)
    cache : TileCache
    digest : str, identifies F (cache keys)
    version : tuple, identifies this version of T (cache keys)
    """

    def __init__(self, T, finv, active, zero_diagonal, cache: TileCache, digest: str = "",
                 version: tuple = ()):
        self.T = T
        self.finv = finv
        self.active = active
        self.zero_diagonal = zero_diagonal
        self.cache = cache
        self.shape = tuple(T.shape)
        self.dtype = np.dtype(T.dtype)
        self._key = (str(T.path), version, "M", bool(zero_diagonal), digest)
        self._version = version
        # -F^-1 in T's dtype, once per operand (a pass's, in this process) rather than
        # once per row block of M made (grey F; a colour F's blocks are applied as such)
        self._minus_finv = None if np.ndim(finv) == 3 else -np.asarray(finv, dtype=self.dtype)
        row_nnz = np.add.reduceat(np.append(np.asarray(T.tile_nnz, dtype=np.int64), 0),
                                  np.asarray(T.tile_indptr)[:-1])
        # T F^-1 with a colour F spreads each entry of T over its pixel's b columns: a
        # row of M holds up to b times T's row's entries
        self._row_nnz = row_nnz * (np.diff(np.asarray(T.tile_indptr)) > 0) * _block_size(finv)

    def _T_rows(self, a: int, b: int, take: bool) -> sp.csr_array:
        """T's rows ``a:b``: a tile row kept in the cache by the read of T's diagonal
        (:func:`t_row_key`; taken out of it when ``take``: M's rows made from it
        replace it), else read from the store."""
        i = a // self.T.tile_size
        if self.T.tile_row_range(i) == (a, b):
            key = t_row_key(self.T, self._version, i)
            held = self.cache.pop(key) if take else self.cache.lookup(key)
            if held is not None:
                return held
        return sp.csr_array(self.T.get_rows(a, b))

    def _make_rows(self, a, b):
        return blocks.m_rows(T_rows=self._T_rows(a, b, take=True), start=a,
                             finv=self.finv, active_rows=self.active[a:b],
                             zero_diagonal=self.zero_diagonal, minus_finv=self._minus_finv,
                             checked=False)  # T's rows checked by its reader, F^-1 by F's

    def rows(self, a: int, b: int) -> sp.csr_array:
        """Rows ``a:b`` of M, shape (b - a, n), global columns."""
        return self.cache.get(self._key + (int(a), int(b)), lambda: self._make_rows(a, b))

    def row_bytes(self, a: int, b: int) -> int:
        """Estimated bytes of rows ``a:b`` of M (T's tile-row nnz, pro rata; times b
        for a colour F's b x b blocks: at most)."""
        ts = self.T.tile_size
        nnz = sum(self._row_nnz[i] * (min(b, (i + 1) * ts) - max(a, i * ts))
                  / (self.T.tile_row_range(i)[1] - i * ts)
                  for i in range(a // ts, -(-b // ts)))
        return stored_bytes(int(nnz), b - a, self.dtype.itemsize)

    def largest_entries(self, a: int, b: int) -> np.ndarray:
        """The largest entry of each of M's rows ``a:b`` (0 for a row without a positive
        one), shape (b - a, 1): from M's rows as the products use them, exactly."""
        return largest_row_entries(self.rows(a, b))

    def abs_matvec_rows(self, a: int, b: int, V) -> np.ndarray:
        """Rows ``a:b`` of |M| V (|M|: M's entries' absolute values), V of shape (n, k):
        from M's rows, cached (or admitted) by :meth:`rows` (|M| mixes the signs of
        T F^-1's entries, so T's rows alone do not give it); the kernel takes each
        entry's absolute value as it reads it."""
        out = np.zeros((b - a, V.shape[1]), dtype=np.result_type(V.dtype, self.dtype))
        spmm_dense(self.rows(a, b), V, out=out, n_threads=1, absolute=True)
        return out

    def matvec_rows(self, a: int, b: int, V, minus_finv_v=None) -> np.ndarray:
        """Rows ``a:b`` of M @ V, V of shape (n, k).

        When M's rows are not cached and the cache has no room for them, T's rows are
        used as read, M V = D V - T F^-1 V (with M's zero diagonal restored when
        F = diag T): building M's rows costs more than the product and would not be
        kept. ``minus_finv_v`` (-F^-1 V, computed once per pass per process) saves
        each task that product.
        """
        out = np.zeros((b - a, V.shape[1]), dtype=np.result_type(V.dtype, self.dtype))
        M_rows = self.cache.lookup(self._key + (int(a), int(b)))
        if M_rows is None and not self.cache.has_room(self.row_bytes(a, b)):
            T_rows = self._T_rows(a, b, take=False)
            if np.ndim(self.finv) == 3:
                return self._matvec_from_T_blocks(T_rows, a, b, V, minus_finv_v, out)
            scaled = -(self.finv[:, None] * V) if minus_finv_v is None else minus_finv_v
            spmm_dense(T_rows, scaled, out=out, n_threads=1)
            if self.zero_diagonal:
                out += (T_rows.diagonal(k=a) * self.finv[a:b])[:, None] * V[a:b]
            else:
                out += self.active[a:b, None] * V[a:b]
            return out
        spmm_dense(self.rows(a, b) if M_rows is None else M_rows, V, out=out, n_threads=1)
        return out

    def _matvec_from_T_blocks(self, T_rows, a: int, b: int, V, minus_finv_v, out):
        """:meth:`matvec_rows` from T's rows for a block-diagonal F (colour): -T F^-1 V,
        with M's zero diagonal blocks restored (T's diagonal blocks times F^-1 V added
        back) or D V added, on the kept rows."""
        finv = BlockDiagonal(self.finv)
        scaled = -finv.apply(V) if minus_finv_v is None else minus_finv_v
        spmm_dense(T_rows, scaled, out=out, n_threads=1)
        if self.zero_diagonal:
            blocks = diagonal_blocks(T_rows, a, finv.b)
            k = V.shape[1]
            out -= np.matmul(blocks, scaled[a:b].reshape(-1, finv.b, k)).reshape(b - a, k)
        else:
            out += V[a:b]
        out *= self.active[a:b, None]
        return out


def t_row_key(T, version: tuple, i: int) -> tuple:
    """The tile cache's key of T's tile row ``i`` (global columns) read whole before
    any pass (for F's diagonal) and kept for M's rows to be made from
    (:meth:`MOperand.rows`), ``version`` T's identity (the process's cache keys)."""
    return (str(T.path), version, "T", int(i))


def largest_row_entries(M: sp.csr_array) -> np.ndarray:
    """The largest entry of each row of CSR ``M`` (0 for a row without a positive one),
    shape (rows, 1), float64: what the spectral radius's bracket needs of M's rows."""
    out = np.zeros((M.shape[0], 1), dtype=np.float64)
    filled = np.flatnonzero(np.diff(M.indptr))
    if len(filled):
        top = np.maximum.reduceat(M.data[:M.indptr[-1]], M.indptr[filled])
        out[filled, 0] = np.maximum(top, 0.0)
    return out
