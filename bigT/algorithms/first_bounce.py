"""The first-bounce transport F (the preconditioner of paper §4.4) and its recovery
from an inverse (paper eq. 33 / 42)."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import InvalidMatrixError, ShapeMismatchError, short_reason
from ..storage import as_store


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


def _pixel_namer(T):
    """``i -> "index 7"`` for a row of T in its stored order, or ``"pixel (y, x)"`` where
    the store numbers pixels in another order than the row-major one users see."""
    order = getattr(T, "pixel_order", None)
    if order is None or np.array_equal(order.permutation, np.arange(order.n)):
        return lambda i: f"index {i}"
    W = order.image_shape[1]
    return lambda i: "pixel (%d, %d)" % divmod(int(order.permutation[i]), W)


def _refuse_nonpositive(f: np.ndarray, active: np.ndarray, what: str, path,
                        name=lambda i: f"index {i}") -> None:
    """InvalidMatrixError when F has a negative entry, or a zero one on a pixel that is
    not left out (its row or column of T holds light): counts and first pixels
    (``name`` spells a stored row)."""
    bad = np.flatnonzero(active & (f <= 0))
    if not len(bad):
        return
    neg, zero = bad[f[bad] < 0], bad[f[bad] == 0]
    parts = []
    if len(neg):
        parts.append(f"{len(neg)} negative entries (first at {name(neg[0])}, "
                     f"value {f[neg[0]]:.4g})")
    if len(zero):
        parts.append(f"{len(zero)} zero entries on pixels whose row or column is not "
                     f"zero (first at {name(zero[0])})")
    raise InvalidMatrixError(
        f"{what} has " + " and ".join(parts) + "; F = diag(T) needs a positive "
        "diagonal: fix the measurement, or pass {option} or a vector", path,
        option=("first_bounce", "identity"))


def load_first_bounce(path) -> np.ndarray:
    """The vector of a ``--first-bounce`` file: a ``.npy`` of real numbers.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    ndarray
        As stored (any shape; the caller checks the length).

    Raises
    ------
    InvalidMatrixError
        A missing, truncated or garbage file, a ``.npz`` archive, pickled objects, or
        values that are not real numbers (strings, complex); the message names the file.
    """
    try:
        f = np.load(os.fspath(path), allow_pickle=False)
    except FileNotFoundError:
        raise InvalidMatrixError("no such file (first_bounce needs a .npy vector)",
                                 path) from None
    except Exception as exc:  # numpy raises ValueError, EOFError, OSError... on garbage
        raise InvalidMatrixError(f"cannot read as a .npy vector ({short_reason(exc, path)})",
                                 path) from None
    if not isinstance(f, np.ndarray):  # np.load opens a .npz as an archive of arrays
        f.close()
        raise InvalidMatrixError("is a .npz archive; first_bounce takes a .npy file "
                                 "holding one vector (numpy.save)", path)
    if f.dtype.kind not in "biuf":
        raise InvalidMatrixError(f"holds values of dtype {f.dtype}, not real numbers", path)
    return f


def _check_reciprocal(f: np.ndarray, active: np.ndarray, dtype, what: str, path,
                      name=lambda i: f"index {i}") -> None:
    """InvalidMatrixError when 1/f overflows ``dtype`` (an entry below 1/max: a
    subnormal float32 diagonal, for one): F^-1 would hold Inf."""
    dtype = np.dtype(dtype) if np.dtype(dtype).kind == "f" else np.dtype(np.float64)
    small = np.flatnonzero(active & (np.abs(f) < 1.0 / np.finfo(dtype).max) & (f != 0))
    if len(small):
        i = small[0]
        wider = "" if dtype == np.float64 else " or store it as float64"
        raise InvalidMatrixError(
            f"{what} has {len(small)} entries too small for {dtype.name} (first at "
            f"{name(i)}, value {f[i]:.3g}): F^-1 = 1/{what} overflows; scale T (its inverse "
            f"scales exactly){wider}", path)


def resolve_first_bounce(T, spec="diag") -> FirstBounce:
    """Turn ``first_bounce=`` into F.

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
    spec : "diag", "identity", (n,) array-like, or path of a ``.npy`` file with one
        (e.g. the result of :func:`recover_first_bounce`). A vector is indexed by pixel
        in row-major image order (an (H, W) image raveled), as the public API speaks;
        it is permuted into T's stored order here.

    Returns
    -------
    FirstBounce
        Its vectors in T's stored (matrix) order, as the engine uses them.

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
    d = np.asarray(T.diagonal(output_order="matrix"), dtype=np.float64)
    source = None  # the --first-bounce file, named in the errors about its vector
    if isinstance(spec, (str, os.PathLike)) and str(spec) not in ("diag", "identity"):
        source = os.fspath(spec)
        spec = load_first_bounce(source)
    if isinstance(spec, str):
        kind = spec
        f = d.copy() if kind == "diag" else np.ones(n)
    else:
        kind = "vector"
        f = _stored_order(T, _as_vector(spec, n, source))
    name = _pixel_namer(T)
    if np.isnan(d).any():
        bad = np.flatnonzero(np.isnan(d))
        raise InvalidMatrixError(f"T's diagonal has {len(bad)} NaN entries, the first at "
                                 f"{name(bad[0])}", getattr(T, "path", None))
    zero_diag = np.flatnonzero(d == 0)
    excluded = _empty_rows_and_cols(T, zero_diag) if len(zero_diag) else zero_diag
    active = np.ones(n, dtype=bool)
    active[excluded] = False
    what, where = (("T's diagonal", getattr(T, "path", None)) if kind == "diag"
                   else ("first_bounce", source))
    if kind != "identity":
        _refuse_nonpositive(f, active, what, where, name)
        _check_reciprocal(f, active, getattr(T, "dtype", np.float64), what, where, name)
    f = np.where(active, f, 0.0)
    finv = np.zeros(n)
    finv[active] = 1.0 / f[active]
    digest = hashlib.sha1(np.ascontiguousarray(f).tobytes()).hexdigest()[:16]
    return FirstBounce(kind, f, finv, active, int(len(excluded)), digest)


