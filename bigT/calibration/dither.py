"""Dither thresholds for quantising a projector image.

A value that falls between two integer codes k and k + 1 at fraction p (0 <= p < 1 of
the way, measured in *linear light*, see :meth:`ProjectorResponse.encode`) is sent as
k + 1 where p exceeds the pixel's threshold t, else as k. With t uniform on [0, 1) the
expected light is exactly the wanted one; the two kinds differ in how t varies:

``ordered``
    The 8 x 8 Bayer matrix (Bayer 1973), tiled over the image: thresholds
    (B + 0.5) / 64 with B the matrix's entries 0..63, so any 8 x 8 block holds every
    threshold once and a uniform area's mean is right to 1/64 of a code step. The
    pattern is the same in every frame, so a video does not flicker.
``random``
    Independent uniform thresholds from a seeded generator: no pattern, white noise of
    at most one code step, different per seed.
"""

from __future__ import annotations

import numpy as np

#: Dither kinds :meth:`ProjectorResponse.encode` accepts (``False`` and ``"none"`` round).
DITHER_KINDS = ("none", "ordered", "random")


def bayer_matrix(order: int = 3) -> np.ndarray:
    """The (2^order, 2^order) Bayer index matrix, entries 0 .. 4^order - 1.

    Built by the recursion B_{2n} = [[4B, 4B + 2], [4B + 3, 4B + 1]].
    """
    matrix = np.zeros((1, 1), dtype=np.int64)
    for _ in range(order):
        matrix = np.block([[4 * matrix, 4 * matrix + 2], [4 * matrix + 3, 4 * matrix + 1]])
    return matrix


def thresholds(kind: str, spatial_shape: tuple[int, ...], seed: int = 0) -> np.ndarray:
    """Per-pixel thresholds in (0, 1) of ``spatial_shape``.

    Parameters
    ----------
    kind : ``"ordered"`` or ``"random"``
    spatial_shape : tuple of int
        The image's pixel grid, ``(H, W)`` or ``(K, H, W)`` for frames (the Bayer matrix
        tiles the last two axes; a 1-D shape takes its first row).
    seed : int, the generator's seed for ``"random"``

    Returns
    -------
    ndarray of float64, shape ``spatial_shape``
    """
    if kind == "random":
        return np.random.default_rng(seed).random(spatial_shape)
    if kind != "ordered":
        raise ValueError(f"unknown dither kind {kind!r} (use {', '.join(DITHER_KINDS)})")
    matrix = (bayer_matrix() + 0.5) / 64.0
    if len(spatial_shape) == 0:
        return np.full((), matrix[0, 0])
    if len(spatial_shape) == 1:
        return np.resize(matrix[0], spatial_shape)
    H, W = spatial_shape[-2:]
    tiled = np.tile(matrix, (-(-H // 8), -(-W // 8)))[:H, :W]
    return np.broadcast_to(tiled, spatial_shape)
