"""The dask wiring: task names, one task per tile row, zero tile pairs never read,
mat-vecs, and the same result on a distributed.Client."""

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.schedule import graph
from bigT.schedule.operators import StoreOperand, TileCache
from bigT.storage import from_scipy


def _dominant(n, seed, density=0.2):
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=density, random_state=rng).toarray()
    np.fill_diagonal(A, 0)
    A *= 0.5 / max(A.sum(0).max(), A.sum(1).max())
    return A + np.eye(n)


def _dense_eq13(T, n):
    Finv = np.diag(1 / np.diag(T))
    M = np.eye(len(T)) - T @ Finv
    return Finv @ sum(np.linalg.matrix_power(M, k) for k in range(n + 1))


def test_task_names_and_one_task_per_row():
    ctx = graph.Context()
    handle = graph.register(ctx)
    try:
        tasks = graph.build_row_tasks("power", lambda c, i: {"i": i}, range(5), ctx, handle,
                                      ("x", 1))
    finally:
        graph.unregister(handle)
    keys = [t.key for t in tasks]
    assert len(set(keys)) == 5
    assert all(k.startswith("power-") for k in keys)
    # deterministic: same op and parts give the same names
    tasks2 = graph.build_row_tasks("power", None, range(5), ctx, handle, ("x", 1))
    assert [t.key for t in tasks2] == keys


def test_run_rows_threads_and_matvec(tmp_path):
    A = _dominant(50, 1)
    S = from_scipy(sp.csr_array(A), tmp_path / "A.zarr", tile_size=16, dtype="float64")
    seen = []
    out = graph.run_rows("probe", lambda ctx, i: seen.append(i) or {"i": i}, range(S.grid[0]),
                         graph.Context(), workers=2)
    assert sorted(seen) == [0, 1, 2, 3] and len(out) == 4
    V = np.random.default_rng(0).standard_normal((50, 3))
    Y = graph.matvec("mv", lambda i, V: S.get_tile_row(i) @ V, S.grid[0], S.tile_row_range, V)
    np.testing.assert_allclose(Y, A @ V, atol=1e-12)


def test_zero_tile_pairs_are_never_read(tmp_path, monkeypatch):
    # block-diagonal T: tile pairs across blocks are zero, and the second block has
    # no interreflection, so P's tile rows there are empty from term 1 on
    A = np.zeros((64, 64))
    A[:32, :32] = _dominant(32, 2, density=0.5)
    A[32:, 32:] = np.diag(1 + np.arange(32) / 32)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype="float64")
    reads = []
    orig = StoreOperand._read_row

    def row(self, j):
        r = orig(self, j)
        reads.append((str(self.store.path), int(j), r.nnz))
        return r

    monkeypatch.setattr(StoreOperand, "_read_row", row)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0, progress=False)
    P_reads = [r for r in reads if r[0].endswith("/P")]
    assert P_reads and all(nnz > 0 for _, _, nnz in P_reads)
    assert {j for _, j, _ in P_reads} <= {0, 1}
    np.testing.assert_allclose(bigT.open(tmp_path / "X.zarr").to_scipy().toarray(),
                               _dense_eq13(A, 3), atol=1e-12)
    assert rep.history[-1].tiles_computed == 4


def test_tile_cache_bounded_and_scan_resistant():
    """Admitted while they fit, kept until dropped: a second scan of the same rows hits
    the first ones (an LRU smaller than the scan would hit none)."""
    c = TileCache(1000)
    for _ in range(2):
        for k in range(20):
            c.get(("p", "row", k), lambda: np.zeros(30))  # 240 bytes each
    assert c.used == 4 * 240
    assert (c.hits, c.misses) == (4, 36)
    c.get(("q", "row", 0), lambda: np.zeros(1))
    c.drop_where(lambda path: path != "q")
    assert c.used == 8
    misses = c.misses
    for k in range(3):
        c.get(("p", "row", k), lambda: np.zeros(30))
    assert c.misses == misses + 3  # dropped entries are recomputed
    c.resize(500)  # the last admitted go first
    assert c.used == 8 + 2 * 240
    c.get(("p", "row", 0), lambda: None)
    c.get(("p", "row", 2), lambda: np.zeros(30))
    assert c.misses == misses + 4


def test_distributed_client_same_result(tmp_path):
    distributed = pytest.importorskip("distributed")
    A = _dominant(48, 3)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype="float64")
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=1e-8, progress=False)
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2,
                            dashboard_address=None) as client:
        bigT.stratified_inverse(T, tmp_path / "Y.zarr", terms=3, prune=1e-8, progress=False,
                                client=client)
    X = bigT.open(tmp_path / "X.zarr").to_scipy().toarray()
    Y = bigT.open(tmp_path / "Y.zarr").to_scipy().toarray()
    np.testing.assert_array_equal(X, Y)
