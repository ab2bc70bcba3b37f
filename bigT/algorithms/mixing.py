"""Global colour mixing: is a colour T three grey transports between two 3x3 mixings?

When the rig's colour mixing is the same for every pixel (Chen et al., PROCAMS 2008),

    T[3p+i, 3q+j] = sum_k C[i, k] T_k[p, q] P[k, j],   i.e.  T = (I (x) C) U (I (x) P),

with C the camera's channel sensitivities (3x3), P the projector's primaries (3x3) and
U channel-diagonal (U[3p+k, 3q+k] = T_k[p, q], zero across channels). Then
T^-1 = (I (x) P^-1) U^-1 (I (x) C^-1), and U^-1 is three grey inverses
(:mod:`.global_mixing`): a ninth of the entries of the general path's products.

This module finds (C, P) and checks that they hold:

* :func:`recorded_mixing`: the mixing an acquisition or a scene recorded with T
  (``T.metadata["mixing"] = {"camera": 3x3, "projector": 3x3}``), or one a caller gives;
* :func:`estimate_mixing`: from T's 3x3 diagonal blocks B_p = C D_p P (D_p diagonal): for
  a reference block B_b, every B_p B_b^-1 = C (D_p D_b^-1) C^-1 shares C's columns as
  eigenvectors, so C comes from the eigenvectors of a random combination of them and
  P = C^-1 B_b (D_b absorbed into P; any scale or order of C's columns is absorbed into
  U, and harmless);
* :func:`mixing_residue`: one streaming pass over all of T, un-mixing each pixel block
  (C^-1 B P^-1) and measuring the cross-channel entries against the in-channel ones;
* :func:`choose_colour_path`: which path ``stratified_inverse`` takes, and why.

The per-pixel blocks of a tile row are gathered by :func:`pixel_blocks`, which the
split (:mod:`.global_mixing`) and the mixing estimate share.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import BigTError
from . import defaults

#: ``colour_path`` values of :func:`~bigT.algorithms.stratified_inverse`.
COLOUR_PATHS = ("auto", "general", "global")


@dataclass(frozen=True)
class ColourMixing:
    """One 3x3 camera and one 3x3 projector mixing for the whole rig.

    Attributes
    ----------
    camera : (3, 3) float64 ndarray
        C: camera channel i's response to band k is ``camera[i, k]``.
    projector : (3, 3) float64 ndarray
        P: band k's share of projector primary j is ``projector[k, j]``.
    source : str
        Where they came from: ``"recorded with T"``, ``"given by the caller"`` or
        ``"estimated from T's diagonal blocks"``.
    residual : float or None
        The cross-channel residue of T un-mixed by them (:func:`mixing_residue`;
        None until measured).
    """

    camera: np.ndarray
    projector: np.ndarray
    source: str
    residual: float | None = None

    def __post_init__(self):
        for name in ("camera", "projector"):
            m = np.array(getattr(self, name), dtype=np.float64)
            m.setflags(write=False)
            object.__setattr__(self, name, m)

    @property
    def camera_inverse(self) -> np.ndarray:
        return np.linalg.inv(self.camera)

    @property
    def projector_inverse(self) -> np.ndarray:
        return np.linalg.inv(self.projector)

    def with_residual(self, residual: float) -> "ColourMixing":
        return replace(self, residual=float(residual))

    def to_json(self) -> dict:
        """``{"camera": 3x3, "projector": 3x3}``: the form T's metadata records."""
        return {"camera": self.camera.tolist(), "projector": self.projector.tolist()}


@dataclass(frozen=True)
class ColourPathChoice:
    """Which path a colour inverse takes, and why (the line ``bigT invert`` prints).

    Attributes
    ----------
    path : {"general", "global"}
    reason : str
        In words, e.g. ``"global colour mixing (recorded with T; cross-channel residue
        3e-08 <= 1e-05): three grey inverses"``.
    mixing : ColourMixing or None
        The verified mixing of the global path (or the one that failed, when known).
    """

    path: str
    reason: str
    mixing: ColourMixing | None = None


