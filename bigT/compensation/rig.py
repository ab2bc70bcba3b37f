"""The rig a transport was acquired on: what ``bigT acquire build`` stores beside T, read
back so that ``compensate`` works at the camera's and the projector's own resolutions.

``acquire build`` of a projector of H x W pixels in s x s super-pixels seen by a camera
of Hc x Wc pixels makes T over the (H/s, W/s) super-pixel grid, and saves beside it

* the correspondence, ``T.zarr/acquisition/correspondence.npy``: (Hc, Wc) int32, each
  camera pixel's super-pixel (its row-major index on the grid), -1 outside every
  group (:func:`load_correspondence`);
* the rig's sizes in T's metadata ``acquisition`` (``projector``, ``superpixel``,
  ``camera``);
* the projector's fitted response, ``T.zarr/projector_response.json``, named by T's
  metadata key ``projector_response`` (:func:`stored_response_path`).

:class:`RigGeometry` maps a desired camera image onto the camera super-pixels (the mean
of each group's pixels: what T's rows are) and the super-pixel values the compensation
gives onto the projector's pixels (each super-pixel's pixels take its value, or a
bilinear interpolation between their centres), so a user hands ``compensate`` what the
audience should see and gets what the projector must show.

This module is the reader of those files for every layer above storage (acquisition's
build writes them and imports their names from here; compensation may not import
acquisition).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import ImageError, StoreError
from ..storage import as_location

#: T's metadata key of the acquisition's settings (``projector``, ``superpixel``, ``camera``).
ACQUISITION_KEY = "acquisition"
#: The correspondence map's file, inside the ``acquisition`` folder of T's store.
CORRESPONDENCE = "correspondence.npy"
#: T's metadata key naming the projector response stored with it.
PROJECTOR_RESPONSE_KEY = "projector_response"
#: The projector response's file in T's store when the metadata names none.
PROJECTOR_RESPONSE_FILE = "projector_response.json"


def correspondence_path(store):
    """``STORE/acquisition/correspondence.npy`` (a Path, or an ObjectPath in a bucket)."""
    return as_location(store) / ACQUISITION_KEY / CORRESPONDENCE


def load_correspondence(store) -> np.ndarray:
    """The correspondence map saved with an acquired T, shape (Hc, Wc), int32: each
    camera pixel's super-pixel (row-major on the grid), -1 outside every group.

    Raises
    ------
    StoreError
        The store holds none (it was not built by ``bigT acquire build``).
    """
    path = correspondence_path(store)
    if not path.is_file():
        raise StoreError("holds no correspondence map (not built by bigT acquire build)",
                         as_location(store))
    if not isinstance(path, Path):  # an object: read whole (a camera frame of int32)
        import io

        return np.load(io.BytesIO(path.read_bytes(CORRESPONDENCE_MAX_BYTES)),
                       allow_pickle=False)
    return np.load(path, allow_pickle=False)


#: The largest correspondence map read from object storage: an int32 per camera pixel
#: of a 65536^2 camera would be 16 GiB; 1 GiB is a 16k x 16k camera.
CORRESPONDENCE_MAX_BYTES = 1 << 30


def _size(text) -> str:
    return f"{text[0]}x{text[1]}"


@dataclass(frozen=True, eq=False)
class RigGeometry:
    """The camera's, the super-pixels' and the projector's resolutions, and the maps
    between them.

    Attributes
    ----------
    labels : ndarray, shape (Hc, Wc), int64
        Each camera pixel's super-pixel, row-major on ``grid``; -1 outside every group.
    grid : (int, int), the super-pixel grid (Hs, Ws): T's image shape
    superpixel : int, the side s of a super-pixel in projector pixels
    """

    labels: np.ndarray
    grid: tuple[int, int]
    superpixel: int

    @property
    def camera(self) -> tuple[int, int]:
        """(Hc, Wc), the camera's image."""
        return tuple(int(v) for v in self.labels.shape)

    @property
    def projector(self) -> tuple[int, int]:
        """(H, W) = (Hs s, Ws s), the projector's image."""
        return (self.grid[0] * self.superpixel, self.grid[1] * self.superpixel)

    def describe(self) -> str:
        """``camera image 40x52 -> 12x16 super-pixels -> projector 24x32``."""
        return (f"camera image {_size(self.camera)} -> {_size(self.grid)} super-pixels -> "
                f"projector {_size(self.projector)}")

    @cached_property
    def _averaging(self):
        """(Hs Ws, Hc Wc) sparse matrix: row g averages the camera pixels of group g
        (a group no pixel sees: a zero row)."""
        import scipy.sparse as sp  # ~0.1 s, only for a rig's camera images

        flat = self.labels.reshape(-1)
        inside = np.flatnonzero(flat >= 0)
        groups = flat[inside]
        n = self.grid[0] * self.grid[1]
        counts = np.bincount(groups, minlength=n).astype(np.float64)
        weights = 1.0 / counts[groups]
        return sp.csr_array((weights, (groups, inside)), shape=(n, flat.size))

    def to_superpixels(self, frames: np.ndarray) -> np.ndarray:
        """Camera frames onto the camera super-pixels: each group's mean.

        Parameters
        ----------
        frames : ndarray, shape (K, Hc, Wc) or (K, Hc, Wc, 3)

        Returns
        -------
        ndarray, shape (K, Hs, Ws) or (K, Hs, Ws, 3), of ``frames``' float dtype (a
        super-pixel no camera pixel sees is 0)
        """
        K, tail = frames.shape[0], frames.shape[3:]
        channels = int(np.prod(tail, dtype=np.int64))
        # (Hc Wc, K C): one sparse product for the batch
        flat = np.moveaxis(frames.reshape(K, -1, channels), 0, 1).reshape(-1, K * channels)
        means = self._averaging @ flat
        out = np.moveaxis(means.reshape(-1, K, channels), 1, 0).reshape(K, *self.grid, *tail)
        return out.astype(frames.dtype if frames.dtype.kind == "f" else np.float64, copy=False)

    def to_camera(self, frames: np.ndarray) -> np.ndarray:
        """Super-pixel frames back onto the camera's pixels (each pixel its group's
        value; 0 outside every group): (K, Hs, Ws[, 3]) -> (K, Hc, Wc[, 3])."""
        K, tail = frames.shape[0], frames.shape[3:]
        flat = frames.reshape(K, -1, *tail)
        labels = self.labels.reshape(-1)
        out = flat[:, np.maximum(labels, 0)]
        out[:, labels < 0] = 0
        return out.reshape(K, *self.camera, *tail)

    def to_projector(self, frames: np.ndarray, smooth: bool = False) -> np.ndarray:
        """Super-pixel frames onto the projector's pixels.

        Parameters
        ----------
        frames : ndarray, shape (K, Hs, Ws) or (K, Hs, Ws, 3)
        smooth : bool
            False: each super-pixel's s x s pixels take its value (what T was measured
            with). True: bilinear interpolation between the super-pixels' centres
            (edges held), so the projector shows no s x s blocks.

        Returns
        -------
        ndarray, shape (K, H, W) or (K, H, W, 3), ``frames``' dtype
        """
        s = self.superpixel
        if not smooth:
            return np.repeat(np.repeat(frames, s, axis=1), s, axis=2)
        rows = _bilinear_weights(self.grid[0], s)
        cols = _bilinear_weights(self.grid[1], s)
        out = _interpolate(frames, *rows, axis=1)
        return _interpolate(out, *cols, axis=2).astype(frames.dtype, copy=False)

    def block_means(self, frames: np.ndarray) -> np.ndarray:
        """Projector frames back onto the super-pixels: the mean of each s x s block
        (the light a super-pixel sends, as T's column measured it):
        (K, H, W[, 3]) -> (K, Hs, Ws[, 3])."""
        s = self.superpixel
        K, tail = frames.shape[0], frames.shape[3:]
        blocks = frames.reshape(K, self.grid[0], s, self.grid[1], s, *tail)
        return blocks.mean(axis=(2, 4))


