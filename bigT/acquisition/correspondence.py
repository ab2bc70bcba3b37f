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

    For a colour T (``order.channels == 3``) the image is (Hc, Wc, 3) and row 3 p + i
    is the mean of camera channel i over super-pixel p's group.

    Parameters
    ----------
    correspondence : Correspondence
    order : PixelOrder of T (its image shape is the super-pixel grid)

    Attributes
    ----------
    n : int, T's side (super-pixels times channels)
    counts : ndarray, shape (n,), int64, matrix order: camera pixels of each row's group
    seen : ndarray, shape (n,), bool, matrix order: rows whose group has a pixel
    seen_superpixels : int, super-pixels whose group has a pixel
    """

    def __init__(self, correspondence: Correspondence, order: PixelOrder):
        labels = correspondence.labels.ravel()
        self._pixels = np.flatnonzero(labels >= 0)
        self._channels = c = order.channels
        # T's pixel number of each grouped camera pixel: grid index g -> value 3 g (its
        # first channel) -> matrix index 3 p -> p
        self._rows = order.inverse_permutation[c * labels[self._pixels]] // c
        self.n = order.n
        per_pixel = np.bincount(self._rows, minlength=order.pixels)
        self.counts = np.repeat(per_pixel, c)
        self.seen = self.counts > 0
        self.seen_superpixels = int(np.count_nonzero(per_pixel))
        self._scale = np.divide(1.0, per_pixel, out=np.zeros(order.pixels),
                                where=per_pixel > 0)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """``image`` of shape (Hc, Wc), or (Hc, Wc, 3) for a colour T.

        Returns ndarray, shape (n,), float64: 0 on unseen rows."""
        values = image.reshape(-1, self._channels)[self._pixels]
        means = np.empty((len(self._scale), self._channels))
        for i in range(self._channels):
            means[:, i] = np.bincount(self._rows, weights=values[:, i],
                                      minlength=len(self._scale)) * self._scale
        return means.ravel()


def from_graycode(manifest: Manifest, captures: Captures) -> Correspondence:
    """Decode the Gray-code captures (thresholds relative to the camera's noise and each
    pixel's contrast, :func:`.patterns.decode_graycode`)."""
    # geometry only: a colour capture's grey view, and that view's noise
    labels = decode_graycode(manifest, captures.linear_grey, noise=captures.noise())
    return Correspondence(labels, manifest.grid, "graycode")


def _responses(captures: Captures, patterns, key):
    """(key, grey response) of each place ``key(pattern)`` lights, in order: a grey
    pattern's signal, or the sum of its primaries' (consecutive in a colour set: the
    place lit in white), each capture through the grey view. One capture in memory at
    a time."""
    current, total = None, None
    for p in patterns:
        k = key(p)
        if k != current and total is not None:
            yield current, total
            total = None
        s = captures.signal_grey(p)
        current, total = k, s if total is None else total + s
    if total is not None:
        yield current, total


def _strongest(captures: Captures, patterns, key) -> tuple[np.ndarray, np.ndarray]:
    """Per camera pixel, the largest response (:func:`_responses`) over ``patterns``
    and the key of the place giving it."""
    best = np.zeros(captures.shape)
    which = np.full(captures.shape, -1, dtype=np.int64)
    for k, s in _responses(captures, patterns, key):
        larger = s > best
        best[larger] = s[larger]
        which[larger] = k
    return best, which


def from_maximum_response(manifest: Manifest, captures: Captures, white: np.ndarray,
                          pixel_floor: float, *, progress=lambda it: it) -> Correspondence:
    """Each camera pixel to the super-pixel with its largest response (brute force), or
    to the crossing of the row and column stripes with their largest (stripes).

    Parameters
    ----------
    white : ndarray, shape (Hc, Wc), the white capture less the black level (grey view)
    pixel_floor : float, responses at or below it are noise (of a colour set: of the sum
        of a place's three primaries, :meth:`Captures.pixel_floor` of 3 summed)
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
