"""Mapping between images and matrix indices.

A transport matrix maps projector pixels to camera pixels; the matrix index of a
pixel depends on the *pixel order* recorded in the store:

``"row-major"``
    index = r * W + c, the order of ``image.ravel()``.
``"tile-major"``
    the image is cut into tiles of ``image_tile = (th, tw)`` pixels (the last tile row
    and column may be smaller); tiles are numbered in row-major order and the pixels
    of one tile are contiguous, in row-major order inside the tile. Far-apart image
    regions then fall into different matrix tiles, so more matrix tiles are zero
    (docs/DESIGN.md, "Pixel order matters").

The permutation stored with a matrix is ``perm`` with ``matrix_index k <-> row-major
pixel perm[k]``; it is derived from the image shape and tile, never stored twice.

Colour (``channels = 3``): the matrix index of channel c (0, 1, 2 = R, G, B) of the
pixel numbered p in the order above is 3·p + c, so a pixel's three channels are
adjacent and its 3×3 colour-mixing block is a diagonal block of T. An (H, W, 3) image
raveled row-major is exactly the row-major order's numbering, 3·(y·W + x) + c, and
:attr:`PixelOrder.permutation` numbers *values* (pixel and channel) rather than pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..config import DEFAULT_IMAGE_TILE
from ..errors import ImageError, ShapeMismatchError

PIXEL_ORDERS = ("row-major", "tile-major")
#: Values per pixel a transport may have: grey, or R, G, B.
CHANNEL_COUNTS = (1, 3)


@dataclass(frozen=True)
class PixelOrder:
    """How the pixels of an ``image_shape`` image are numbered in a matrix.

    Parameters
    ----------
    image_shape : (int, int)
        (H, W) of the image; the matrix side is n = H * W.
    order : {"row-major", "tile-major"}
    image_tile : (int, int)
        (th, tw) of one image tile; used by "tile-major" only.
    channels : {1, 3}
        Values per pixel: 1 for grey, 3 for R, G, B (the matrix side is then 3 H W).
    """

    image_shape: tuple[int, int]
    order: str = "row-major"
    image_tile: tuple[int, int] = field(default=DEFAULT_IMAGE_TILE)
    channels: int = 1

    def __post_init__(self):
        shape = tuple(int(s) for s in self.image_shape)
        tile = tuple(int(s) for s in self.image_tile)
        if len(shape) != 2 or min(shape) < 1:
            raise ShapeMismatchError(f"image_shape must be (H, W) with H, W >= 1, got {self.image_shape}")
        if self.order not in PIXEL_ORDERS:
            raise ValueError(f"pixel_order must be one of {PIXEL_ORDERS}, got {self.order!r}")
        if len(tile) != 2 or min(tile) < 1:
            raise ShapeMismatchError(f"image_tile must be (th, tw) with th, tw >= 1, got {self.image_tile}")
        if isinstance(self.channels, bool) or self.channels not in CHANNEL_COUNTS:
            raise ShapeMismatchError(f"channels must be 1 (grey) or 3 (R, G, B), got "
                                     f"{self.channels!r:.60}")
        object.__setattr__(self, "image_shape", shape)
        object.__setattr__(self, "image_tile", tile)

    @property
    def pixels(self) -> int:
        """Number of pixels, H * W."""
        return self.image_shape[0] * self.image_shape[1]

    @property
    def n(self) -> int:
        """Number of values (pixels times channels), the matrix side."""
        return self.pixels * self.channels

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """Shape of one image: (H, W) for grey, (H, W, 3) for colour."""
        return self.image_shape if self.channels == 1 else (*self.image_shape, self.channels)

    @cached_property
    def pixel_permutation(self) -> np.ndarray:
        """(H W,) int64: row-major pixel index of each pixel number."""
        H, W = self.image_shape
        if self.order == "row-major":
            return np.arange(H * W, dtype=np.int64)
        th, tw = self.image_tile
        rows, cols = np.divmod(np.arange(H * W, dtype=np.int64), W)
        # Sort pixels by (tile row, tile col, row in tile, col in tile).
        key = np.lexsort((cols % tw, rows % th, cols // tw, rows // th))
        return key.astype(np.int64)

    @cached_property
    def permutation(self) -> np.ndarray:
        """(n,) int64: row-major value index (of the raveled (H, W) or (H, W, C)
        image) of each matrix index."""
        if self.channels == 1:
            return self.pixel_permutation
        c = self.channels  # 3 p + k <- 3 perm[p] + k: a pixel's channels stay adjacent
        return (c * self.pixel_permutation[:, None] + np.arange(c)).ravel()

    @cached_property
    def inverse_permutation(self) -> np.ndarray:
        """(n,) int64: matrix index of each row-major pixel index."""
        inv = np.empty(self.n, dtype=np.int64)
        inv[self.permutation] = np.arange(self.n, dtype=np.int64)
        return inv

    def to_matrix(self, images: np.ndarray) -> np.ndarray:
        """Images to matrix-ordered vectors.

        Parameters
        ----------
        images : ndarray, shape ``frame_shape`` or (K, *frame_shape)
            (H, W) / (K, H, W) grey, (H, W, 3) / (K, H, W, 3) colour.

        Returns
        -------
        ndarray, shape (n,) or (n, K)
        """
        images = np.asarray(images)
        fs = self.frame_shape
        single = images.ndim == len(fs)
        if images.shape[images.ndim - len(fs):] != fs or images.ndim not in (len(fs), len(fs) + 1):
            raise ImageError(f"image of shape {images.shape} does not match the matrix's "
                             f"image shape {fs}")
        flat = images.reshape(-1, self.n)[:, self.permutation]
        return flat[0] if single else np.ascontiguousarray(flat.T)

    def to_images(self, vectors: np.ndarray) -> np.ndarray:
        """Matrix-ordered vectors back to images.

        Parameters
        ----------
        vectors : ndarray, shape (n,) or (n, K)

        Returns
        -------
        ndarray, shape ``frame_shape`` or (K, *frame_shape)
        """
        vectors = np.asarray(vectors)
        if vectors.shape[0] != self.n or vectors.ndim not in (1, 2):
            raise ShapeMismatchError(f"vectors of shape {vectors.shape} do not have n = {self.n} rows")
        cols = vectors.reshape(self.n, -1).T
        images = cols[:, self.inverse_permutation].reshape(-1, *self.frame_shape)
        return images[0] if vectors.ndim == 1 else images

    def to_attrs(self) -> dict:
        """JSON-serialisable description stored in the zarr attributes (``channels``
        only for colour, so a grey store's attributes are as they always were)."""
        out = {"image_shape": list(self.image_shape), "pixel_order": self.order,
               "image_tile": list(self.image_tile)}
        if self.channels != 1:
            out["channels"] = self.channels
        return out

    @classmethod
    def from_attrs(cls, attrs: dict) -> "PixelOrder | None":
        """Inverse of :meth:`to_attrs`; None when the matrix maps no image.

        Raises
        ------
        ShapeMismatchError
            A value of the wrong JSON type: sizes that are not integers (3.5), an
            order that is not one of :data:`PIXEL_ORDERS`.
        """
        if not attrs.get("image_shape"):
            return None
        order = attrs.get("pixel_order", "row-major")
        if not isinstance(order, str) or order not in PIXEL_ORDERS:
            raise ShapeMismatchError(f"pixel_order must be one of {PIXEL_ORDERS}, got {order!r:.60}")
        return cls(_int_pair(attrs["image_shape"], "image_shape"), order,
                   _int_pair(attrs.get("image_tile") or list(DEFAULT_IMAGE_TILE), "image_tile"),
                   attrs.get("channels", 1))


def _int_pair(value, name: str) -> tuple[int, int]:
    """``value`` as (int, int) when it is a JSON list of two integers (not 3.5, not
    true); ShapeMismatchError otherwise."""
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) for v in value)):
        raise ShapeMismatchError(f"{name} must be two integers, got {value!r:.60}")
    return value[0], value[1]
