"""The product kernel's workspaces (each spans n columns: 863 MB at 4K) are let go
when a mat-vec pass starts: its tasks multiply by no stored factor, and the idle
workspaces a product pass left would otherwise sit beside the mat-vec's dense blocks
(the 4K inverse's peak went past a 4 GiB limit that way)."""

import numpy as np
import scipy.sparse as sp

import bigT
from bigT.kernels import csr
from bigT.schedule import worker


def test_a_matvec_pass_lets_the_product_workspaces_go(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    n = 96
    A = sp.random(n, n, density=0.3, random_state=rng).toarray()
    np.fill_diagonal(A, 0)
    A *= 0.5 / A.sum(0).max()
    T = sp.csr_array(np.eye(n) * rng.uniform(0.5, 1.0, n) + A)
    store = bigT.from_scipy(T, tmp_path / "T.zarr", tile_size=32, dtype="float64")
    idle = []  # (idle workspaces before, after) as each mat-vec task of M sets its cache
    budget = worker.TaskContext.cache_budget

    def counted_budget(ctx):
        before = len(csr._WORKSPACES._idle)
        out = budget(ctx)
        if ctx.spec.op == "matvec-M":
            idle.append((before, len(csr._WORKSPACES._idle)))
        return out

    monkeypatch.setattr(worker.TaskContext, "cache_budget", counted_budget)
    bigT.stratified_inverse(store, tmp_path / "X.zarr", terms=3, prune=0.0,
                            in_memory=False, progress=False)
    assert idle, "no mat-vec of M ran"
    assert max(b for b, _ in idle) >= 1, "no product left a workspace idle before a mat-vec"
    assert all(a == 0 for _, a in idle)
    X = bigT.open(tmp_path / "X.zarr").to_scipy().toarray()
    Td = T.toarray()
    Finv = np.diag(1 / np.diag(Td))
    M = np.eye(n) - Td @ Finv
    expected = Finv @ sum(np.linalg.matrix_power(M, k) for k in range(4))
    np.testing.assert_allclose(X, expected, atol=1e-10)