# --- the pixel blocks of a tile row ------------------------------------------------

def pixel_blocks(rows: sp.csr_array) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 3x3 pixel blocks holding an entry in ``rows``.

    Parameters
    ----------
    rows : csr_array, shape (3 m, 3 n)
        Rows of a colour matrix (the first one a pixel's channel 0), global columns.

    Returns
    -------
    p : (b,) int64, the block's row pixel, counted from the first row's
    q : (b,) int64, its column pixel
    blocks : (b, 3, 3) float64, the blocks, sorted by (p, q)
    """
    coo = sp.coo_array(rows)
    r = coo.row.astype(np.int64)
    c = coo.col.astype(np.int64)
    pixels = rows.shape[1] // 3
    keys, slot = np.unique((r // 3) * pixels + c // 3, return_inverse=True)
    flat = np.bincount(slot.ravel() * 9 + (r % 3) * 3 + c % 3,
                       weights=coo.data.astype(np.float64), minlength=9 * len(keys))
    return keys // pixels, keys % pixels, flat.reshape(-1, 3, 3)


def row_chunks(store, max_entries: int = config.GLOBAL_MIXING_CHUNK_ENTRIES):
    """Yield ``(start, rows)``: ``store``'s rows in pixel-aligned chunks (a multiple of
    3 rows, about ``max_entries`` entries each; whole tile rows are read once)."""
    for i in range(store.grid[0]):
        a, b = store.tile_row_range(i)
        block = sp.csr_array(store.get_tile_row(i))
        per_row = max(1, block.nnz // max(1, b - a))
        step = max(3, (max_entries // per_row) // 3 * 3)
        for s in range(0, b - a, step):
            yield a + s, block[s:min(s + step, b - a)]


def _cross_and_in(unmixed: np.ndarray) -> tuple[float, float]:
    """Sums of squares of the cross-channel and the in-channel entries of (b, 3, 3)."""
    sq = unmixed * unmixed
    inside = np.einsum("bkk->", sq)
    sq[:, range(3), range(3)] = 0.0
    return float(sq.sum()), float(inside)


def relative_residue(cross_sq: float, in_sq: float) -> float:
    """||cross-channel||_F / ||in-channel||_F (inf when nothing is in-channel)."""
    return float(np.sqrt(cross_sq / in_sq)) if in_sq > 0 else float("inf")


def unmix(blocks: np.ndarray, mixing: ColourMixing) -> np.ndarray:
    """C^-1 B P^-1 of each (b, 3, 3) block."""
    return mixing.camera_inverse @ blocks @ mixing.projector_inverse


# --- where the mixing comes from ---------------------------------------------------

def mixing_tolerance(dtype) -> float:
    """The cross-channel residue below which the mixing is taken as global, for a
    store of ``dtype`` (docs on :data:`bigT.config.GLOBAL_MIXING_RTOL`)."""
    return (config.GLOBAL_MIXING_RTOL if np.dtype(dtype) == np.float32
            else config.GLOBAL_MIXING_RTOL_FLOAT64)


def checked_mixing(value, source: str, where=None) -> ColourMixing:
    """A (camera, projector) pair or ``{"camera": ..., "projector": ...}`` as a
    :class:`ColourMixing`; BigTError (naming ``where``) when either is not a finite,
    invertible 3x3 matrix."""
    if isinstance(value, ColourMixing):
        return replace(value, source=source)
    try:
        camera, projector = ((value["camera"], value["projector"]) if isinstance(value, dict)
                             else value)
        pair = [np.asarray(m, dtype=np.float64) for m in (camera, projector)]
    except (TypeError, ValueError, KeyError):
        raise BigTError(f"the colour mixing {source} is not a (camera, projector) pair of "
                        "3x3 matrices", where) from None
    for name, m in zip(("camera", "projector"), pair):
        if m.shape != (3, 3) or not np.isfinite(m).all():
            raise BigTError(f"the {name} mixing {source} is not a finite 3x3 matrix "
                            f"(shape {m.shape})", where)
        if np.linalg.cond(m) > config.GLOBAL_MIXING_MAX_COND:
            raise BigTError(f"the {name} mixing {source} is singular or nearly so "
                            f"(condition number {np.linalg.cond(m):.3g})", where)
    return ColourMixing(pair[0], pair[1], source)


def recorded_mixing(T) -> ColourMixing | None:
    """The mixing recorded with T (``metadata["mixing"]``), or None."""
    value = (getattr(T, "metadata", None) or {}).get("mixing")
    return None if value is None else checked_mixing(value, "recorded with T", T.path)


def diagonal_blocks(T) -> np.ndarray:
    """(n_pixels, 3, 3) float64: every pixel's diagonal block of the colour T (read
    from the diagonal tiles only)."""
    out = np.zeros((T.shape[0] // 3, 3, 3))
    for i in range(T.grid[0]):
        if not T.has_tile(i, i):
            continue
        a, _ = T.tile_row_range(i)
        p, q, blocks = pixel_blocks(sp.csr_array(T.get_tile(i, i)))
        on = p == q
        out[a // 3 + p[on]] = blocks[on]
    return out


def estimate_mixing(T, seed: int = 0) -> ColourMixing | None:
    """(C, P) estimated from T's diagonal blocks, or None when fewer than two pixels
    have a well-conditioned block (condition number below
    ``config.GLOBAL_MIXING_MAX_COND``).

    For a reference block B_b, K = sum_j w_j B_j B_b^-1 = C (sum_j w_j D_j D_b^-1) C^-1
    (random weights w over up to ``config.GLOBAL_MIXING_CANDIDATES`` sampled pixels):
    its eigenvectors are C's columns wherever some pixel tells two bands apart, and any
    basis will do where none does (the bands then differ by a scale only). Each of
    ``config.GLOBAL_MIXING_TRIES`` tries takes another reference (the best-conditioned
    blocks first) and other weights; the try whose (C, P) leaves the smallest
    cross-channel residue on the sampled blocks wins. Not verified: see
    :func:`mixing_residue`.
    """
    rng = np.random.default_rng(seed)
    blocks = diagonal_blocks(T)
    good = _well_conditioned(blocks)
    if len(good) < 2:
        return None
    if len(good) > config.GLOBAL_MIXING_CANDIDATES:
        good = rng.choice(good, config.GLOBAL_MIXING_CANDIDATES, replace=False)
    sample = blocks[good]
    conds = np.linalg.cond(sample)
    best = None
    for b in np.argsort(conds)[:config.GLOBAL_MIXING_TRIES]:
        w = rng.standard_normal(len(sample))
        K = np.einsum("j,jik->ik", w, sample) @ np.linalg.inv(sample[b])
        vectors = np.real(np.linalg.eig(K)[1])
        if np.linalg.cond(vectors) > config.GLOBAL_MIXING_MAX_COND:
            continue  # two bands no pixel tells apart, and eig's basis is degenerate
        mixing = _normalised(vectors, sample[b])
        score = relative_residue(*_cross_and_in(unmix(sample, mixing)))
        if best is None or score < best[0]:
            best = (score, mixing)
    return None if best is None else best[1]


def _well_conditioned(blocks: np.ndarray) -> np.ndarray:
    """Indices of the blocks that are nonzero with a condition number below
    ``config.GLOBAL_MIXING_MAX_COND``."""
    lit = np.flatnonzero(np.abs(blocks).sum(axis=(1, 2)) > 0)
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(blocks[lit])
    return lit[np.isfinite(cond) & (cond < config.GLOBAL_MIXING_MAX_COND)]


def _normalised(vectors: np.ndarray, reference: np.ndarray) -> ColourMixing:
    """(C, P) from C's eigenvector columns and a reference block B_b = C D_b P, put in
    a readable form: C's columns ordered so that band k is mostly camera channel k,
    scaled to a largest entry of +1, and P = C^-1 B_b with its rows scaled to a
    largest magnitude of 1 (positive scales: U's diagonal keeps T's sign)."""
    mags = np.abs(vectors)
    order = max(itertools.permutations(range(3)),
                key=lambda perm: np.prod([mags[k, perm[k]] for k in range(3)]))
    C = vectors[:, order]
    C = C / C[np.argmax(np.abs(C), axis=0), range(3)]
    P = np.linalg.solve(C, reference)
    P = P / np.abs(P).max(axis=1, keepdims=True)
    return ColourMixing(C, P, "estimated from T's diagonal blocks")


# --- the verification pass ---------------------------------------------------------

def mixing_residue(T, mixing: ColourMixing) -> float:
    """||cross-channel entries||_F / ||in-channel entries||_F of (I (x) C^-1) T
    (I (x) P^-1), over all of T (one streaming pass over its tile rows): 0 for a
    global mixing up to T's rounding, the size of the per-pixel variation otherwise."""
    cross = inside = 0.0
    for _, rows in row_chunks(T):
        c, i = _cross_and_in(unmix(pixel_blocks(rows)[2], mixing))
        cross, inside = cross + c, inside + i
    return relative_residue(cross, inside)


