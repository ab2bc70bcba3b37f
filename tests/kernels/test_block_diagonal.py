"""bigT.kernels.BlockDiagonal and its helpers against dense numpy."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.errors import ShapeMismatchError
from bigT.kernels import BlockDiagonal, diagonal_blocks, off_block_diagonal


def _dense(values):
    values = np.asarray(values)
    return np.diag(values) if values.ndim == 1 else sp.block_diag(list(values)).toarray()


@pytest.fixture(params=[1, 3])
def case(request):
    b = request.param
    rng = np.random.default_rng(b)
    m = 10
    values = rng.standard_normal(m * b) if b == 1 else rng.standard_normal((m, b, b))
    A = sp.random(4 * b, m * b, density=0.3, random_state=rng, format="csr")
    return b, BlockDiagonal(values), _dense(values), A


def test_products_match_dense(case):
    b, B, dense, A = case
    start = 3 * b
    rows = slice(start, start + A.shape[0])  # A: rows 3b:7b of an (mb, mb) matrix
    V = np.random.default_rng(0).standard_normal((A.shape[0], 2))
    np.testing.assert_allclose(B.apply(V, start), dense[rows, rows] @ V, atol=1e-14)
    got = B.scale_rows(A, start)
    np.testing.assert_allclose(got.toarray(), dense[rows, rows] @ A.toarray(), atol=1e-14)
    assert got.has_sorted_indices
    np.testing.assert_allclose(B.scale_cols(A).toarray(), A.toarray() @ dense, atol=1e-14)
    np.testing.assert_array_equal(B.rows(start, start + 2 * b, np.float64).toarray(),
                                  dense[start:start + 2 * b])


def test_block_helpers_match_dense():
    rng = np.random.default_rng(1)
    A = sp.random(9, 30, density=0.5, random_state=rng, format="csr")
    start = 12  # rows 12:21 of a 30 x 30 matrix: pixels 4, 5, 6
    dense = A.toarray()
    want = np.stack([dense[3 * k:3 * k + 3, start + 3 * k:start + 3 * k + 3] for k in range(3)])
    np.testing.assert_array_equal(diagonal_blocks(A, start, 3), want)
    off = dense.copy()
    for k in range(3):
        off[3 * k:3 * k + 3, start + 3 * k:start + 3 * k + 3] = 0
    np.testing.assert_array_equal(off_block_diagonal(A, start, 3).toarray(), off)


def test_rows_must_cover_whole_blocks():
    B = BlockDiagonal(np.ones((4, 3, 3)))
    with pytest.raises(ShapeMismatchError, match="whole 3x3 blocks"):
        B.apply(np.ones((3, 1)), start=1)
    with pytest.raises(ShapeMismatchError, match=r"\(n,\) or \(m, b, b\)"):
        BlockDiagonal(np.ones((4, 3)))
