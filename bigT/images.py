"""Grayscale image I/O for compensation, relighting and bounce separation.

Every image is handled as a float64 array of values in [0, 1] (more where a simulated
camera image exceeds 1):

=========================  =====================  ===================================
format                     read                   write
=========================  =====================  ===================================
PNG, 8-bit                 value / 255            round(clip(v, 0, 1) * 255), uint8
PNG, 16-bit (the default)  value / 65535          round(clip(v, 0, 1) * 65535), uint16
TIFF (``.tif``/``.tiff``)  uint8/uint16 scaled,   float32, unclipped
                           floats as they are
``.npy``                   floats as they are     float32, unclipped
=========================  =====================  ===================================

A *folder* of such files (sorted by name, other files ignored) is a batch of frames.

Colour: the transport is grayscale, as in the paper (§6.1), so a colour image is refused
with an :class:`~bigT.errors.ImageError` that names the file and its channel count; an
(H, W, 1) image is accepted as (H, W). Convert colour frames to grayscale (or split the
channels into three frames and process them as a batch) before calling bigT.

NaN or Inf values, and a size that does not match the transport's image shape, are
:class:`~bigT.errors.ImageError` s naming the file. A file's header is read before its
pixels: one declaring more values than an image of the transport's shape can hold (or,
where no shape is known, more than :data:`bigT.config.IMAGE_MAX_VALUES`) is refused
before anything is decoded, so a small forged file never costs gigabytes.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from . import config
from .atomic import atomic_output, refuse_overwriting_inputs
from .errors import ImageError, short_reason

#: File name suffixes read as images (lower case).
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
#: Bit depth of PNG files written when none is asked for.
DEFAULT_PNG_BITS = 16
#: Most channels a readable image may have per pixel (RGBA): an image of the transport's
#: (H, W) holds at most this many values per pixel before it is refused as colour.
MAX_CHANNELS = 4


def is_image_file(path: str | os.PathLike) -> bool:
    """True when ``path`` has one of :data:`IMAGE_SUFFIXES`."""
    return Path(path).suffix.lower() in IMAGE_SUFFIXES


def list_frames(folder: str | os.PathLike) -> list[Path]:
    """Image files of ``folder``, sorted by name.

    Raises
    ------
    ImageError
        When the folder holds no image file.
    """
    folder = Path(folder)
    frames = sorted((p for p in folder.iterdir() if p.is_file() and is_image_file(p)),
                    key=lambda p: p.name)
    if not frames:
        raise ImageError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in the folder", folder)
    return frames


def _iio_call(name, *args):
    """imageio.v3.<name>(*args), quiet about its vendored-tifffile deprecation notice."""
    import imageio.v3 as iio  # imageio and its plugins: ~0.2 s, only when a file is read

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*vendored tifffile", category=DeprecationWarning)
        # Pillow's own size guard: the header was bounded already (check_declared_size)
        warnings.filterwarnings("ignore", message=".*could be decompression bomb")
        return getattr(iio, name)(*args)


def _to_unit(raw: np.ndarray, path) -> np.ndarray:
    if raw.dtype == np.uint8:
        return raw.astype(np.float64) / 255.0
    if raw.dtype == np.uint16:
        return raw.astype(np.float64) / 65535.0
    if raw.dtype == np.bool_:
        return raw.astype(np.float64)
    if np.issubdtype(raw.dtype, np.floating):
        return raw.astype(np.float64)
    raise ImageError(f"unsupported pixel type {raw.dtype} (use 8/16-bit integers or floats)", path)


def check_image(image: np.ndarray, path="<array>", shape: Sequence[int] | None = None) -> np.ndarray:
    """Validate one grayscale image already in memory.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 1)
    path : str
        Name used in error messages.
    shape : (int, int), optional
        The (H, W) the image must have.

    Returns
    -------
    ndarray, shape (H, W), float64
    """
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3:
        raise ImageError(
            f"image with {image.shape[2]} channels (colour or alpha); bigT's transport is "
            "grayscale: convert it to one channel first", path)
    if image.ndim != 2:
        raise ImageError(f"expected a 2-D grayscale image, got an array of shape {image.shape}", path)
    image = _to_unit(image, path)
    if not np.isfinite(image).all():
        bad = int(np.size(image) - np.count_nonzero(np.isfinite(image)))
        raise ImageError(f"{bad} pixel(s) are NaN or Inf", path)
    if shape is not None and tuple(image.shape) != tuple(shape):
        raise ImageError(
            f"image of shape {tuple(image.shape)} does not match the transport's image shape "
            f"{tuple(shape)}", path)
    return image


def declared_shape(path: str | os.PathLike) -> tuple[int, ...] | None:
    """The array shape an image file's header declares, read without decoding a pixel.

    Returns
    -------
    tuple of int or None
        (H, W) or (H, W, C) for PNG and TIFF (C the channels, when more than one), the
        array's shape for ``.npy``; None when the header cannot be parsed (the decoder
        then says why the file is unreadable).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            return _npy_shape(path)
        # the plugin classes parse the header only, without Image.open's size warning
        from PIL import PngImagePlugin, TiffImagePlugin  # Pillow: only when a file is read

        cls = PngImagePlugin.PngImageFile if suffix == ".png" else TiffImagePlugin.TiffImageFile
        with cls(os.fspath(path)) as im:
            (W, H), channels = im.size, len(im.getbands())
    except FileNotFoundError:
        raise ImageError("no such file", path) from None
    except Exception:  # not a parsable header: the decoder reports it
        return None
    return (H, W) if channels == 1 else (H, W, channels)