# --- the choice --------------------------------------------------------------------

def checked_colour_path(colour_path: str) -> str:
    if colour_path not in COLOUR_PATHS:
        raise BigTError(f"colour_path must be one of {COLOUR_PATHS}, got {colour_path!r:.60}",
                        option=("colour_path", colour_path))
    return colour_path


def choose_colour_path(T, colour_path: str = "auto", mixing=None, *,
                       first_bounce=defaults.FIRST_BOUNCE, on_term=None,
                       seed: int = 0) -> ColourPathChoice:
    """The path the inverse of the colour ``T`` takes, and why.

    ``"general"``: the general engine (3x3 block-diagonal F). ``"global"`` and
    ``"auto"``: the mixing is the one given (``mixing``, a (C, P) pair), else the one
    recorded with T, else estimated from T's diagonal blocks; it is verified over all
    of T (:func:`mixing_residue`) against :func:`mixing_tolerance`. ``"auto"`` takes
    the global path when it holds, the general one otherwise; ``"global"`` raises
    BigTError (saying why) when it does not hold.

    The global path needs F = diag(U) or I (``first_bounce`` "diag" or "identity":
    a given F is a colour F, not U's) and no ``on_term`` callback (its terms are U's).
    """
    colour_path = checked_colour_path(colour_path)
    if colour_path == "general":
        return ColourPathChoice("general", "general: asked for")
    refusal, found = _global_path_refusal(first_bounce, on_term), None
    if refusal is None:
        try:
            found = (checked_mixing(mixing, "given by the caller") if mixing is not None
                     else recorded_mixing(T) or estimate_mixing(T, seed))
        except BigTError as exc:  # a damaged record: the general path needs none
            if colour_path == "global":
                raise
            return ColourPathChoice("general", f"general: {exc.problem}")
        if found is None:
            refusal = ("no global mixing found: fewer than two pixels have a "
                       "well-conditioned 3x3 block")
        else:
            found = found.with_residual(mixing_residue(T, found))
            tol = mixing_tolerance(T.dtype)
            why = f"{found.source}; cross-channel residue {found.residual:.2g}"
            if found.residual <= tol:
                return ColourPathChoice(
                    "global", f"global colour mixing ({why} <= {tol:g}): three grey "
                    "inverses", found)
            refusal = f"per-pixel mixing varies ({why} > {tol:g})"
    if colour_path == "global":
        raise BigTError(f"the global colour-mixing path does not apply: {refusal}; use "
                        "{option}", T.path, option=("colour_path", "general"))
    return ColourPathChoice("general", f"general: {refusal}", found)


def _global_path_refusal(first_bounce, on_term) -> str | None:
    """Why the global path cannot run with these options (None when it can)."""
    if not (isinstance(first_bounce, str) and first_bounce in ("diag", "identity")):
        return "a given first bounce F is a colour F, which the global path's grey " \
               "inverses cannot take"
    if on_term is not None:
        return "a per-term callback (on_term, as the target-error search uses) " \
               "measures the general path's terms"
    return None
