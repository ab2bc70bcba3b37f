"""Pruning error within the bound derived in docs/DESIGN.md ("Pruning"):
||X_n - T_n^-1||_inf <= ||F^-1||_inf prune sum_{k=1..n} sum_{l=1..k} ||M||_inf^(k-l) r_l,
with r_l <= n_cols entries dropped per row at term l."""

import numpy as np
import pytest

import bigT

from inverse_helpers import dense, dense_stratified, random_dominant


@pytest.mark.parametrize("prune", [1e-4, 1e-3])
def test_pruned_power_within_bound(tmp_path, make_store, prune):
    A = random_dominant(96, seed=11, density=0.25, margin=0.8)
    T = make_store(A, tile_size=32)
    n_terms = 5
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=n_terms, prune=prune,
                                  progress=False)
    exact = dense_stratified(A, n_terms)
    X = dense(tmp_path / "X.zarr")
    err = np.abs(X - exact).sum(axis=1).max()
    d = np.diag(A)
    M = np.eye(len(A)) - A / d[None, :]
    m = np.abs(M).sum(axis=1).max()
    r = len(A)
    bound = (1 / d).max() * prune * sum(sum(m ** (k - l) * r for l in range(1, k + 1))
                                        for k in range(1, n_terms + 1))
    assert 0 < err <= bound
    assert np.count_nonzero(X) < np.count_nonzero(exact)  # pruning did drop entries
    assert rep.history[-1].nnz_X == np.count_nonzero(X)


def test_pruned_methods_agree_roughly(tmp_path, make_store):
    A = random_dominant(64, seed=12, density=0.3)
    T = make_store(A, tile_size=16)
    exact = dense_stratified(A, 4)
    errs = {}
    for method in ("power", "horner"):
        bigT.stratified_inverse(T, tmp_path / f"{method}.zarr", terms=4, prune=1e-4,
                                method=method, progress=False)
        errs[method] = np.abs(dense(tmp_path / f"{method}.zarr") - exact).max()
    assert max(errs.values()) < 1e-2
