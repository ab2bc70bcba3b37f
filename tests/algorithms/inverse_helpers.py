"""Helpers for the engine's tests: small matrices stored with small tiles so the
multi-tile paths run, and dense references computed with numpy only."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bigT.storage import from_scipy, open as open_store

# Paper eq. 34, as printed.
T_PAPER = np.array([
    [1.7713, 0.0213, 0.1835, 0.0675],
    [0.0213, 1.7713, 0.1835, 0.0675],
    [0.1835, 0.1835, 1.7875, 0.0137],
    [0.0675, 0.0675, 0.0137, 1.7550],
])


def dense_stratified(T, n, f=None):
    """Paper eq. 13 evaluated densely: F^-1 sum_{k=0..n} (I - T F^-1)^k, F = diag(f)
    (default diag T)."""
    T = np.asarray(T, dtype=np.float64)
    f = np.diag(T).copy() if f is None else np.asarray(f, dtype=np.float64)
    Finv = np.diag(1.0 / f)
    M = np.eye(len(T)) - T @ Finv
    S = np.zeros_like(T)
    P = np.eye(len(T))
    for _ in range(n + 1):
        S += P
        P = M @ P
    return Finv @ S


def random_dominant(n, density=0.15, seed=0, margin=0.6):
    """A random nonnegative T with a positive diagonal dominating each row and column:
    rho(I - T diag(T)^-1) < 1."""
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=density, random_state=rng, format="csr").toarray()
    np.fill_diagonal(A, 0)
    d = 1.0 + rng.random(n)
    s = np.maximum(A.sum(axis=1), A.sum(axis=0)) + 1e-12
    A = A * (margin * d.min() / s.max())
    return np.diag(d) + A


def store(tmp_path, A, name="T.zarr", tile_size=16, dtype="float64"):
    return from_scipy(sp.csr_array(np.asarray(A)), tmp_path / name, tile_size=tile_size,
                      dtype=dtype)


def dense(path):
    return open_store(path).to_scipy().toarray()