def _stored_order(T, f: np.ndarray) -> np.ndarray:
    """The row-major per-pixel vector ``f`` in T's stored order (as it is when T records
    no pixel order)."""
    order = getattr(T, "pixel_order", None)
    return f if order is None else f[order.permutation]


def _as_vector(spec, n: int, source) -> np.ndarray:
    """``spec`` as an (n,) float64 vector of finite numbers; errors name ``source`` (the
    file it was read from, None for an array)."""
    try:
        f = np.asarray(spec, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise InvalidMatrixError("first_bounce must hold real numbers", source) from None
    if f.shape != (n,):
        raise ShapeMismatchError(f"first_bounce has {f.size} entries, T has {n} rows",
                                 source)
    if not np.isfinite(f).all():
        bad = np.flatnonzero(~np.isfinite(f))
        raise InvalidMatrixError(f"first_bounce has {len(bad)} non-finite entries, "
                                 f"the first at index {bad[0]}", source)
    return f


def recover_first_bounce(X, output_order: str = "row-major") -> np.ndarray:
    """The true first bounce of a diffuse scene from an inverse, F_ii = 1 / (T^-1)_ii
    (paper eq. 33; eq. 42 with the stratified inverse T_n^-1).

    Parameters
    ----------
    X : BlockCSR, path of an inverse store, scipy sparse matrix or 2-D ndarray, (n, n)
    output_order : {"row-major", "matrix"}
        Of a store's pixels (:meth:`BlockCSR.diagonal`): row-major image order by
        default (``F.reshape(H, W)`` is an image), ``"matrix"`` for the stored order. A
        scipy matrix or an ndarray has no pixel order: its own numbering.

    Returns
    -------
    (n,) float64 ndarray
        1 / X_ii; 0 where X_ii = 0 (pixels left out of the inverse). Pass it (or a
        ``.npy`` file holding it) as ``first_bounce=`` of a second run.
    """
    if isinstance(X, (str, os.PathLike)):
        X = as_store(X, "X")
    if isinstance(X, np.ndarray):
        d = np.diagonal(X)
    elif sp.issparse(X):
        d = X.diagonal()
    else:
        d = X.diagonal(output_order=output_order)
    d = np.asarray(d, dtype=np.float64)
    out = np.zeros_like(d)
    nz = d != 0
    out[nz] = 1.0 / d[nz]
    return out
