"""The first-bounce transport F (the preconditioner of paper §4.4) and its recovery
from an inverse (paper eq. 33 / 42)."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import InvalidMatrixError, ShapeMismatchError


@dataclass(frozen=True)
class FirstBounce:
    """F = diag(f) and what the series needs from it.

    Attributes
    ----------
    kind : {"diag", "identity", "vector"}
    f : (n,) float64 ndarray, F's diagonal (0 on excluded pixels)
    finv : (n,) float64 ndarray, 1/f (0 on excluded pixels)
    active : (n,) bool ndarray, pixels kept in the inverse
    excluded : int, pixels left out (their row and column of T are zero: no light
        reaches them, none leaves them)
    digest : str, hash of f, recorded in the inverse's metadata
    """

    kind: str
    f: np.ndarray
    finv: np.ndarray
    active: np.ndarray
    excluded: int
    digest: str

    @property
    def zero_diagonal(self) -> bool:
        """F = diag T: the diagonal of M = D - T F^-1 is exactly zero."""
        return self.kind == "diag"


def _empty_rows_and_cols(T, candidates: np.ndarray) -> np.ndarray:
    """Which of ``candidates`` have an all-zero row and column in T (one streaming pass
    over the tile rows, run only when the diagonal has zeros)."""
    n = T.shape[0]
    row_nz = np.zeros(n, dtype=bool)
    col_nz = np.zeros(n, dtype=bool)
    for i in range(T.grid[0]):
        a, _ = T.tile_row_range(i)
        r = sp.csr_array(T.get_tile_row(i))
        r.eliminate_zeros()
        row_nz[a:a + r.shape[0]] = np.diff(r.indptr) > 0
        col_nz[np.unique(r.indices)] = True
    return candidates[~row_nz[candidates] & ~col_nz[candidates]]


def _refuse_nonpositive(f: np.ndarray, active: np.ndarray, what: str, path) -> None:
    """InvalidMatrixError when F has a negative entry, or a zero one on a pixel that is
    not left out (its row or column of T holds light): counts and first indices."""
    bad = np.flatnonzero(active & (f <= 0))
    if not len(bad):
        return
    neg, zero = bad[f[bad] < 0], bad[f[bad] == 0]
    parts = []
    if len(neg):
        parts.append(f"{len(neg)} negative entries (first at index {neg[0]}, "
                     f"value {f[neg[0]]:.4g})")
    if len(zero):
        parts.append(f"{len(zero)} zero entries on pixels whose row or column is not "
                     f"zero (first at index {zero[0]})")
    raise InvalidMatrixError(
        f"{what} has " + " and ".join(parts) + "; F = diag(T) needs a positive "
        "diagonal: fix the measurement, or pass first_bounce='identity' or a vector", path)


def resolve_first_bounce(T, spec="diag") -> FirstBounce:
    """Turn ``first_bounce=`` into F.

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
    spec : "diag", "identity", (n,) array-like, or path of a ``.npy`` file with one
        (e.g. the result of :func:`recover_first_bounce`).

    Raises
    ------
    InvalidMatrixError
        With ``"diag"``: a negative or NaN diagonal entry, or a zero one on a pixel
        whose row or column is not zero (count and first index given). With a vector:
        a non-finite entry, or one <= 0 on such a pixel.
    ShapeMismatchError
        A vector of the wrong length.
    """
    n = T.shape[0]
    d = np.asarray(T.diagonal(), dtype=np.float64)
    if isinstance(spec, (str, os.PathLike)) and str(spec) not in ("diag", "identity"):
        spec = np.load(os.fspath(spec))
    if isinstance(spec, str):
        kind = spec
        f = d.copy() if kind == "diag" else np.ones(n)
    else:
        kind = "vector"
        f = np.asarray(spec, dtype=np.float64).ravel()
        if f.shape != (n,):
            raise ShapeMismatchError(f"first_bounce has {f.size} entries, T has {n} rows")
        if not np.isfinite(f).all():
            bad = np.flatnonzero(~np.isfinite(f))
            raise InvalidMatrixError(f"first_bounce has {len(bad)} non-finite entries, "
                                     f"the first at index {bad[0]}")
    if np.isnan(d).any():
        bad = np.flatnonzero(np.isnan(d))
        raise InvalidMatrixError(f"T's diagonal has {len(bad)} NaN entries, the first at "
                                 f"index {bad[0]}", getattr(T, "path", None))
    zero_diag = np.flatnonzero(d == 0)
    excluded = _empty_rows_and_cols(T, zero_diag) if len(zero_diag) else zero_diag
    active = np.ones(n, dtype=bool)
    active[excluded] = False
    if kind != "identity":
        _refuse_nonpositive(f, active, "T's diagonal" if kind == "diag" else "first_bounce",
                            getattr(T, "path", None))
    f = np.where(active, f, 0.0)
    finv = np.zeros(n)
    finv[active] = 1.0 / f[active]
    digest = hashlib.sha1(np.ascontiguousarray(f).tobytes()).hexdigest()[:16]
    return FirstBounce(kind, f, finv, active, int(len(excluded)), digest)


def recover_first_bounce(X) -> np.ndarray:
    """The true first bounce of a diffuse scene from an inverse, F_ii = 1 / (T^-1)_ii
    (paper eq. 33; eq. 42 with the stratified inverse T_n^-1).

    Parameters
    ----------
    X : BlockCSR, path of an inverse store, scipy sparse matrix or 2-D ndarray, (n, n)

    Returns
    -------
    (n,) float64 ndarray
        1 / X_ii; 0 where X_ii = 0 (pixels left out of the inverse). Pass it (or a
        ``.npy`` file holding it) as ``first_bounce=`` of a second run.
    """
    if isinstance(X, (str, os.PathLike)):
        from ..schedule._backend import open_store

        X = open_store(X)
    if isinstance(X, np.ndarray):
        d = np.diagonal(X)
    elif sp.issparse(X):
        d = X.diagonal()
    else:
        d = X.diagonal()
    d = np.asarray(d, dtype=np.float64)
    out = np.zeros_like(d)
    nz = d != 0
    out[nz] = 1.0 / d[nz]
    return out
