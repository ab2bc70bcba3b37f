"""Block-diagonal matrices of b x b blocks (b = 1: a diagonal held as its vector).

The first bounce F of a colour transport (and F^-1) is block-diagonal with one 3 x 3
colour-mixing block per pixel, the rows and columns 3 p .. 3 p + 2 of pixel p; a grey
F is diagonal. :class:`BlockDiagonal` holds either and applies it to dense blocks and
to CSR row blocks, from the left or the right. Products with a block-diagonal factor
are O(b nnz): vectorised numpy for dense blocks, one scipy product with the
(n, n) CSR of the blocks for sparse ones (b^2 entries a row; the b = 1 cases are the
scale kernels of :mod:`.csr`, so a grey F costs what it always did).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import ShapeMismatchError
from .csr import scale_cols, scale_rows

__all__ = ["BlockDiagonal", "diagonal_blocks", "off_block_diagonal"]


class BlockDiagonal:
    """A block-diagonal (n, n) matrix.

    Parameters
    ----------
    values : ndarray
        (n,) for b = 1 (the diagonal), or (n / b, b, b), the blocks in order.

    Attributes
    ----------
    values : the array given
    b : int, the block size
    n : int, the matrix side
    """

    def __init__(self, values: np.ndarray):
        values = np.asarray(values)
        if values.ndim == 1:
            b = 1
        elif values.ndim == 3 and values.shape[1] == values.shape[2]:
            b = values.shape[1]
        else:
            raise ShapeMismatchError(f"a block diagonal is (n,) or (m, b, b), got shape "
                                     f"{values.shape}")
        self.values, self.b = values, int(b)
        self.n = values.shape[0] * self.b
        self._csr = None

    def astype(self, dtype) -> BlockDiagonal:
        return BlockDiagonal(self.values.astype(dtype))

    def _check_start(self, start: int, rows: int) -> None:
        if start % self.b or not 0 <= start <= start + rows <= self.n:
            raise ShapeMismatchError(f"rows {start}:{start + rows} do not cover whole "
                                     f"{self.b}x{self.b} blocks of a {self.n}x{self.n} "
                                     "block diagonal")

    def apply(self, V: np.ndarray, start: int = 0) -> np.ndarray:
        """Rows ``start:start + r`` of B times V, V of shape (r, k): those rows of B V
        when V holds the same rows of a dense block; shape (r, k)."""
        r = V.shape[0]
        if self.b == 1:
            return self.values[start:start + r, None] * V
        self._check_start(start, r)
        blocks = self.values[start // self.b:(start + r) // self.b]
        k = V.shape[1]
        out = np.matmul(blocks, V.reshape(-1, self.b, k))
        return out.reshape(r, k)

    def scale_rows(self, A, start: int = 0, dtype=None) -> sp.csr_array:
        """B's rows ``start:start + r`` (in ``dtype``, A's by default) times A (an
        (r, m) row block with the same rows), shape (r, m), sorted indices; each row of
        the result mixes the b rows of its block."""
        A = sp.csr_array(A)
        r = A.shape[0]
        dtype = A.dtype if dtype is None else dtype
        if self.b == 1:
            return scale_rows(A, np.asarray(self.values[start:start + r], dtype=dtype))
        self._check_start(start, r)
        local = _block_csr(self.values[start // self.b:(start + r) // self.b], dtype)
        return _canonical(local @ A)

    def scale_cols(self, A) -> sp.csr_array:
        """A times B, A of shape (r, n); shape (r, n), sorted indices."""
        A = sp.csr_array(A)
        if self.b == 1:
            return scale_cols(A, np.asarray(self.values, dtype=A.dtype))
        return _canonical(A @ self.csr(A.dtype))

    def rows(self, start: int, stop: int, dtype) -> sp.csr_array:
        """Rows ``start:stop`` of B as CSR of shape (stop - start, n), global columns,
        zero entries dropped."""
        if self.b == 1:
            v = np.asarray(self.values[start:stop], dtype=dtype)
            rows = np.flatnonzero(v)
            return sp.csr_array((v[rows], (rows, rows + start)), shape=(stop - start, self.n))
        self._check_start(start, stop - start)
        local = _block_csr(self.values[start // self.b:stop // self.b], dtype)
        coo = local.tocoo()
        return _canonical(sp.csr_array((coo.data, (coo.row, coo.col + start)),
                                       shape=(stop - start, self.n)))

    def csr(self, dtype) -> sp.csr_array:
        """B as an (n, n) CSR (b^2 entries a row, zeros dropped), made once per dtype."""
        if self._csr is None or self._csr.dtype != np.dtype(dtype):
            self._csr = _block_csr(self.values, dtype)
        return self._csr


def _block_csr(blocks: np.ndarray, dtype) -> sp.csr_array:
    """The (m b, m b) block-diagonal CSR of ``blocks`` (m, b, b), zeros dropped."""
    m, b, _ = blocks.shape
    base = (np.arange(m) * b)[:, None, None]
    rows = np.broadcast_to(base + np.arange(b)[None, :, None], blocks.shape)
    cols = np.broadcast_to(base + np.arange(b)[None, None, :], blocks.shape)
    keep = blocks != 0
    out = sp.csr_array((blocks[keep].astype(dtype), (rows[keep], cols[keep])),
                       shape=(m * b, m * b))
    return _canonical(out)


def _canonical(A) -> sp.csr_array:
    """``A`` as a csr_array with sorted, duplicate-free indices (what the stores and
    the kernels take)."""
    A = sp.csr_array(A)
    A.sum_duplicates()
    A.sort_indices()
    return A


def _block_of_entries(A: sp.csr_array, start: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """(global row, column) of each stored entry of the row block A whose first row is
    global row ``start``: int64 arrays of A.nnz."""
    row = start + np.repeat(np.arange(A.shape[0], dtype=np.int64), np.diff(A.indptr))
    return row, np.asarray(A.indices[:A.indptr[-1]], dtype=np.int64)


def off_block_diagonal(A, start: int, b: int) -> sp.csr_array:
    """The row block A (first row: global row ``start``, a multiple of b) without the
    entries of its b x b diagonal blocks: (i, j) with i // b == j // b are dropped."""
    A = sp.csr_array(A)
    row, col = _block_of_entries(A, start, b)
    keep = (row // b) != (col // b)
    counts = np.bincount(row[keep] - start, minlength=A.shape[0])
    indptr = np.concatenate([[0], np.cumsum(counts)])
    out = sp.csr_array((A.data[:A.indptr[-1]][keep], A.indices[:A.indptr[-1]][keep], indptr),
                       shape=A.shape)
    out.has_sorted_indices = A.has_sorted_indices
    return out


def diagonal_blocks(A, start: int, b: int) -> np.ndarray:
    """The b x b diagonal blocks of the row block A (first row: global row ``start``,
    a multiple of b; global columns), shape (r / b, b, b), A's float dtype."""
    A = sp.csr_array(A)
    r = A.shape[0]
    if start % b or r % b:
        raise ShapeMismatchError(f"rows {start}:{start + r} do not cover whole {b}x{b} "
                                 "blocks")
    row, col = _block_of_entries(A, start, b)
    on = (row // b) == (col // b)
    out = np.zeros((r // b, b, b), dtype=np.result_type(A.dtype, np.float32))
    np.add.at(out, ((row[on] - start) // b, row[on] % b, col[on] % b), A.data[:A.indptr[-1]][on])
    return out