def _bilinear_weights(n: int, s: int):
    """For the n s pixels of an axis cut into n cells of s: each pixel's two nearest
    cell centres (i0, i1) and the weight of i1."""
    centre = (np.arange(n * s) + 0.5) / s - 0.5  # the pixel's centre in cell units
    centre = np.clip(centre, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(centre).astype(np.int64), max(n - 2, 0))
    i1 = np.minimum(i0 + 1, n - 1)
    return i0, i1, centre - i0


def _interpolate(frames, i0, i1, t, axis):
    shape = [1] * frames.ndim
    shape[axis] = t.size
    t = t.reshape(shape)
    return np.take(frames, i0, axis=axis) * (1 - t) + np.take(frames, i1, axis=axis) * t


def rig_geometry(T) -> RigGeometry | None:
    """The geometry of the rig T was acquired on: None when T records none (a
    synthetic scene, a converted matrix) or holds no correspondence map.

    Raises
    ------
    StoreError
        The correspondence does not fit T (its labels outside T's grid), or the
        recorded sizes disagree with T's image.
    """
    settings = (getattr(T, "metadata", None) or {}).get(ACQUISITION_KEY)
    order = getattr(T, "pixel_order", None)
    if not isinstance(settings, dict) or order is None or not correspondence_path(T.path).is_file():
        return None
    labels = load_correspondence(T.path).astype(np.int64)
    grid = tuple(int(v) for v in order.image_shape)
    superpixel = int(settings.get("superpixel", 1))
    projector = tuple(int(v) for v in settings.get("projector", ()))
    if projector and projector != (grid[0] * superpixel, grid[1] * superpixel):
        raise StoreError(f"records a {_size(projector)} projector in {superpixel}x"
                         f"{superpixel} super-pixels, but its image is {_size(grid)}", T.path)
    if labels.ndim != 2 or labels.size == 0 or labels.max() >= grid[0] * grid[1] or labels.min() < -1:
        raise StoreError(f"its correspondence map ({correspondence_path(T.path)}) does not fit "
                         f"its {_size(grid)} super-pixels", T.path)
    return RigGeometry(labels, grid, superpixel)


