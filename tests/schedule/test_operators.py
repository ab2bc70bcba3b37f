"""MOperand's mat-vec, through M's cached rows and straight from T's (when the cache
has no room), on T's tile rows and on row blocks finer than them, against a dense
numpy M = D - T F^-1."""

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.schedule.cache import TileCache
from bigT.schedule.operators import MOperand
from bigT.storage import from_scipy


def _T(n, seed):
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=0.2, random_state=seed).toarray()
    A += np.diag(rng.uniform(1, 2, n) * (1 + A.sum(axis=1)))
    A[5, :] = 0  # a pixel no light reaches: zero row and column
    A[:, 5] = 0
    return A


@pytest.mark.parametrize("dtype, atol", [("float64", 1e-12), ("float32", 1e-5)])
@pytest.mark.parametrize("zero_diagonal", [True, False])
def test_matvec_from_T_rows_equals_M_rows_and_dense(tmp_path, zero_diagonal, dtype, atol):
    n = 40
    A = _T(n, 3)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype=dtype)
    A = T.to_scipy().toarray().astype(np.float64)  # the reference sees the stored values
    active = np.ones(n, bool)
    active[5] = False
    f = np.diag(A).copy() if zero_diagonal else np.diag(A) * 1.3
    finv = np.where(active, 1 / np.where(f == 0, 1, f), 0.0)
    M_dense = np.diag(active.astype(float)) - A * finv[None, :]
    if zero_diagonal:
        np.fill_diagonal(M_dense, 0.0)
    V = np.random.default_rng(1).standard_normal((n, 3))
    finv = finv.astype(dtype)
    via_rows = MOperand(T, finv, active, zero_diagonal, TileCache(1 << 30))
    via_T = MOperand(T, finv, active, zero_diagonal, TileCache(0))
    minus_finv_v = -(finv[:, None] * V)
    blocks = [T.tile_row_range(i) for i in range(T.grid[0])] + [(0, 8), (8, 24), (30, 40)]
    for a, b in blocks:
        ref = M_dense[a:b] @ V
        np.testing.assert_allclose(via_rows.matvec_rows(a, b, V), ref, atol=atol)
        np.testing.assert_allclose(via_T.matvec_rows(a, b, V), ref, atol=atol)
        np.testing.assert_allclose(via_T.matvec_rows(a, b, V, minus_finv_v), ref, atol=atol)
        np.testing.assert_allclose(via_rows.rows(a, b).toarray(), M_dense[a:b], atol=atol)
    assert via_T.cache.used == 0 and via_rows.cache.used > 0


def test_m_row_size_estimate_is_what_is_cached(tmp_path):
    """has_room is asked with the size M's row will take (int32 indices even when D is
    added, F != diag T), so a row that fits is kept, not rebuilt every mat-vec."""
    from bigT.schedule.cache import nbytes

    A = _T(40, 4)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype="float32")
    active = np.ones(40, bool)
    active[5] = False  # the unlit pixel: no entry of T, none of D
    finv = np.where(active, 1 / (np.diag(A) * 1.3 + ~active), 0).astype(np.float32)
    M = MOperand(T, finv, active, False, TileCache(1 << 20))
    ranges = [T.tile_row_range(i) for i in range(T.grid[0])]
    for a, b in ranges:
        assert nbytes(M.rows(a, b)) == M.row_bytes(a, b)
        assert M.rows(a, b).indices.dtype == np.int32
    V = np.ones((40, 1))
    misses = M.cache.misses
    for _ in range(3):
        for a, b in ranges:
            M.matvec_rows(a, b, V)
    assert M.cache.misses == misses  # built once, then hits


@pytest.mark.parametrize("cache_bytes", [1 << 30, 0])
def test_largest_entries_of_m_rows_against_dense(tmp_path, cache_bytes):
    """Each row's largest entry of M (0 when none is positive), with M's rows cached or
    built for the call: the engine's test of M = -|M| before the bracket."""
    n = 40
    A = _T(n, 6)
    A[7, 12] = -1e-3  # a negative entry of T: a positive one of M
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype="float32")
    A = T.to_scipy().toarray().astype(np.float64)
    active = np.ones(n, bool)
    active[5] = False
    finv = np.where(active, 1 / np.where(np.diag(A) == 0, 1, np.diag(A)), 0.0)
    M_dense = np.diag(active.astype(float)) - A * finv[None, :]
    np.fill_diagonal(M_dense, 0.0)
    M = MOperand(T, finv.astype(np.float32), active, True, TileCache(cache_bytes))
    got = np.concatenate([M.largest_entries(*T.tile_row_range(i)) for i in range(T.grid[0])])
    want = np.maximum(M_dense.max(axis=1), 0.0)[:, None]
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert got[7, 0] > 0 and np.count_nonzero(got) == 1
