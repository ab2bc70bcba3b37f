"""What a scene's summary says of its transport, measured on the stores: the spectral
radii of M = I - T F^-1 and of A, the bounce shares of a white image's light (per
channel for colour) and T 1 (the preview), each product streamed from disk beyond the
build's memory limit."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import config
from ..schedule.memory import resident_bytes, return_freed_memory
from ..spectral import SpectralRadius, spectral_radius
from . import radiosity, stored
from .colouring import ColourParts


def finite_or_none(value: float) -> float | None:
    """JSON has no inf or NaN: an undetermined radius is stored as null."""
    return float(value) if math.isfinite(value) else None


def spectral_radius_T(times_T, d) -> SpectralRadius:
    """rho(M) for M = I - T diag(d)^-1 on the pixels with d > 0, to
    ``config.SCENE_SPECTRAL_RTOL`` (bracketed beyond ``config.SCENE_BRACKET_MIN_N``
    pixels, :func:`_radius`); ``times_T(V)`` is T @ V."""
    inv = np.zeros_like(d)
    inv[d > 0] = 1.0 / d[d > 0]
    lit = d > 0

    def minus_M(V):
        # (T - diag(d)) diag(d)^-1 V: the diagonal cancels exactly (V - T diag(d)^-1 V
        # left 1e-16 of rounding on a diagonal T)
        W = V * inv[:, None]
        return times_T(W) - d[:, None] * W

    return _radius(minus_M, len(d), lit)


def _radius(apply_nonneg, n: int, active: np.ndarray | None = None) -> SpectralRadius:
    """rho of the nonnegative operator ``apply_nonneg`` (T >= 0 makes -M and A so) on
    ``active``: ARPACK to ``config.SCENE_SPECTRAL_RTOL``, or beyond
    ``config.SCENE_BRACKET_MIN_N`` unknowns the Collatz-Wielandt bracket first (ARPACK
    only where it is not narrow, ``bigT.spectral.spectral_radius``)."""
    if n > config.SCENE_BRACKET_MIN_N:
        return spectral_radius(lambda V: -apply_nonneg(V), n, active, nonpositive=True,
                               rtol=config.SCENE_SPECTRAL_RTOL,
                               max_products=config.SCENE_SPECTRAL_MAX_PRODUCTS)
    return spectral_radius(apply_nonneg, n, active, rtol=config.SCENE_SPECTRAL_RTOL,
                           max_products=config.SCENE_SPECTRAL_MAX_PRODUCTS)


#: A colour pixel's 3x3 block of T counts as singular beyond this condition number (its
#: channels cannot be told apart): the ground truth's rho(M) leaves the pixel out.
BLOCK_COND_MAX = 1e12


def spectral_radius_blocks(times_T, D: np.ndarray) -> SpectralRadius:
    """rho(M) for M = I - T F^-1, F = the (n_pixels, 3, 3) diagonal blocks ``D`` of a
    colour T, on the pixels whose block is invertible (the others are left out, as an
    unlit grey pixel is); ``times_T(V)`` is T @ V. M is not sign-definite (F^-1 has
    negative entries): Arnoldi (or every eigenvalue when small) decides."""
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.linalg.cond(D) if len(D) else np.zeros(0)
    good = np.isfinite(cond) & (cond < BLOCK_COND_MAX)
    inv = np.zeros_like(D)
    inv[good] = np.linalg.inv(D[good])

    def blocks_times(B, V):
        p = V.shape[1]
        return np.einsum("nij,njp->nip", B, V.reshape(-1, 3, p)).reshape(-1, p)

    def minus_M(V):
        W = blocks_times(inv, V)  # F^-1 V
        return times_T(W) - blocks_times(D, W)  # (T - F) F^-1 V

    return spectral_radius(minus_M, 3 * len(D), np.repeat(good, 3),
                           rtol=config.SCENE_SPECTRAL_RTOL,
                           max_products=config.SCENE_SPECTRAL_MAX_PRODUCTS)


@dataclass(frozen=True)
class GroundTruthStats:
    """What a scene's summary says of its transport, measured on the stores.

    Attributes
    ----------
    rho_M, rho_A : SpectralRadius
        Of M = I - T diag(T)^-1 and of A.
    shares : list of float
        Each bounce's share of the light of a white projector image.
    T1 : ndarray, (n,) float64
        T 1, the camera's view of a white projector image (the preview).
    shares_per_channel : list of 3 lists of float, or None
        Colour: each bounce's share of the light the camera sees in channel R, G, B.
    """

    rho_M: SpectralRadius
    rho_A: SpectralRadius
    shares: list
    T1: np.ndarray
    shares_per_channel: list | None = None

    def fields(self) -> dict:
        colour = {} if self.shares_per_channel is None else {
            "bounce_shares_per_channel": self.shares_per_channel}
        return {**colour, "spectral_radius": finite_or_none(self.rho_M.value),
                "spectral_radius_A": finite_or_none(self.rho_A.value),
                "spectral_radius_uncertainty": finite_or_none(self.rho_M.uncertainty),
                "spectral_radius_A_uncertainty": finite_or_none(self.rho_A.uncertainty),
                "spectral_radius_method": self.rho_M.method,
                "spectral_radius_A_method": self.rho_A.method,
                "bounce_shares": self.shares}


#: The (n,) float64 vectors the statistics hold beside the cached tile rows: the
#: bracket's v, w and product, the bounce images' two, T 1.
STATS_VECTORS = 6


def _cache_bytes(memory_limit: int, n: int) -> int:
    """Bytes of decoded tile rows the statistics' products may cache: a share of the
    limit, and no more than what the process does not hold already (the build's
    earlier phases leave ~2 GB resident at 4K) besides the vectors."""
    free = (int(memory_limit) - resident_bytes() - STATS_VECTORS * 8 * int(n)
            - int(config.SCENE_STATS_HEADROOM_SHARE * memory_limit))
    return max(0, min(int(config.SCENE_STATS_CACHE_SHARE * memory_limit), free))


def _radii_and_bounces(T, A, f, G, memory_limit: int, radius_of_M, lit: np.ndarray):
    """What both kinds of scene measure: rho(M) (``radius_of_M(times_T)``), T 1, rho(A)
    and the bounce images of the light ``lit`` (f G lit first), T and A each held
    within ``memory_limit`` in turn."""
    n = T.shape[0]
    times_T = stored.stored_apply(T, _cache_bytes(memory_limit, n))
    rho_M = radius_of_M(times_T)
    T1 = times_T(np.ones(n))
    del times_T
    return_freed_memory()  # T's cached tile rows back to the system before A's are read
    times_A = stored.stored_apply(A, _cache_bytes(memory_limit, n))
    rho_A = _radius(times_A, n)
    b0 = f * (G @ lit if G is not None else lit)
    bounces = radiosity.bounce_images(times_A, b0, config.SCENE_SHARE_MAX_BOUNCES,
                                      config.SCENE_SHARE_TOL)
    return rho_M, T1, rho_A, bounces


def ground_truth_stats(T, A, f, G, memory_limit: int) -> GroundTruthStats:
    """Spectral radii, bounce shares and T 1 from the stored T and A, one matrix at a
    time held within ``memory_limit`` (streamed from disk beyond it)."""
    d = np.asarray(T.diagonal(output_order="matrix"), np.float64)
    rho_M, T1, rho_A, bounces = _radii_and_bounces(
        T, A, f, G, memory_limit, lambda times_T: spectral_radius_T(times_T, d),
        np.ones(T.shape[0]))
    return GroundTruthStats(rho_M, rho_A, radiosity.light_shares(bounces), T1)


def colour_ground_truth_stats(T, A, f, G, colour: ColourParts,
                               memory_limit: int) -> GroundTruthStats:
    """:func:`ground_truth_stats` for a colour scene: rho(M) with F the 3x3 diagonal
    blocks of T, rho of the bands' A (that of the camera's C A C^-1), and the bounce
    shares of what the camera sees, in all and per channel.

    ``f`` (3 n_pixels,) and ``G`` are the bands' first bounce and blur, interleaved."""
    D = stored.diagonal_blocks(T)
    lit = colour.projector_matrix @ np.ones(T.shape[0])  # the bands a white image lights
    rho_M, T1, rho_A, bounces = _radii_and_bounces(
        T, A, f, G, memory_limit, lambda times_T: spectral_radius_blocks(times_T, D), lit)
    seen = [np.einsum("pik,pk->pi", colour.camera, b.reshape(-1, 3)) for b in bounces]
    per_channel = [radiosity.light_shares([s[:, c] for s in seen]) for c in range(3)]
    return GroundTruthStats(rho_M, rho_A, radiosity.light_shares(seen), T1, per_channel)
