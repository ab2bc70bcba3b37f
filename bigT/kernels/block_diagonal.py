"""Block-diagonal matrices of b x b blocks (b = 1: a diagonal held as its vector).

The first bounce F of a colour transport (and F^-1) is block-diagonal with one 3 x 3
colour-mixing block per pixel, the rows and columns 3 p .. 3 p + 2 of pixel p; a grey
F is diagonal. :class:`BlockDiagonal` holds either and applies it to dense blocks and
to CSR row blocks, from the left or the right. Products with a block-diagonal factor
are O(b nnz): vectorised numpy for dense blocks, numba kernels for CSR row blocks
(:mod:`._block_kernels`: two passes, the output allocated once; scipy's product with
the (n, n) CSR of the blocks and the sort after it took three times as long and held
three copies; the b = 1 cases are the scale kernels of :mod:`.csr`, so a grey F costs
what it always did).
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
        # whole blocks only: the kernels step over rows b at a time and do no bounds checks
        if start % self.b or rows % self.b or not 0 <= start <= start + rows <= self.n:
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
        if self.b != 3:  # no kernel: scipy's product (no colour F is other than 3 x 3)
            local = _block_csr(self.values[start // self.b:(start + r) // self.b], dtype)
            return _canonical(local @ A)
        A = _sorted(A)
        indptr, indices, data = _kernels().scale_rows_blocks_internal(
            A.indptr, A.indices, A.data, np.ascontiguousarray(self.values), start // 3,
            np.dtype(dtype))
        return _csr(indptr, indices, data, A.shape)

    def scale_cols(self, A, negate: bool = False,
                   drop_diagonal_blocks_at: int | None = None) -> sp.csr_array:
        """A times B, A of shape (r, n); shape (r, n), sorted indices, exact zeros
        dropped. ``negate``: -(A B). ``drop_diagonal_blocks_at``: A's first row is this
        global row (a multiple of b), and the entries of the result's b x b diagonal
        blocks are left out (M = -T F^-1 off its diagonal blocks, in one pass)."""
        A = sp.csr_array(A)
        start = drop_diagonal_blocks_at
        if self.b == 1:
            out = scale_cols(A, np.asarray(self.values, dtype=A.dtype))  # a new array
            if negate:
                out.data *= -1
            return out if start is None else off_block_diagonal(out, start, 1)
        if A.shape[1] != self.n:  # the kernels index blocks by column: no bounds checks
            raise ShapeMismatchError(f"a {A.shape[0]}x{A.shape[1]} block does not multiply "
                                     f"a {self.n}x{self.n} block diagonal")
        if start is not None:
            self._check_start(start, A.shape[0])
        if self.b != 3:  # no kernel: scipy's product (no colour F is other than 3 x 3)
            out = _canonical(A @ self.csr(A.dtype))
            if negate:
                out.data *= -1
            return out if start is None else off_block_diagonal(out, start, self.b)
        A = _sorted(A)
        indptr, indices, data = _kernels().scale_cols_blocks_internal(
            A.indptr, A.indices, A.data, np.ascontiguousarray(self.values),
            0 if start is None else start, start is not None, -1.0 if negate else 1.0,
            A.dtype)
        return _csr(indptr, indices, data, A.shape)

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


def _kernels():
    # numba's kernels: compiled (or loaded from cache) on first use, off the import path
    from . import _block_kernels
    return _block_kernels


def _sorted(A: sp.csr_array) -> sp.csr_array:
    """A with sorted, duplicate-free indices (a canonical copy when they are not): the
    kernels find a pixel's b columns adjacent, and the row merge takes one entry per
    column (its output is marked canonical)."""
    if A.has_canonical_format:
        return A
    A = A.copy()
    A.sum_duplicates()
    A.sort_indices()
    return A


def _csr(indptr, indices, data, shape) -> sp.csr_array:
    """A kernel's output as a csr_array: sorted and duplicate-free by construction,
    its row pointers in the indices' dtype (int32 where it holds them: the memory
    plan counts int32 indices)."""
    if indices.dtype == np.int32 and (len(indptr) == 0 or indptr[-1] < 2**31):
        indptr = indptr.astype(np.int32)
    out = sp.csr_array((data, indices, indptr), shape=shape)
    out.has_sorted_indices = True
    out.has_canonical_format = True
    return out


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


def off_block_diagonal(A, start: int, b: int) -> sp.csr_array:
    """The row block A (first row: global row ``start``, a multiple of b) without the
    entries of its b x b diagonal blocks: (i, j) with i // b == j // b are dropped."""
    A = sp.csr_array(A)
    indptr, indices, data = _kernels().off_block_diagonal_internal(
        A.indptr, A.indices, A.data, int(start), int(b))
    out = sp.csr_array((data, indices, indptr.astype(A.indptr.dtype)
                        if indptr[-1] < np.iinfo(A.indptr.dtype).max else indptr),
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
    out = np.zeros((r // b, b, b), dtype=np.result_type(A.dtype, np.float32))
    _kernels().diagonal_blocks_internal(A.indptr, A.indices, A.data, int(start), int(b), out)
    return out