def _npy_shape(path: Path) -> tuple[int, ...]:
    """The shape in a ``.npy`` header (whatever the file's length: a short file that
    declares a huge array must not be allocated by np.load before it fails)."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                else np.lib.format.read_array_header_2_0)
        return tuple(int(d) for d in read(f)[0])


def check_declared_size(path: str | os.PathLike, shape: Sequence[int] | None = None) -> None:
    """Refuse an image whose header declares more values than bigT would read.

    Parameters
    ----------
    path : an image file (:data:`IMAGE_SUFFIXES`).
    shape : (int, int), optional
        The transport's (H, W): at most H W x :data:`MAX_CHANNELS` values are read.
        Without it, at most :data:`bigT.config.IMAGE_MAX_VALUES`.

    Raises
    ------
    ImageError
        Naming the file and the declared size, before any pixel is decoded.
    """
    declared = declared_shape(path)
    if declared is None:
        return
    values = int(np.prod(declared, dtype=np.float64))  # float: a forged header can overflow int64
    if shape is not None:
        if values > int(np.prod(shape)) * MAX_CHANNELS:
            raise ImageError(
                f"the header declares an image of shape {declared}, far larger than the "
                f"transport's image shape {tuple(shape)}; refused before decoding it", path)
    elif values > config.IMAGE_MAX_VALUES:
        raise ImageError(
            f"the header declares an image of shape {declared} ({values:,} values), more "
            f"than the {config.IMAGE_MAX_VALUES:,} bigT reads (bigT.config.IMAGE_MAX_VALUES); "
            "refused before decoding it", path)


def read_image(path: str | os.PathLike, shape: Sequence[int] | None = None) -> np.ndarray:
    """Read one grayscale image as floats in [0, 1].

    Parameters
    ----------
    path : path to a ``.png``, ``.tif``/``.tiff`` or ``.npy`` file.
    shape : (int, int), optional
        The (H, W) the image must have (the store's image shape).

    Returns
    -------
    ndarray, shape (H, W), float64
    """
    return check_image(read_raw_image(path, shape), path, shape)


def read_raw_image(path: str | os.PathLike, shape: Sequence[int] | None = None) -> np.ndarray:
    """The pixels of an image file as stored (uint8, uint16, floats...), unchecked but
    for the size its header declares (:func:`check_declared_size`, ``shape`` the
    transport's (H, W) when known); :func:`read_image` is this and :func:`check_image`.
    Acquisition needs the stored type to check bit depths and find saturated pixels."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ImageError(f"unknown image format {suffix!r} (use {', '.join(IMAGE_SUFFIXES)})", path)
    check_declared_size(path, shape)
    try:
        if suffix == ".npy":
            return np.load(path, allow_pickle=False)
        return _iio_call("imread", path)
    except FileNotFoundError:
        raise ImageError("no such file", path) from None
    except Exception as exc:  # imageio/pillow/numpy raise many types on a damaged file
        raise ImageError(f"cannot read the image ({short_reason(exc, path)})", path) from None


def write_image(path: str | os.PathLike, image: np.ndarray, *, bits: int | None = None) -> Path:
    """Write one grayscale image; the format follows the suffix (see the module table).

    Parameters
    ----------
    path : destination; its folder is created when missing.
    image : ndarray, shape (H, W), float
    bits : {8, 16}, optional
        PNG bit depth (default :data:`DEFAULT_PNG_BITS`); ignored for other formats.
    """
    path = Path(path)
    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 2:
        raise ImageError(f"write_image takes one (H, W) image, got shape {image.shape}", path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        pixels = image.astype(np.float32)
    elif suffix in (".tif", ".tiff"):
        pixels = image.astype(np.float32)
    elif suffix == ".png":
        bits = DEFAULT_PNG_BITS if bits is None else int(bits)
        if bits not in (8, 16):
            raise ImageError(f"PNG bit depth must be 8 or 16, got {bits}", path)
        top = 255 if bits == 8 else 65535
        scaled = np.rint(np.clip(np.nan_to_num(image), 0.0, 1.0) * top)
        pixels = scaled.astype(np.uint8 if bits == 8 else np.uint16)
    else:
        raise ImageError(f"unknown image format {suffix!r} (use {', '.join(IMAGE_SUFFIXES)})", path)
    with atomic_output(path, "the image") as tmp:
        if suffix == ".npy":
            with open(tmp, "wb") as f:  # given a name, numpy appends ".npy" to ".NPY"
                np.save(f, pixels)
        else:
            _iio_call("imwrite", tmp, pixels)
    return path


def png_bits(path: str | os.PathLike) -> int | None:
    """Bit depth of a PNG file (8 or 16), None for other formats."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        return None
    import imageio.v3 as iio  # ~0.2 s, only when a file is read

    return 8 if iio.improps(path).dtype == np.uint8 else 16


class ImageSource:
    """One image file or a folder of frames, read in batches.

    Parameters
    ----------
    path : an image file or a folder of image files.
    shape : (int, int), optional
        The (H, W) every frame must have.

    Attributes
    ----------
    files : list of Path, the frames in order.
    is_folder : bool
    """

    def __init__(self, path: str | os.PathLike, shape: Sequence[int] | None = None):
        self.path = Path(path)
        self.shape = None if shape is None else tuple(int(s) for s in shape)
        if self.path.is_dir():
            self.is_folder = True
            self.files = list_frames(self.path)
        elif self.path.exists():
            self.is_folder = False
            if not is_image_file(self.path):
                raise ImageError(f"unknown image format {self.path.suffix!r} "
                                 f"(use {', '.join(IMAGE_SUFFIXES)})", self.path)
            self.files = [self.path]
        else:
            raise ImageError("no such file or folder", self.path)

    def __len__(self) -> int:
        return len(self.files)

    def batches(self, size: int) -> Iterator[tuple[list[Path], np.ndarray]]:
        """Yield (files, frames) with frames of shape (k, H, W), float64, k <= size."""
        size = max(1, int(size))
        for start in range(0, len(self.files), size):
            files = self.files[start:start + size]
            yield files, np.stack([read_image(f, self.shape) for f in files])

    def read_all(self) -> np.ndarray:
        """All frames, shape (K, H, W)."""
        return np.stack([read_image(f, self.shape) for f in self.files])


class ImageSink:
    """Where results go: one image file, or a folder mirroring a source's frame names.

    Parameters
    ----------
    path : destination file (single image) or folder (batch).
    source : ImageSource
        The input; a folder source gives a folder sink with the same file names.
    suffix : str, optional
        Force this suffix (e.g. ``".npy"`` for unclipped simulated images) instead of
        each input's.
    bits : int, optional
        PNG bit depth; by default the bit depth of each input PNG (16 for other inputs).
    inputs : paths, optional
        The other inputs of the command (stores, files), which no file written may
        destroy, as none may destroy the source (OutputError, before anything is
        written).
    """

    def __init__(self, path: str | os.PathLike, source: ImageSource, *, suffix: str | None = None,
                 bits: int | None = None, inputs=()):
        self.path = Path(path)
        self.source = source
        self.suffix = suffix
        self.bits = bits
        if source.is_folder:
            if self.path.exists() and not self.path.is_dir():
                raise ImageError("the input is a folder, so the output must be a folder too", self.path)
        else:
            if self.path.is_dir():
                self.path = self.path / source.path.name
            if suffix is None and not is_image_file(self.path):
                raise ImageError(f"unknown output format {self.path.suffix!r} "
                                 f"(use {', '.join(IMAGE_SUFFIXES)})", self.path)
        # no folder is made here: write_image makes it with the first file
        refuse_overwriting_inputs(self.targets(), [source.path, *inputs],
                                  folders=[self.path] if source.is_folder else ())

    def targets(self) -> list[Path]:
        """Every file :meth:`write` may write, one per frame of the source."""
        return [self.target(f) for f in self.source.files]

    def target(self, src: Path) -> Path:
        """Output path for the input frame ``src``."""
        dest = self.path / src.name if self.source.is_folder else self.path
        return dest.with_suffix(self.suffix) if self.suffix else dest

    def write(self, files: Sequence[Path], frames: np.ndarray) -> list[Path]:
        out = []
        for src, frame in zip(files, frames):
            bits = self.bits if self.bits is not None else png_bits(src)
            out.append(write_image(self.target(src), frame, bits=bits))
        return out