def stored_response_path(T) -> Path | None:
    """The projector response stored with T (``T.zarr/projector_response.json``, or
    the file T's metadata ``projector_response`` names inside the store), None when
    it holds none."""
    name = (getattr(T, "metadata", None) or {}).get(PROJECTOR_RESPONSE_KEY)
    candidates = [name] if isinstance(name, str) else []
    candidates.append(PROJECTOR_RESPONSE_FILE)
    for candidate in candidates:
        path = as_location(T.path) / candidate
        if path.is_file():
            return path
    return None


def recorded_transport(X) -> Path | None:
    """The T an inverse store was computed from (its record's fingerprint, what
    ``bigT info`` shows), when that store still exists; None for an X that records
    none (a converted matrix)."""
    from ..storage import InverseStore

    root = getattr(X, "redirected_from", None) or getattr(X, "path", None)
    if root is None:
        return None
    try:
        record = InverseStore(root).read_record()
    except (StoreError, OSError, ValueError):
        return None
    params = {} if record is None else record.params
    path = (params.get("T") or {}).get("path") if isinstance(params.get("T"), dict) else None
    if not isinstance(path, str):
        return None
    try:
        location = as_location(path)
        found = (location / "zarr.json").is_file()
    except (StoreError, OSError, ValueError):
        return None
    return location if found else None


def check_camera_or_grid(found: tuple[int, ...], geometry: RigGeometry, path) -> str:
    """Which image a frame of (H, W) ``found`` is: ``"camera"`` or ``"superpixels"``.

    Raises
    ------
    ImageError
        Neither size, in one line naming both accepted ones.
    """
    size = tuple(int(v) for v in found[:2])
    if size == geometry.camera:
        return "camera"
    if size == geometry.grid:
        return "superpixels"
    raise ImageError(f"is {_size(size)}: give the camera's image, "
                     f"{_size(geometry.camera)} (averaged onto the {_size(geometry.grid)} "
                     f"super-pixels through the rig's correspondence), or the super-pixels' "
                     f"own, {_size(geometry.grid)}", path)
