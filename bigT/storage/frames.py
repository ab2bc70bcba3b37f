"""Images and the matrix's vectors: a store's pixel order applied to frames.

Images are (H, W) or (K, H, W) float arrays in row-major image layout; the matrix
numbers pixels in the store's :class:`PixelOrder` (tile-major by default). Everything
that multiplies a store by images (compensation, relighting, the target-error probes)
converts through here: small batches with PixelOrder's numpy reference, large ones
with the one-pass kernels of :mod:`bigT.kernels.pixels`.
"""

from __future__ import annotations

import numpy as np

from .. import config
from ..errors import ImageError
from ..kernels import pixels
from .pixel_order import PixelOrder


def pixel_order_of(store, image_shape=None) -> PixelOrder:
    """The store's pixel order; a row-major order of ``image_shape`` when it records none."""
    order = getattr(store, "pixel_order", None)
    if order is not None:
        return order
    n = store.shape[1]
    if image_shape is None or int(np.prod(image_shape)) != n:
        raise ImageError(f"the store records no image shape and images of shape "
                         f"{None if image_shape is None else tuple(image_shape)} do not have "
                         f"n = {n} pixels", getattr(store, "path", None))
    return PixelOrder(tuple(image_shape))


def as_frames(images, store, name="<array>"):
    """(K, H, W) float64 frames and whether the input was one (H, W) image."""
    images = np.asarray(images, dtype=np.float64)
    if images.ndim not in (2, 3):
        raise ImageError(f"images must be (H, W) or (K, H, W), got shape {images.shape}", name)
    single = images.ndim == 2
    frames = images[None] if single else images
    order = pixel_order_of(store, frames.shape[1:])
    if frames.shape[1:] != order.image_shape:
        raise ImageError(f"image of shape {frames.shape[1:]} does not match the transport's "
                         f"image shape {order.image_shape}", name)
    if not np.isfinite(frames).all():
        raise ImageError("images contain NaN or Inf", name)
    return frames, single, order


def to_vectors(frames: np.ndarray, order: PixelOrder, dtype) -> np.ndarray:
    """(K, H, W) frames -> (n, K) matrix-ordered columns of ``dtype``."""
    return frames_to_matrix(frames[None] if frames.ndim == 2 else frames, order, dtype)


def to_frames(vectors: np.ndarray, order: PixelOrder, clip=None) -> np.ndarray:
    """(n, K) matrix-ordered columns -> (K, H, W) float64 frames (clipped to ``clip``)."""
    return matrix_to_frames(vectors, order, clip)[0]


def frames_to_matrix(frames: np.ndarray, order, dtype, n_threads: int = 1) -> np.ndarray:
    """(K, H, W) frames -> (n, K) C-contiguous batch in the store's pixel order
    (``n_threads`` threads over row ranges of the batch)."""
    K = frames.shape[0]
    src = np.ascontiguousarray(frames.reshape(K, -1))
    out = np.empty((order.n, K), dtype=dtype)
    if out.size <= config.KERNEL_NUMPY_MAX_WORK:
        out[...] = order.to_matrix(frames).reshape(order.n, K)  # the numpy reference
    else:
        pixels.gather(src, order.permutation, out, n_threads)
    return out


def matrix_to_frames(Y: np.ndarray, order, clip=None, *, dtype=np.float64,
                     n_threads: int = 1) -> tuple[np.ndarray, int, int]:
    """(n, K) batch -> (K, H, W) frames of ``dtype``, clipped to ``clip`` = (lo, hi)
    (either may be None); returns the frames and the counts of values below lo and
    above hi. ``n_threads`` threads over row ranges of the batch (their pixels are
    disjoint)."""
    Y = np.ascontiguousarray(Y.reshape(order.n, -1))
    K = Y.shape[1]
    lo, hi = (None, None) if clip is None else clip
    out = np.empty((K, order.n), dtype=dtype)
    if out.size <= config.KERNEL_NUMPY_MAX_WORK:
        V = Y.astype(np.float64)
        below = 0 if lo is None else int(np.count_nonzero(V < lo))
        above = 0 if hi is None else int(np.count_nonzero(V > hi))
        if lo is not None or hi is not None:
            V = np.clip(V, lo, hi)
        out[...] = order.to_images(V).reshape(K, order.n)  # the numpy reference
    else:
        below, above = pixels.scatter(Y, order.permutation, (lo, hi), out, n_threads)
    return out.reshape(K, *order.image_shape), int(below), int(above)
