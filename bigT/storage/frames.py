"""Images and the matrix's vectors: a store's pixel order applied to frames.

Images are (H, W) or (K, H, W) float arrays in row-major image layout, (H, W, 3) or
(K, H, W, 3) for a colour store; the matrix numbers values in the store's
:class:`PixelOrder` (tile-major by default; a pixel's channels adjacent, 3 p + c). Everything
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
    """The store's pixel order; a row-major grey order of ``image_shape`` when it
    records none."""
    order = getattr(store, "pixel_order", None)
    if order is not None:
        return order
    n = store.shape[1]
    if image_shape is None or int(np.prod(image_shape)) != n:
        raise ImageError(f"the store records no image shape and images of shape "
                         f"{None if image_shape is None else tuple(image_shape)} do not have "
                         f"n = {n} pixels", getattr(store, "path", None))
    return PixelOrder(tuple(image_shape))


def describe_frame(shape) -> str:
    """``"grey (H, W)"`` or ``"colour (H, W, 3)"``: an image's shape as a user reads it."""
    shape = tuple(shape)
    return f"{'colour' if len(shape) == 3 else 'grey'} {shape}"


def as_frames(images, store, name="<array>"):
    """(K, *frame_shape) float64 frames and whether the input was one image.

    Grey stores take (H, W) or (K, H, W); colour ones (H, W, 3) or (K, H, W, 3). A grey
    image given to a colour store, or the reverse, is an ImageError saying which.
    """
    images = np.asarray(images, dtype=np.float64)
    channels = getattr(store, "channels", 1)
    frame_ndim = 2 if channels == 1 else 3
    if images.ndim not in (frame_ndim, frame_ndim + 1):
        raise ImageError(_shape_problem(images.shape, channels), name)
    single = images.ndim == frame_ndim
    frames = images[None] if single else images
    order = pixel_order_of(store, frames.shape[1:])
    if frames.shape[1:] != order.frame_shape:
        raise ImageError(_shape_problem(images.shape, channels, order), name)
    if not np.isfinite(frames).all():
        raise ImageError("images contain NaN or Inf", name)
    return frames, single, order


def _shape_problem(shape, channels: int, order: PixelOrder | None = None) -> str:
    """Why an array of ``shape`` is not an image (or batch) for a ``channels`` store
    (of ``order``, when known)."""
    shape = tuple(shape)
    hw = None if order is None else order.image_shape
    if channels == 3 and (shape[-1] != 3 or shape[-3:-1] != hw and shape[-2:] == hw):
        return (f"grey images of shape {shape} given to a colour transport (3 channels): give "
                f"(H, W, 3) or (K, H, W, 3) RGB images")
    if channels == 1 and shape[-1] == 3 and len(shape) in (3, 4) and (
            hw is None or shape[-3:-1] == hw):
        return (f"colour images of shape {shape} given to a grey transport: give (H, W) or "
                f"(K, H, W) grey images")
    if order is not None:
        return (f"image of shape {shape} does not match the transport's image shape "
                f"{order.frame_shape}")
    want = "(H, W) or (K, H, W)" if channels == 1 else "(H, W, 3) or (K, H, W, 3)"
    return f"images must be {want}, got shape {shape}"


def to_vectors(frames: np.ndarray, order: PixelOrder, dtype) -> np.ndarray:
    """(K, *frame_shape) frames (or one frame) -> (n, K) matrix-ordered columns of
    ``dtype``."""
    single = frames.ndim == len(order.frame_shape)
    return frames_to_matrix(frames[None] if single else frames, order, dtype)


def to_frames(vectors: np.ndarray, order: PixelOrder, clip=None) -> np.ndarray:
    """(n, K) matrix-ordered columns -> (K, *frame_shape) float64 frames (clipped to
    ``clip``)."""
    return matrix_to_frames(vectors, order, clip)[0]


def frames_to_matrix(frames: np.ndarray, order, dtype, n_threads: int = 1) -> np.ndarray:
    """(K, *frame_shape) frames -> (n, K) C-contiguous batch in the store's pixel
    order (``n_threads`` threads over row ranges of the batch)."""
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
    """(n, K) batch -> (K, *frame_shape) frames of ``dtype``, clipped to ``clip`` = (lo, hi)
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
    return out.reshape(K, *order.frame_shape), int(below), int(above)
