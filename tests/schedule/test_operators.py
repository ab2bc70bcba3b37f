"""MOperand's mat-vec, through M's cached tile rows and straight from T's (when the
cache has no room), against a dense numpy M = D - T F^-1."""

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.schedule.operators import MOperand, TileCache
from bigT.storage import from_scipy


def _T(n, seed):
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=0.2, random_state=seed).toarray()
    A += np.diag(rng.uniform(1, 2, n) * (1 + A.sum(axis=1)))
    A[5, :] = 0  # a pixel no light reaches: zero row and column
    A[:, 5] = 0
    return A


@pytest.mark.parametrize("zero_diagonal", [True, False])
def test_matvec_from_T_rows_equals_M_rows_and_dense(tmp_path, zero_diagonal):
    n = 40
    A = _T(n, 3)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype="float64")
    active = np.ones(n, bool)
    active[5] = False
    f = np.diag(A).copy() if zero_diagonal else np.diag(A) * 1.3
    finv = np.where(active, 1 / np.where(f == 0, 1, f), 0.0)
    M_dense = np.diag(active.astype(float)) - A * finv[None, :]
    if zero_diagonal:
        np.fill_diagonal(M_dense, 0.0)
    V = np.random.default_rng(1).standard_normal((n, 3))
    via_rows = MOperand(T, finv, active, zero_diagonal, TileCache(1 << 30))
    via_T = MOperand(T, finv, active, zero_diagonal, TileCache(0))
    for i in range(T.grid[0]):
        a, b = T.tile_row_range(i)
        ref = M_dense[a:b] @ V
        np.testing.assert_allclose(via_rows.matvec_row(i, V), ref, atol=1e-12)
        np.testing.assert_allclose(via_T.matvec_row(i, V), ref, atol=1e-12)
    assert via_T.cache.used == 0 and via_rows.cache.used > 0
