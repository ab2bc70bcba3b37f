"""Radiosity transport between patches, built sparse and row block by row block.

* Form factors (paper eq. 1 discretised, point to point):
  ``FF_ij = cos_i cos_j a_j / (pi r^2 + (a_i + a_j) / 2)``. The ``(a_i + a_j)/2`` term
  is the disk-approximation regularisation of Wallace et al. (1989): far pairs get the
  textbook ``cos_i cos_j a_j / (pi r^2)``; touching pairs (across a fold) stay below 1
  instead of blowing up. It is symmetric in i, j, so reciprocity
  ``a_i FF_ij = a_j FF_ji`` holds exactly.
* Truncation: a pair (both directions) is kept when ``max(FF_ij, FF_ji) >= cut``. As
  ``FF_ij <= a_j / (pi r^2)``, only centres within ``r_max = sqrt(max(a) / (pi cut))``
  can qualify; they are enumerated with a k-d tree, one chunk of rows at a time, so
  the n^2 pairs are never formed.
* ``A = diag(albedo) FF`` (paper eq. 3) and ``T = (I - A)^-1 F`` (eq. 6) by the
  forward Neumann series (eq. 8), one tile row at a time:
  ``R_0 = I[rows]``, ``R_k = R_{k-1} A`` (pruned), ``T[rows] = (sum_k R_k) F``.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .. import config
from ..errors import BigTError, DivergenceError, MemoryLimitError
from ..kernels import spgemm
from ..progress import progress_bar
from .geometry import Patches


def _pair_form_factors(P: Patches, i: np.ndarray, j: np.ndarray):
    """FF_ij and FF_ji for pairs (i, j), zero where either surface faces away."""
    d = P.points[j] - P.points[i]
    r2 = np.einsum("ij,ij->i", d, d)
    r = np.sqrt(r2)
    cos_i = np.einsum("ij,ij->i", P.normals[i], d) / r
    cos_j = -np.einsum("ij,ij->i", P.normals[j], d) / r
    # 1e-9: coplanar patches (cos = 0 up to rounding) exchange no light
    facing = (cos_i > 1e-9) & (cos_j > 1e-9)
    k = np.where(facing, cos_i * cos_j, 0.0) / (np.pi * r2 + 0.5 * (P.areas[i] + P.areas[j]))
    return k * P.areas[j], k * P.areas[i]


def _visible(P: Patches, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """True where the segment p_i -> p_j passes through no occluding sphere.

    Analytic ray-sphere test, vectorised over pairs: the point of the segment closest
    to the centre is strictly inside the sphere. An endpoint lying on a sphere, with the
    segment leaving it outward (cos > 0 was already required), touches it at distance R
    exactly; the relative margin keeps that from counting as a hit.
    """
    ok = np.ones(len(i), dtype=bool)
    if len(P.spheres) == 0 or len(i) == 0:
        return ok
    p = P.points[i]
    d = P.points[j] - p
    dd = np.einsum("ij,ij->i", d, d)
    lo = np.minimum(p, P.points[j])
    hi = np.maximum(p, P.points[j])
    for cx, cy, cz, R in P.spheres:
        c = np.array([cx, cy, cz])
        near = ok & np.all((lo <= c + R) & (hi >= c - R), axis=1)
        if not near.any():
            continue
        idx = np.flatnonzero(near)
        pc = c - p[idx]
        t = np.clip(np.einsum("ij,ij->i", pc, d[idx]) / dd[idx], 0.0, 1.0)
        closest = pc - t[:, None] * d[idx]
        inside = np.einsum("ij,ij->i", closest, closest) < R * R * (1.0 - config.SCENE_VISIBILITY_MARGIN)
        ok[idx[inside]] = False
    return ok


def face_trees(P: Patches, cut: float):
    """(r_max, {face: (k-d tree of its centres, their indices)}) for a cut > 0.

    As ``FF_ij <= a_j / (pi r^2)``, only centres within ``r_max`` of each other can
    reach the cut. One tree per face: when patches of one face cannot exchange light
    (a planar or convex face), only the other faces are searched."""
    r_max = math.sqrt(P.areas.max() / (math.pi * cut))
    trees = {}
    for g in np.unique(P.face):
        idx = np.flatnonzero(P.face == g)
        trees[g] = (cKDTree(P.points[idx]), idx)
    return r_max, trees


def _candidate_pairs(P: Patches, i0: int, i1: int, cut: float, trees, r_max: float):
    """(i, j) int64 arrays: the pairs of rows i0:i1 that may reach the cut (every pair
    when cut = 0, less those within a face that exchanges no light)."""
    n = P.n
    if cut == 0:
        i = np.repeat(np.arange(i0, i1), n)
        j = np.tile(np.arange(n), i1 - i0)
        if not P.same_face_exchange:
            keep = P.face[i] != P.face[j]
            i, j = i[keep], j[keep]
        return i, j
    ii, jj = [], []
    for h in np.unique(P.face[i0:i1]):
        src = i0 + np.flatnonzero(P.face[i0:i1] == h)
        sub = cKDTree(P.points[src])
        for g, (tree, idx) in trees.items():
            if g == h and not P.same_face_exchange:
                continue
            pairs = sub.sparse_distance_matrix(tree, r_max, output_type="ndarray")
            ii.append(src[pairs["i"]])
            jj.append(idx[pairs["j"]])
    i = np.concatenate(ii) if ii else np.zeros(0, np.int64)
    j = np.concatenate(jj) if jj else np.zeros(0, np.int64)
    return i, j


def check_all_pairs(n: int, cut: float) -> None:
    """Refuse (MemoryLimitError) a cut of 0 where testing all n^2 pairs is too much."""
    if cut == 0 and n * n > config.SCENE_MAX_ALL_PAIRS:
        raise MemoryLimitError(
            f"cut = 0 tests all {n}^2 pairs, more than config.SCENE_MAX_ALL_PAIRS = "
            f"{config.SCENE_MAX_ALL_PAIRS}; give a form-factor cut (e.g. {{option}}) "
            "or a density preset", option=("ff_cut", 1e-6))


def form_factor_rows(P: Patches, cut: float = 0.0, *, rows=None, chunk: int | None = None,
                     search=None):
    """Yield the rows of the (truncated) form-factor matrix FF, chunk by chunk.

    Each chunk is searched on its own (a k-d tree of its centres against one tree per
    face), so memory holds one chunk's candidate pairs, whatever n.

    Parameters
    ----------
    P : Patches, in the matrix order wanted for FF.
    cut : float >= 0
        Pairs with ``max(FF_ij, FF_ji) < cut`` are dropped (both directions, so the
        pattern stays symmetric and reciprocity holds for every stored entry).
        ``cut = 0`` keeps every pair that sees each other (all n^2 pairs are tested).
    rows : (start, stop), optional
        The rows wanted (default all).
    chunk : int, optional
        Rows per search (default ``config.SCENE_PAIR_CHUNK``).
    search : (r_max, trees), optional
        :func:`face_trees` of ``P`` and ``cut``, made once by a caller that asks for
        many row ranges (made here when not given).

    Yields
    ------
    (i0, csr_array of shape (i1 - i0, n), float64, sorted indices, zero diagonal)
    """
    n = P.n
    chunk = chunk or config.SCENE_PAIR_CHUNK
    if cut < 0 or not math.isfinite(cut):
        raise BigTError(f"cut must be a finite number >= 0, got {cut}")
    if search is None:
        search = face_trees(P, cut) if cut > 0 else (math.inf, {})
    r_max, trees = search
    start, stop = (0, n) if rows is None else (int(rows[0]), int(rows[1]))
    for i0 in range(start, stop, chunk):
        i1 = min(stop, i0 + chunk)
        i, j = _candidate_pairs(P, i0, i1, cut, trees, r_max)
        keep = i != j
        i, j = i[keep], j[keep]
        f_ij, f_ji = _pair_form_factors(P, i, j)
        keep = np.maximum(f_ij, f_ji) >= cut if cut > 0 else (f_ij > 0)
        keep &= f_ij > 0
        i, j, f_ij = i[keep], j[keep], f_ij[keep]
        vis = _visible(P, i, j)
        i, j, f_ij = i[vis], j[vis], f_ij[vis]
        idx = np.int32 if n < 2**31 else np.int64
        block = sp.coo_array((f_ij, (i.astype(idx) - i0, j.astype(idx))),
                             shape=(i1 - i0, n)).tocsr()
        block.sum_duplicates()
        block.sort_indices()
        yield i0, block


def form_factors(P: Patches, cut: float = 0.0, *, chunk: int | None = None,
                 max_nnz: int | None = None, progress=None) -> sp.csr_array:
    """The (truncated) form-factor matrix FF in memory, shape (n, n), float64, zero
    diagonal (:func:`form_factor_rows` assembled; scenes write it tile row by tile row
    instead).

    Parameters
    ----------
    P, cut, chunk : as :func:`form_factor_rows`
    max_nnz : int, optional
        Refuse (MemoryLimitError) beyond this many stored entries
        (default ``config.SCENE_MAX_A_NNZ``).
    """
    n = P.n
    max_nnz = config.SCENE_MAX_A_NNZ if max_nnz is None else int(max_nnz)
    check_all_pairs(n, cut)
    chunk = chunk or config.SCENE_PAIR_CHUNK
    blocks, total = [], 0
    pieces = form_factor_rows(P, cut, chunk=chunk)
    for i0, block in progress_bar(pieces, progress=progress, desc="form factors",
                                  unit="chunk", total=-(-n // chunk)):
        total += block.nnz
        if total > max_nnz:
            raise MemoryLimitError(
                f"the form-factor matrix passed {max_nnz} entries (config.SCENE_MAX_A_NNZ) "
                f"after {i0 + block.shape[0]} of {n} rows; raise the form-factor cut")
        blocks.append(block)
    if not blocks:
        return sp.csr_array((n, n), dtype=np.float64)
    FF = sp.csr_array(sp.vstack(blocks, format="csr"))
    FF.sort_indices()
    return FF


def interreflection(FF: sp.csr_array, albedo: np.ndarray) -> sp.csr_array:
    """A = diag(albedo) FF, shape (n, n), float64."""
    A = sp.csr_array(FF.multiply(np.asarray(albedo, np.float64)[:, None]))
    A.sort_indices()
    return A


def band_interreflection(FF: sp.csr_array, albedo: np.ndarray) -> sp.csr_array:
    """The three bands' A_k = diag(albedo[:, k]) FF interleaved: entry (3 p + k, 3 q + k)
    is A_k[p, q], shape (3 m, 3 n) for FF of shape (m, n) and albedo (m, 3), float64."""
    A = sp.csr_array(sp.kron(FF, sp.eye_array(3), format="csr"))
    A = sp.csr_array(A.multiply(np.asarray(albedo, np.float64).reshape(-1, 1)))
    A.sort_indices()
    return A


def interleave_bands(G: sp.csr_array) -> sp.csr_array:
    """G acting on each band alike: entry (3 p + k, 3 q + k) is G[p, q]."""
    return sp.csr_array(sp.kron(G, sp.eye_array(3), format="csr"))


def block_diagonal(blocks: np.ndarray) -> sp.csr_array:
    """The (3 m, 3 m) block-diagonal matrix of m (3, 3) ``blocks``, CSR float64."""
    m = len(blocks)
    bsr = sp.bsr_array((np.asarray(blocks, np.float64), np.arange(m), np.arange(m + 1)),
                       shape=(3 * m, 3 * m))
    return sp.csr_array(bsr.tocsr())


def mix_bands(T_bands: sp.csr_array, camera: np.ndarray, projector: sp.csr_array
              ) -> sp.csr_array:
    """Rows of a colour T from the same rows of the interleaved band transport:
    T[3 p + i, 3 q + j] = sum_k C_p[i, k] T_k[p, q] P_q[k, j].

    Parameters
    ----------
    T_bands : csr_array, (3 m, 3 n)
        Rows 3 p0 .. 3 p1 of the bands interleaved (entry (3 p + k, 3 q + k) = T_k[p, q]).
    camera : ndarray, (m, 3, 3)
        C_p of the m camera pixels p0 .. p1.
    projector : csr_array, (3 n, 3 n)
        The block-diagonal of every projector pixel's P_q (:func:`block_diagonal`).
    """
    T = sp.csr_array(block_diagonal(camera) @ (T_bands @ projector))
    T.sort_indices()
    return T


def gaussian_blur_matrix(size, sigma: float, order: np.ndarray) -> sp.csr_array:
    """Projector defocus G, shape (n, n): column j spreads projector pixel j over the
    image with a Gaussian of standard deviation ``sigma`` pixels, truncated at
    ``ceil(3 sigma)`` and normalised so each column sums to 1 (no light lost).

    ``order`` is the pixel order's permutation (matrix index -> row-major pixel).
    """
    H, W = (int(s) for s in size)
    n = H * W
    rad = int(math.ceil(config.SCENE_BLUR_TRUNCATE * sigma))
    inv = np.empty(n, dtype=np.int64)
    inv[order] = np.arange(n)
    rr, cc = np.divmod(np.arange(n), W)
    rows, cols, vals = [], [], []
    for dr in range(-rad, rad + 1):
        for dc in range(-rad, rad + 1):
            w = math.exp(-(dr * dr + dc * dc) / (2.0 * sigma * sigma))
            r2, c2 = rr + dr, cc + dc
            ok = (r2 >= 0) & (r2 < H) & (c2 >= 0) & (c2 < W)
            rows.append(inv[r2[ok] * W + c2[ok]])
            cols.append(inv[np.flatnonzero(ok)])
            vals.append(np.full(int(ok.sum()), w))
    G = sp.coo_array((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                     shape=(n, n)).tocsr()
    colsum = np.asarray(G.sum(axis=0)).ravel()
    G = sp.csr_array(G.multiply(1.0 / colsum[None, :]))
    G.sort_indices()
    return G


def in_memory_product(A: sp.csr_array):
    """``times_A(R, threshold)``: R @ A pruned at ``threshold``, for an A in memory."""
    def times_A(R, threshold):
        return spgemm(R, A, threshold=threshold)

    return times_A


def transport_rows(A, f: np.ndarray, r0: int, r1: int, *, prune: float, stop: float,
                   max_bounces: int, G: sp.csr_array | None = None):
    """Rows r0:r1 of T = (sum_k A^k) diag(f) [G], float64 CSR, and the bounce count.

    ``A`` is an (n, n) csr_array, or a callable ``times_A(R, threshold)`` giving R @ A
    pruned with an ``nnz`` attribute (a stored A read tile row by tile row, see
    ``bigT.scenes.builder``).
    ``R_k`` entries below ``prune`` are dropped inside the product; the series stops
    once the newest bounce's largest entry times max(f) is below ``stop``.
    """
    times_A = A if callable(A) else in_memory_product(A)
    n = len(f)
    m = r1 - r0
    R = sp.csr_array((np.ones(m), np.arange(r0, r1), np.arange(m + 1)), shape=(m, n))
    S = R.copy()
    fmax = float(np.abs(f).max()) if len(f) else 0.0
    k = 0
    while R.nnz and A.nnz:  # a callable A carries its nnz too
        R = times_A(R, prune)
        k += 1
        if R.nnz == 0:
            break
        S = S + R
        if float(np.abs(R.data).max()) * fmax < stop:
            break
        if k >= max_bounces:
            raise DivergenceError(
                f"the bounce series of rows {r0}:{r1} had not converged after {k} bounces "
                f"(largest entry {float(np.abs(R.data).max()):.3g}); the albedo is too high "
                "for this geometry")
    T = sp.csr_array(S.multiply(f[None, :]))
    if G is not None:
        T = sp.csr_array(T @ G)
    T.sort_indices()
    return T, k


def light_shares(bounces) -> list[float]:
    """Each bounce's share of the total light: sum(b_k) / sum_j sum(b_j), adding up to
    1 (the definition ``bigT bounces`` uses for an image's parts too)."""
    totals = np.array([float(np.sum(b)) for b in bounces])
    whole = totals.sum()
    return (totals / whole).tolist() if whole else [0.0] * len(totals)


def bounce_images(A, F1: np.ndarray, max_bounces: int, rel_tol: float):
    """b_k = A^k F 1 for k = 0..K, stopping when ||b_k|| < rel_tol ||b_0||.

    ``A``: a sparse (n, n) matrix, or a callable ``A(v)`` giving A @ v."""
    times = A if callable(A) else (lambda v: A @ v)
    out = [np.asarray(F1, np.float64)]
    n0 = np.linalg.norm(out[0])
    while len(out) <= max_bounces:
        b = times(out[-1])
        out.append(b)
        if np.linalg.norm(b) < rel_tol * n0:
            break
    return out
