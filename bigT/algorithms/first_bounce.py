"""The first-bounce transport F (the preconditioner of paper §4.4) and its recovery
from an inverse (paper eq. 33 / 42).

Grey: F is diagonal, held as the vector f. Colour (a store of 3 channels, index
3 p + c): F is block-diagonal, one 3 x 3 colour-mixing block per pixel (with
``first_bounce="diag"``, T's own diagonal blocks), held as the (n/3, 3, 3) blocks and
inverted per pixel, each block's condition number checked
(``config.COLOUR_BLOCK_MAX_CONDITION``). Everything the engine does with F or F^-1
goes through :class:`FirstBounce`'s operations, which cost a grey F what they always
did.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import InvalidMatrixError, ShapeMismatchError, short_reason
from ..kernels import BlockDiagonal, diagonal_blocks
from ..storage import as_store
from ..storage.channel_mixing import mixed_blocks

#: ``first_bounce=`` names: T's diagonal (blocks), the same leaving out the pixels
#: whose colour block is singular or ill-conditioned, and the identity.
NAMED_FIRST_BOUNCES = ("diag", "diag-skip-ill", "identity")


@dataclass(frozen=True)
class FirstBounce:
    """F and what the series needs from it.

    Attributes
    ----------
    kind : {"diag", "diag-skip-ill", "identity", "vector", "blocks"}
        "vector" is a grey F given as an array or file, "blocks" a colour one.
    f : float64 ndarray, F in T's stored order: (n,), its diagonal, for grey; (n/3, 3,
        3), its per-pixel blocks, for colour (0 on excluded pixels)
    finv : float64 ndarray of f's shape, F^-1: 1/f, or each block's inverse (0 on
        excluded pixels)
    active : (n,) bool ndarray, values (pixels, or pixels' channels) kept in the inverse
    excluded : int, pixels left out (their row and column of T are zero: no light
        reaches them, none leaves them; or, asked for, their colour block is
        ill-conditioned)
    digest : str, hash of f, recorded in the inverse's metadata
    ill_conditioned : int, of the excluded pixels, those left out for their colour
        block (``"diag-skip-ill"``)
    smallest_entry : float or None
        T's smallest entry capped at 0 (< 0: T has a negative entry), learned by the
        read that gave T's diagonal when it saw every entry; None when not known
        (:meth:`m_nonpositive`).
    """

    kind: str
    f: np.ndarray
    finv: np.ndarray
    active: np.ndarray
    excluded: int
    digest: str
    ill_conditioned: int = 0
    smallest_entry: float | None = None

    @property
    def m_nonpositive(self) -> bool:
        """Known without reading M that M = D - T F^-1 has no positive entry: grey,
        F = diag T (M's diagonal is dropped, its off-diagonal entries are
        T_ij * (-1/F_jj) with F_jj > 0 on the kept pixels, 0 elsewhere) and T has no
        negative entry. False means not known (M may still have none: the caller
        reads M's rows)."""
        return (self.zero_diagonal and self.channels == 1
                and self.smallest_entry is not None and self.smallest_entry >= 0)

    @property
    def zero_diagonal(self) -> bool:
        """F = diag T (its diagonal blocks, for colour): the diagonal (blocks) of
        M = D - T F^-1 are exactly zero."""
        return self.kind in ("diag", "diag-skip-ill")

    @property
    def channels(self) -> int:
        """F's block size: 1 (grey) or 3 (colour)."""
        return 1 if self.f.ndim == 1 else int(self.f.shape[1])

    @cached_property
    def forward(self) -> BlockDiagonal:
        """F as a :class:`~bigT.kernels.BlockDiagonal`."""
        return BlockDiagonal(self.f)

    @cached_property
    def inverse(self) -> BlockDiagonal:
        """F^-1 as a :class:`~bigT.kernels.BlockDiagonal`."""
        return BlockDiagonal(self.finv)

    def apply(self, V: np.ndarray) -> np.ndarray:
        """F V, V of shape (n, k)."""
        return self.forward.apply(V)

    def apply_inverse(self, V: np.ndarray, start: int = 0, stop: int | None = None
                      ) -> np.ndarray:
        """Rows ``start:stop`` of F^-1 V, V of shape (stop - start, k) (those rows of a
        dense block)."""
        stop = start + V.shape[0] if stop is None else stop
        if stop - start != V.shape[0]:
            raise ShapeMismatchError(f"V has {V.shape[0]} rows for rows {start}:{stop}")
        return self.inverse.apply(V, start)

    def scale_rows(self, S, start: int, dtype=None) -> sp.csr_array:
        """F^-1 S for the row block S (rows ``start:start + r`` of an (n, m) matrix),
        in ``dtype`` (S's by default)."""
        return self.inverse.scale_rows(S, start, dtype)

    def scale_cols(self, S) -> sp.csr_array:
        """S F^-1, S of shape (r, n)."""
        return self.inverse.scale_cols(S)

    def inverse_rows(self, start: int, stop: int, dtype) -> sp.csr_array:
        """Rows ``start:stop`` of F^-1, CSR (stop - start, n), global columns."""
        return self.inverse.rows(start, stop, dtype)


def _empty_rows_and_cols(T, candidates: np.ndarray, rows=None) -> np.ndarray:
    """Which of ``candidates`` have an all-zero row and column in T (one streaming pass
    over the tile rows, ``rows`` where they are held, run only when the diagonal has
    zeros)."""
    n = T.shape[0]
    row_nz = np.zeros(n, dtype=bool)
    col_nz = np.zeros(n, dtype=bool)
    for i in range(T.grid[0]):
        a, _ = T.tile_row_range(i)
        # a copy: eliminate_zeros works in place, and a held row becomes M's
        r = sp.csr_array(T.get_tile_row(i) if rows is None else rows[i], copy=True)
        r.eliminate_zeros()
        row_nz[a:a + r.shape[0]] = np.diff(r.indptr) > 0
        col_nz[np.unique(r.indices)] = True
    return candidates[~row_nz[candidates] & ~col_nz[candidates]]


def _pixel_namer(T):
    """``i -> "index 7"`` for a row of T in its stored order, or ``"pixel (y, x)"`` where
    the store numbers pixels in another order than the row-major one users see. The
    order's permutation (a sort of every pixel: 0.3 s at full HD) is made only when an
    error names a pixel."""
    def name(i) -> str:
        order = getattr(T, "pixel_order", None)
        if order is None or np.array_equal(order.permutation, np.arange(order.n)):
            return f"index {i}"
        return "pixel (%d, %d)" % divmod(int(order.permutation[i]), order.image_shape[1])

    return name


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
    """Turn ``first_bounce=`` into F (:func:`first_bounce_of_rows`, T's entries read
    from its store).

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
    spec : "diag", "diag-skip-ill", "identity", an array, or path of a ``.npy`` file
        with one (e.g. the result of :func:`recover_first_bounce`). For a grey T an
        (n,) vector, for a colour T (``T.channels == 3``) the (n/3, 3, 3) blocks; either
        indexed by pixel in row-major image order (an (H, W) image raveled), as the
        public API speaks, and permuted into T's stored order here. For colour,
        "diag" is T's 3x3 diagonal blocks, each pixel's colour mixing, inverted per
        pixel; "diag-skip-ill" the same, but a pixel whose block is singular or
        ill-conditioned is left out of the inverse like an unlit pixel instead of
        refused. For grey (1x1 blocks, always well-conditioned) it is "diag".

    Returns
    -------
    FirstBounce
        Its vectors in T's stored (matrix) order, as the engine uses them.

    Raises
    ------
    InvalidMatrixError
        With ``"diag"``: a negative or NaN diagonal entry, or a zero one on a pixel
        whose row or column is not zero (count and first index given). With a vector:
        a non-finite entry, or one <= 0 on such a pixel. Colour: a block with a NaN
        (or, given, non-finite) entry, or a lit pixel whose block's condition number
        exceeds ``config.COLOUR_BLOCK_MAX_CONDITION`` (singular: infinite), naming the
        pixel and its condition number (unless ``"diag-skip-ill"``).
    ShapeMismatchError
        A vector (or blocks) of the wrong shape.
    """
    return first_bounce_of_rows(T, spec, None)


def first_bounce_of_rows(T, spec, rows, keep=None) -> FirstBounce:
    """:func:`resolve_first_bounce`, T's diagonal (blocks) and, where the diagonal has
    zeros, its empty rows and columns taken from ``rows`` when given: T's tile rows
    already read (``rows[i]`` is ``T.get_tile_row(i)``, read on first use; the
    in-memory path makes M from the same rows), else read from T's store (its diagonal
    tiles, for the diagonal). The same F either way; a ``spec`` file is loaded first, so
    that its errors come before T is read. ``keep(i, row)`` is handed the tile rows
    read whole from the store (:meth:`bigT.storage.BlockCSR.diagonal_scan`)."""
    n = T.shape[0]
    source = None  # the --first-bounce file, named in the errors about its vector
    if isinstance(spec, (str, os.PathLike)) and str(spec) not in NAMED_FIRST_BOUNCES:
        source = os.fspath(spec)
        spec = load_first_bounce(source)
    if getattr(T, "channels", 1) != 1:
        return _resolve_colour(T, spec, source, rows)
    d, smallest = _diagonal_and_smallest(T, rows, keep)
    d = np.asarray(d, dtype=np.float64)
    if isinstance(spec, str):
        kind = spec
        f = d.copy() if kind != "identity" else np.ones(n)
    else:
        kind = "vector"
        f = _stored_order(T, _as_vector(spec, n, source))
    name = _pixel_namer(T)
    if np.isnan(d).any():
        bad = np.flatnonzero(np.isnan(d))
        raise InvalidMatrixError(f"T's diagonal has {len(bad)} NaN entries, the first at "
                                 f"{name(bad[0])}", getattr(T, "path", None))
    zero_diag = np.flatnonzero(d == 0)
    excluded = _empty_rows_and_cols(T, zero_diag, rows) if len(zero_diag) else zero_diag
    active = np.ones(n, dtype=bool)
    active[excluded] = False
    what, where = (("T's diagonal", getattr(T, "path", None)) if kind != "vector"
                   else ("first_bounce", source))
    if kind != "identity":
        _refuse_nonpositive(f, active, what, where, name)
        _check_reciprocal(f, active, getattr(T, "dtype", np.float64), what, where, name)
    f = np.where(active, f, 0.0)
    finv = np.zeros(n)
    finv[active] = 1.0 / f[active]
    digest = hashlib.sha1(np.ascontiguousarray(f).tobytes()).hexdigest()[:16]
    return FirstBounce(kind, f, finv, active, int(len(excluded)), digest,
                       smallest_entry=smallest)


def _diagonal_and_smallest(T, rows, keep=None) -> tuple[np.ndarray, float | None]:
    """T's main diagonal in its stored order, shape (min(shape),), and its smallest
    entry capped at 0 where the read saw every entry (else None): from T's store
    (:meth:`bigT.storage.BlockCSR.diagonal_scan`, which hands ``keep`` the tile rows
    it read whole), or from its tile rows ``rows``."""
    if rows is not None:
        return _diagonal_of_rows(T, rows)
    scan = getattr(T, "diagonal_scan", None)
    if scan is None:  # a store-like T without the scan: its diagonal only
        return T.diagonal(output_order="matrix"), None
    found = scan(output_order="matrix", keep=keep)
    return found.diagonal, found.smallest


def _diagonal_of_rows(T, rows) -> tuple[np.ndarray, float | None]:
    """T's main diagonal in its stored order, shape (min(shape),), T's dtype, from its
    tile rows ``rows`` (global columns): what ``T.diagonal(output_order="matrix")``
    reads from the store; and the smallest entry of those rows capped at 0, None
    where rows were left unseen (more rows than columns)."""
    n = min(T.shape)
    out = np.zeros(n, dtype=T.dtype)
    smallest = 0.0
    for i in range(T.grid[0]):
        start, _ = T.tile_row_range(i)
        if start >= n:
            break
        row = rows[i]
        d = row.diagonal(k=start)  # entries (r, start + r)
        out[start:start + d.size] = d
        smallest = min(smallest, float(row.data[:row.indptr[-1]].min(initial=0.0)))
    every_row = T.shape[0] <= T.shape[1]  # else the rows below min(shape) were not seen
    return out, (smallest if every_row else None)


def _resolve_colour(T, spec, source, rows=None) -> FirstBounce:
    """:func:`resolve_first_bounce` for a colour T (3 channels): F block-diagonal, one
    3x3 block per pixel, inverted per pixel after its condition number is checked
    (T's diagonal blocks from its tile rows ``rows`` when given)."""
    b = int(T.channels)
    m = T.shape[0] // b
    path = getattr(T, "path", None)
    d = stored_diagonal_blocks(T, rows)
    if np.isnan(d).any():
        p = int(np.flatnonzero(np.isnan(d).any(axis=(1, 2)))[0])
        raise InvalidMatrixError(f"T's diagonal blocks hold NaN entries, the first at "
                                 f"{_pixel_name(T, p)}", path)
    if isinstance(spec, str):
        kind = spec
        F = d.copy() if kind != "identity" else np.broadcast_to(np.eye(b), (m, b, b)).copy()
    else:
        kind = "blocks"
        F = _as_blocks(spec, m, b, source)
        order = getattr(T, "pixel_order", None)
        F = F if order is None else F[order.pixel_permutation]
    lit = _lit_pixels(T, d, b, rows)
    ill = np.zeros(m, dtype=bool)
    if kind != "identity":
        cond = np.full(m, np.inf)
        with np.errstate(all="ignore"):  # a singular block: cond is inf (or ~1e16)
            cond[lit] = np.linalg.cond(F[lit])
        ill = lit & ~(cond <= config.COLOUR_BLOCK_MAX_CONDITION)
        if ill.any() and kind != "diag-skip-ill":
            _refuse_ill_conditioned(T, ill, cond, "first_bounce" if kind == "blocks"
                                    else "T's diagonal block", source if kind == "blocks"
                                    else path)
    active_pixels = lit & ~ill
    F[~active_pixels] = 0.0
    Finv = np.zeros_like(F)
    Finv[active_pixels] = np.linalg.inv(F[active_pixels])
    digest = hashlib.sha1(np.ascontiguousarray(F).tobytes()).hexdigest()[:16]
    return FirstBounce(kind, F, Finv, np.repeat(active_pixels, b),
                       int(m - active_pixels.sum()), digest, int(ill.sum()))


def _lit_pixels(T, d: np.ndarray, b: int, rows=None) -> np.ndarray:
    """(m,) bool: the pixels kept; a pixel whose diagonal block is zero and whose b rows
    and b columns of T are all zero is unlit (left out, as a grey zero diagonal is)."""
    zero = np.flatnonzero(~d.any(axis=(1, 2)))
    lit = np.ones(len(d), dtype=bool)
    if len(zero):
        values = (b * zero[:, None] + np.arange(b)).ravel()
        empty = np.zeros(T.shape[0], dtype=bool)
        empty[_empty_rows_and_cols(T, values, rows)] = True
        lit[zero[empty[values].reshape(-1, b).all(axis=1)]] = False
    return lit


def _refuse_ill_conditioned(T, ill: np.ndarray, cond: np.ndarray, what: str, path) -> None:
    """InvalidMatrixError naming the first ill-conditioned pixel, its condition number
    and how many there are, on one line."""
    p = int(np.flatnonzero(ill)[0])
    c = "inf (singular)" if not np.isfinite(cond[p]) or cond[p] > 1e15 else f"{cond[p]:.3g}"
    raise InvalidMatrixError(
        f"{what} of {_pixel_name(T, p)} has condition number {c} (limit "
        f"{config.COLOUR_BLOCK_MAX_CONDITION:g}; {int(ill.sum())} pixels above it): the "
        "camera cannot tell its channels apart; fix the measurement or pass {option} to "
        "leave such pixels out", path, option=("first_bounce", "diag-skip-ill"))


def _pixel_name(T, p: int) -> str:
    """``"pixel (y, x)"`` of the pixel numbered ``p`` in T's stored order."""
    order = getattr(T, "pixel_order", None)
    if order is None:
        return f"pixel {p}"
    return "pixel (%d, %d)" % divmod(int(order.pixel_permutation[p]), order.image_shape[1])


def stored_diagonal_blocks(A, rows=None) -> np.ndarray:
    """The b x b diagonal blocks of a colour store A (b = ``A.channels``), (n/b, b, b)
    float64 in A's stored order, from its diagonal tiles only (a tile size that is a
    multiple of b keeps every block inside one), or from its tile rows ``rows``
    (``rows[i]`` is ``A.get_tile_row(i)``) when given; of the matrix A represents,
    L S_pp R, for a factored store (``A.mixing``)."""
    b = int(A.channels)
    out = np.zeros((A.shape[0] // b, b, b))
    for i in range(min(A.grid)):
        a, stop = A.tile_row_range(i)
        # a tile row holds global columns: its blocks start at its first row's pixel
        out[a // b:stop // b] = (diagonal_blocks(A.get_tile(i, i), 0, b) if rows is None
                                 else diagonal_blocks(rows[i], a, b))
    return mixed_blocks(getattr(A, "mixing", None), out)


def _as_blocks(spec, m: int, b: int, source) -> np.ndarray:
    """``spec`` as (m, b, b) float64 blocks of finite numbers; errors name ``source``."""
    try:
        F = np.array(spec, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidMatrixError("first_bounce must hold real numbers", source) from None
    if F.shape != (m, b, b):
        raise ShapeMismatchError(f"first_bounce of a colour T ({b} channels) takes one "
                                 f"{b}x{b} block per pixel, shape ({m}, {b}, {b}); got "
                                 f"{F.shape}", source)
    if not np.isfinite(F).all():
        bad = np.flatnonzero(~np.isfinite(F).all(axis=(1, 2)))
        raise InvalidMatrixError(f"first_bounce has {len(bad)} blocks with non-finite "
                                 f"entries, the first of pixel {bad[0]}", source)
    return F


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
    (n,) float64 ndarray, or (n/3, 3, 3) for a colour store
        1 / X_ii; 0 where X_ii = 0 (pixels left out of the inverse). For a colour
        store (3 channels), the inverse of each pixel's 3x3 diagonal block of X (eq. 33
        generalised), pixel by pixel in ``output_order``; an all-zero block (a pixel
        left out) gives 0. Pass it (or a ``.npy`` file holding it) as
        ``first_bounce=`` of a second run.

    Raises
    ------
    InvalidMatrixError
        A colour block of X that is singular but not zero, naming the pixel.
    """
    if isinstance(X, (str, os.PathLike)):
        X = as_store(X, "X")
    if getattr(X, "channels", 1) != 1:
        return _recover_blocks(X, output_order)
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


def _recover_blocks(X, output_order: str) -> np.ndarray:
    """:func:`recover_first_bounce` of a colour store: (n/3, 3, 3) inverses of X's
    diagonal blocks, in ``output_order``."""
    if output_order not in ("row-major", "matrix"):
        raise ValueError(f"output_order must be 'row-major' or 'matrix', got "
                         f"{output_order!r:.60}")
    d = stored_diagonal_blocks(X)
    held = d.any(axis=(1, 2))
    out = np.zeros_like(d)
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(d[held]) if held.any() else np.zeros(0)
    singular = np.flatnonzero(held)[~(cond < 1 / np.finfo(np.float64).eps)]
    if len(singular):
        raise InvalidMatrixError(f"X's 3x3 diagonal block of {_pixel_name(X, singular[0])} "
                                 f"is singular ({len(singular)} such pixels): no first "
                                 "bounce inverts to it", getattr(X, "path", None))
    out[held] = np.linalg.inv(d[held])
    order = getattr(X, "pixel_order", None)
    if output_order == "matrix" or order is None:
        return out
    return out[np.argsort(order.pixel_permutation)]
