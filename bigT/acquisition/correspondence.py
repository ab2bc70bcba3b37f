"""Which camera pixels form the camera super-pixel of each projector super-pixel
(paper §6.1): :class:`Correspondence`.

Without Gray code, a camera pixel belongs to the projector super-pixel with its largest
response ("the group of camera pixels that a projector super-pixel has the maximum
response on"); with Gray code, to the super-pixel its code decodes to. A camera
super-pixel's value is the mean of its pixels, so T comes out square, its diagonal the
direct response. Projector super-pixels no camera pixel belongs to are *unseen*: their
row and column of T are left empty, and the engine leaves such pixels out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import config
from ..storage import PixelOrder
from .captures import Captures
from .manifest import Manifest
from .patterns import decode_graycode


@dataclass(frozen=True)
class Correspondence:
    """Camera pixel -> projector super-pixel.

    Attributes
    ----------
    labels : ndarray, shape (Hc, Wc), int64
        Row-major super-pixel index of the grid, -1 for pixels in no group.
    grid : (int, int), the projector's super-pixel grid
    source : {"graycode", "maximum response"}
    """

    labels: np.ndarray
    grid: tuple[int, int]
    source: str

    @property
    def counts(self) -> np.ndarray:
        """Camera pixels of each super-pixel's group, shape (n,), grid (row-major) order."""
        kept = self.labels[self.labels >= 0]
        return np.bincount(kept, minlength=self.grid[0] * self.grid[1])

    @property
    def seen(self) -> np.ndarray:
        """(n,) bool, grid order: super-pixels with at least one camera pixel."""
        return self.counts > 0

    def reducer(self, order: PixelOrder) -> "GroupMeans":
        return GroupMeans(self, order)


class GroupMeans:
    """Camera image -> camera super-pixel values in matrix order (the mean of each group).

    Parameters
    ----------
    correspondence : Correspondence
    order : PixelOrder of T (its image shape is the super-pixel grid)

    Attributes
    ----------
    n : int
    counts : ndarray, shape (n,), int64, matrix order: camera pixels of each group
    seen : ndarray, shape (n,), bool, matrix order: groups with at least one pixel
    """

    def __init__(self, correspondence: Correspondence, order: PixelOrder):
        labels = correspondence.labels.ravel()
        self._pixels = np.flatnonzero(labels >= 0)
        # matrix index of each grouped pixel: grid index -> matrix index
        self._rows = order.inverse_permutation[labels[self._pixels]]
        self.n = order.n
        self.counts = np.bincount(self._rows, minlength=self.n)
        self.seen = self.counts > 0
        self._scale = np.divide(1.0, self.counts, out=np.zeros(self.n), where=self.seen)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Returns ndarray, shape (n,), float64: 0 on unseen rows."""
        sums = np.bincount(self._rows, weights=image.ravel()[self._pixels], minlength=self.n)
        return sums * self._scale


def from_graycode(manifest: Manifest, captures: Captures) -> Correspondence:
    """Decode the Gray-code captures (thresholds relative to the camera's noise and each
    pixel's contrast, :func:`.patterns.decode_graycode`)."""
    labels = decode_graycode(manifest, captures.linear, noise=captures.noise())
    return Correspondence(labels, manifest.grid, "graycode")


def _strongest(captures: Captures, patterns, key) -> tuple[np.ndarray, np.ndarray]:
    """Per camera pixel, the largest signal over ``patterns`` and ``key(pattern)`` of the
    pattern giving it; one capture in memory at a time."""
    best = np.zeros(captures.shape)
    which = np.full(captures.shape, -1, dtype=np.int64)
    for p in patterns:
        s = captures.signal(p)
        larger = s > best
        best[larger] = s[larger]
        which[larger] = key(p)
    return best, which


def from_maximum_response(manifest: Manifest, captures: Captures, white: np.ndarray,
                          pixel_floor: float, *, progress=lambda it: it) -> Correspondence:
    """Each camera pixel to the super-pixel with its largest response (brute force), or
    to the crossing of the row and column stripes with their largest (stripes).

    Parameters
    ----------
    white : ndarray, shape (Hc, Wc), the white capture less the black level
    pixel_floor : float, responses at or below it are noise
    progress : wraps the iterable of patterns read

    Pixels whose largest response is below ``config.ACQUIRE_MIN_DIRECT_SHARE`` of their
    white signal (lit by interreflection only) or at the noise floor stay out (-1).
    """
    def direct(best):
        return (best > pixel_floor) & (best >= config.ACQUIRE_MIN_DIRECT_SHARE * white)

    gw = manifest.grid[1]
    if manifest.method == "brute-force":
        best, index = _strongest(captures, progress(manifest.of_kind("superpixel")),
                                 lambda p: p.index)
        labels = np.where(direct(best), index, -1)
    else:
        best_r, r = _strongest(captures, progress(manifest.of_kind("row-stripe")),
                               lambda p: p.band)
        best_c, c = _strongest(captures, progress(manifest.of_kind("col-stripe")),
                               lambda p: p.band)
        labels = np.where(direct(best_r) & direct(best_c), r * gw + c, -1)
    return Correspondence(labels, manifest.grid, "maximum response")
