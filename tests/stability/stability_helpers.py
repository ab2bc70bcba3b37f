"""Helpers of the stability suite: transports with a known spectral radius, the engine
run term by term, and dense numpy references that share no code with bigT.

Conventions: T = (I + N) F with N >= 0 (zero diagonal) and F = diag(f) > 0, so that
diag(T) = f, the first bounce bigT takes is F, and M = I - T F^-1 = -N exactly (up to
rounding): rho(M) = rho(N), set by construction. The error of T_k^-1 is then
F^-1 (-N)^(k+1) (I + N)^-1 and its residual I - T T_k^-1 = (-N)^(k+1) (the paper's
alternating, "oscillatory" convergence).
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import scipy.sparse as sp

import bigT

#: Unit roundoff of each float type (half an ulp of 1).
UNIT = {"float32": float(np.finfo(np.float32).eps) / 2,
        "float64": float(np.finfo(np.float64).eps) / 2}


# --- scratch space ---------------------------------------------------------------------

@contextlib.contextmanager
def scratch_dir():
    """A fresh directory, removed afterwards; usable inside hypothesis examples, where
    function-scoped fixtures are not.

    The suite checks numbers, not durability, so it is made on tmpfs (``/dev/shm``)
    when there is one: there the engine's fsyncs and renames cost nothing, which makes
    a series term several times faster than on disk (the suite runs hundreds).
    """
    shm = "/dev/shm"
    base = shm if os.path.isdir(shm) and os.access(shm, os.W_OK) else None
    path = Path(tempfile.mkdtemp(prefix="bigT-stability-", dir=base))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


# --- matrices --------------------------------------------------------------------------

def perron_matrix(n: int, rho: float, seed: int, density: float = 1.0) -> np.ndarray:
    """A nonnegative (n, n) N with zero diagonal and spectral radius exactly ``rho``
    (its Perron root, made so by scaling).

    Parameters
    ----------
    n : int
    rho : float >= 0
    seed : int
    density : float, fraction of off-diagonal entries kept (the rest are zero)

    Returns
    -------
    ndarray, shape (n, n), float64
    """
    rng = np.random.default_rng(seed)
    N = rng.uniform(0.1, 1.0, (n, n)) * (rng.random((n, n)) < density)
    np.fill_diagonal(N, 0.0)
    # a ring keeps N irreducible whatever the density, so its Perron root is positive
    N[np.arange(n), (np.arange(n) + 1) % n] += 0.5
    return N * (rho / spectral_radius(N)) if rho else np.zeros((n, n))


def bipartite_matrix(n: int, rho: float, seed: int) -> np.ndarray:
    """Two walls that only see each other: N = [[0, B], [B^T, 0]], whose spectrum holds
    the pair +-rho, so I + N (hence T) is near singular when rho is close to 1."""
    half = n // 2
    B = np.random.default_rng(seed).uniform(0.1, 1.0, (half, n - half))
    N = np.zeros((n, n))
    N[:half, half:] = B
    N[half:, :half] = B.T
    return N * (rho / spectral_radius(N))


def mixed_sign_matrix(n: int, rho: float, seed: int, density: float = 0.03) -> np.ndarray:
    """A sparse random N with entries of both signs and zero diagonal, scaled to radius
    ``rho``: its eigenvalues fill a disc (the circular law), so dozens sit near the
    top, complex ones included, the hardest case for an eigenvalue estimator. (M = -N
    then holds positive entries: not a physical transport, a stress test.)"""
    rng = np.random.default_rng(seed)
    N = rng.uniform(-1.0, 1.0, (n, n)) * (rng.random((n, n)) < density)
    np.fill_diagonal(N, 0.0)
    return N * (rho / spectral_radius(N))


def first_bounce(n: int, seed: int, low: float = 0.5, high: float = 2.0) -> np.ndarray:
    """A positive first-bounce diagonal f (albedo times irradiance, say)."""
    return np.random.default_rng(seed + 10_000).uniform(low, high, n)


def transport(N: np.ndarray, f: np.ndarray) -> np.ndarray:
    """T = (I + N) diag(f): diag(T) = f and M = I - T F^-1 = -N."""
    return (np.eye(len(f)) + N) * f[None, :]


def spectral_radius(A: np.ndarray) -> float:
    """max |lambda| of a dense matrix (numpy's eigvals, independent of bigT)."""
    return float(np.abs(np.linalg.eigvals(A)).max())


def measured_transport(T: np.ndarray, noise: np.ndarray, sigma: float,
                       floor: float = 2.0) -> np.ndarray:
    """T as a capture gives it: T + black level + noise, minus the black level.

    Parameters
    ----------
    T : ndarray, (n, n), the true transport
    noise : ndarray, (n, n), a standard normal pattern
    sigma : float, noise level, relative to the mean first bounce
    floor : float, off-diagonal entries under ``floor`` noise deviations are dropped
        (the noise floor; the diagonal, bright, is always kept)

    Returns
    -------
    ndarray, (n, n): the noise is left as it is, negative wherever T is about zero;
    the floor also drops the faintest true interreflections.
    """
    scale = sigma * float(np.diag(T).mean())
    Tm = T + scale * noise
    off = ~np.eye(len(T), dtype=bool)
    Tm[off & (np.abs(Tm) < floor * scale)] = 0.0
    return Tm


# --- dense references ------------------------------------------------------------------

def power_form(T: np.ndarray, n: int, f: np.ndarray | None = None) -> np.ndarray:
    """Paper eq. 13: F^-1 sum_{k=0..n} (I - T F^-1)^k, F = diag(f) (default diag T)."""
    f = np.diag(T).copy() if f is None else f
    M = np.eye(len(T)) - T / f[None, :]
    S, P = np.zeros_like(M), np.eye(len(T))
    for _ in range(n + 1):
        S, P = S + P, M @ P
    return S / f[:, None]


def binomial_form(T: np.ndarray, n: int, f: np.ndarray | None = None) -> np.ndarray:
    """Paper eq. 14: F^-1 sum_{l=0..n} C(n+1, l+1) (-T F^-1)^l."""
    f = np.diag(T).copy() if f is None else f
    G = -T / f[None, :]
    S, P = np.zeros_like(G), np.eye(len(T))
    for l in range(n + 1):
        S, P = S + math.comb(n + 1, l + 1) * P, G @ P
    return S / f[:, None]


def relative_error(X: np.ndarray, X_exact: np.ndarray) -> float:
    """||X - X_exact||_F / ||X_exact||_F, in float64."""
    X_exact = np.asarray(X_exact, np.float64)
    return float(np.linalg.norm(np.asarray(X, np.float64) - X_exact) / np.linalg.norm(X_exact))


def relative_residual(T: np.ndarray, X: np.ndarray) -> float:
    """||I - T X||_F / sqrt(n): the quantity bigT's residual estimate and ``tol`` use."""
    n = len(T)
    R = np.eye(n) - np.asarray(T, np.float64) @ np.asarray(X, np.float64)
    return float(np.linalg.norm(R) / math.sqrt(n))


def fitted_rate(errors) -> float:
    """The geometric rate q of errors ~ C q^k: exp of the least-squares slope of
    log(error) against k (k = 0, 1, ... over the values given)."""
    e = np.log(np.asarray(errors, np.float64))
    return float(math.exp(np.polyfit(np.arange(len(e)), e, 1)[0]))


# --- stores and runs -------------------------------------------------------------------

def write_store(A, path: Path, dtype: str = "float64", tile_size: int = 16,
                image_shape=None) -> "bigT.BlockCSR":
    """A bigT store of the dense or sparse matrix ``A`` (explicit zeros dropped)."""
    A = sp.csr_array(np.asarray(A) if not sp.issparse(A) else A)
    A.eliminate_zeros()
    return bigT.from_scipy(A, path, tile_size=tile_size, dtype=dtype, image_shape=image_shape)


def read_dense(path) -> np.ndarray:
    """The stored matrix, dense, in its own dtype."""
    return bigT.open(path).to_scipy().toarray()


def invert(T, out: Path, terms: int, **kw):
    """One call of the engine, quiet and unpruned unless told."""
    kw.setdefault("prune", 0.0)
    return bigT.stratified_inverse(T, out, terms=terms, progress=False, **kw)


def term_by_term(T, out: Path, terms: int, **kw):
    """Every term 0..terms of one inverse store, by extending it one term per call (the
    engine resumes from the term it holds).

    Returns
    -------
    reports : list of InverseReport, one per term
    Xs : list of ndarray, X_k dense in the store's dtype
    """
    reports, Xs = [], []
    for k in range(terms + 1):
        reports.append(invert(T, out, k, **kw))
        Xs.append(read_dense(out))
    return reports, Xs
