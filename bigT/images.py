"""Image I/O for compensation, relighting and bounce separation: grey and RGB.

Every image is handled as a float64 array of values in [0, 1] (more where a simulated
camera image exceeds 1), of shape (H, W) for a grey image and (H, W, 3) for a colour
one (R, G, B):

=========================  =====================  ===================================
format                     read                   write
=========================  =====================  ===================================
PNG, 8-bit                 value / 255            round(clip(v, 0, 1) * 255), uint8
PNG, 16-bit (the default)  value / 65535          round(clip(v, 0, 1) * 65535), uint16
TIFF (``.tif``/``.tiff``)  uint8/uint16 scaled,   float32, unclipped
                           floats as they are
``.npy``                   floats as they are     float32, unclipped
=========================  =====================  ===================================

the same for grey and colour. These are the file's values, in its own encoding:
:mod:`bigT.colour` names the encoding (an 8-bit colour image is sRGB-encoded unless the
user says otherwise, :func:`image_encoding`) and turns values into linear light and
back.

The PNG codecs are chosen for speed, since a folder of frames is decoded and encoded on
several threads beside the products (:mod:`bigT.compensation.pipeline`): every PNG is
written by OpenCV (:func:`encode_png`), and the common kinds (grey, grey + alpha, RGB,
RGBA of 8 bits, 16-bit grey) are read by Pillow's decoder called directly; both release
the GIL. A 16-bit colour PNG is read by OpenCV, because Pillow reads one as 8 bits
without a word (ffmpeg where OpenCV cannot); the other kinds (palettes, 1-bit, ...) by
imageio.

Colour: a transport has 1 (grey) or 3 (RGB) channels, and an image given to it must
have as many (``channels=``): a grey image given to a colour transport, or a colour image
to a grey one, is an :class:`~bigT.errors.ImageError` naming the file, what it holds
and what to do. An (H, W, 1) image is grey; an alpha channel (grey + alpha, RGBA) is
dropped when the image is fully opaque, and refused otherwise (bigT does not guess the
background a transparent pixel shows).

NaN or Inf values, and a size that does not match the transport's image shape, are
:class:`~bigT.errors.ImageError` s naming the file. A file's header is read before its
pixels: one declaring more values than an image of the transport's shape can hold (H W
x :data:`MAX_CHANNELS`, RGBA; or, where no shape is known, more than
:data:`bigT.config.IMAGE_MAX_VALUES`) is refused before anything is decoded, so a small
forged file never costs gigabytes.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import warnings
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from . import colour, config
from .atomic import (atomic_output, fsync_dir, refuse_overwriting_inputs,
                     remove_dead_writers_files)
from .errors import ImageError, short_reason

#: File name suffixes read as images (lower case).
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
#: Bit depth of PNG files written when none is asked for.
DEFAULT_PNG_BITS = 16
#: Most channels a readable image may have per pixel (RGBA): an image file of the
#: transport's (H, W) declaring more values than H W x this is refused from its header.
MAX_CHANNELS = 4
#: Channels of a transport and of the images it takes: grey or RGB.
TRANSPORT_CHANNELS = (1, 3)


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


def _to_unit(raw: np.ndarray, path, dtype=np.float64) -> np.ndarray:
    # codes / top straight in float32 too: both roundings of the exact quotient are
    # correct (float64 has more than 2 x 24 + 2 bits), so the values are those of the
    # float64 image cast, bit for bit, one pass sooner
    scalar = np.dtype(dtype).type
    if raw.dtype == np.uint8:
        return raw.astype(scalar) / scalar(255)
    if raw.dtype == np.uint16:
        return raw.astype(scalar) / scalar(65535)
    if raw.dtype == np.bool_:
        return raw.astype(scalar)
    if np.issubdtype(raw.dtype, np.floating):
        return raw.astype(np.float64)
    raise ImageError(f"unsupported pixel type {raw.dtype} (use 8/16-bit integers or floats)", path)


def check_image(image: np.ndarray, path="<array>", shape: Sequence[int] | None = None,
                channels: int | None = None) -> np.ndarray:
    """Validate one image already in memory.

    Parameters
    ----------
    image : ndarray, shape (H, W), (H, W, 1), (H, W, 3), or with an alpha channel
        (H, W, 2) or (H, W, 4), which must be fully opaque and is dropped.
    path : str
        Name used in error messages.
    shape : (int, int), optional
        The (H, W) the image must have.
    channels : {1, 3}, optional
        The transport's channels, which the image must have (any, when None).

    Returns
    -------
    ndarray, shape (H, W) (grey) or (H, W, 3) (colour), float64
    """
    return _checked_image(image, path, shape, channels, np.float64)


def _checked_image(image: np.ndarray, path, shape, channels, dtype) -> np.ndarray:
    """:func:`check_image`'s image in ``dtype`` (float64 or float32): a float32 one holds
    the float64 one's values cast, bit for bit, with the same errors."""
    image = _grey_or_rgb(image, path, channels)
    if np.dtype(dtype) != np.float64 and image.dtype.kind in "ub":
        return _checked_shape(_to_unit(image, path, dtype), path, shape)  # codes: finite
    image = _to_unit(image, path)
    if not np.isfinite(image).all():
        bad = int(np.size(image) - np.count_nonzero(np.isfinite(image)))
        raise ImageError(f"{bad} value(s) are NaN or Inf" if image.ndim == 3
                         else f"{bad} pixel(s) are NaN or Inf", path)
    return _checked_shape(image.astype(dtype, copy=False), path, shape)


def _grey_or_rgb(image: np.ndarray, path, channels) -> np.ndarray:
    """``image`` as (H, W) or (H, W, 3), its values as they are (an opaque alpha channel
    dropped, (H, W, 1) squeezed), checked against ``channels`` (1, 3 or None: any)."""
    image = _without_alpha(np.asarray(image), path)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] != 3:
        raise ImageError(f"image with {image.shape[2]} channels; bigT reads grey (1 channel) "
                         "or RGB (3 channels) images", path)
    if image.ndim not in (2, 3):
        raise ImageError(f"expected a grey image (H, W) or a colour image (H, W, 3), got an "
                         f"array of shape {image.shape}", path)
    if channels is not None:
        check_channels(image.shape, channels, path)
    return image


def _checked_shape(image: np.ndarray, path, shape) -> np.ndarray:
    if shape is not None and tuple(image.shape[:2]) != tuple(shape):
        raise ImageError(
            f"image of shape {tuple(image.shape[:2])} does not match the transport's image "
            f"shape {tuple(shape)}", path)
    return image


def image_channels(image_shape: Sequence[int]) -> int:
    """1 for an (H, W) image, the last axis for an (H, W, C) one."""
    return 1 if len(image_shape) == 2 else int(image_shape[2])


def check_channels(image_shape: Sequence[int], channels: int, path="<array>") -> None:
    """Refuse an image of shape ``image_shape`` ((H, W) or (H, W, 3)) given to a
    transport of ``channels`` (1 or 3), in one line saying what to do.

    Raises
    ------
    ImageError
        A grey image given to a colour transport, or the reverse; ``channels`` not 1 or 3.
    """
    if channels not in TRANSPORT_CHANNELS:
        raise ImageError(f"a transport has 1 (grey) or 3 (RGB) channels, not {channels!r}", path)
    found = image_channels(image_shape)
    if found == channels:
        return
    size = tuple(int(s) for s in image_shape[:2])
    if channels == 3:
        raise ImageError(
            f"grey image {size} given to a colour transport (3 channels): give an RGB image "
            f"of shape {(*size, 3)}, or use a grey transport", path)
    raise ImageError(
        f"colour image {(*size, found)} ({found} channels) given to a grey transport "
        "(1 channel): convert it to grey, or use a colour transport", path)


def _without_alpha(image: np.ndarray, path) -> np.ndarray:
    """``image`` without its alpha channel ((H, W, 2): grey + alpha, (H, W, 4): RGBA)
    when every pixel is opaque; other arrays as they are.

    Raises
    ------
    ImageError
        Some pixel is not fully opaque.
    """
    if image.ndim != 3 or image.shape[2] not in (2, 4):
        return image
    alpha = image[:, :, -1]
    opaque = (np.iinfo(image.dtype).max if np.issubdtype(image.dtype, np.integer)
              else True if image.dtype == np.bool_ else 1.0)
    see_through = int(np.count_nonzero(alpha != opaque))
    if see_through:
        raise ImageError(f"image with transparency ({see_through} pixel(s) not fully opaque); "
                         "bigT reads grey or RGB: flatten it onto its background first", path)
    return image[:, :, :-1]


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
        return _tiff_shape(path) if suffix in (".tif", ".tiff") else None
    return (H, W) if channels == 1 else (H, W, channels)


def _tiff_shape(path: Path) -> tuple[int, ...] | None:
    """The shape in a TIFF's header by tifffile, which reads the sample layouts Pillow
    cannot (an RGB image of floats), from its tags only."""
    try:
        return tuple(int(d) for d in _iio_call("improps", path).shape)
    except Exception:  # not a parsable header: the decoder reports it
        return None


def _npy_shape(path: Path) -> tuple[int, ...]:
    """The shape in a ``.npy`` header (whatever the file's length: a short file that
    declares a huge array must not be allocated by np.load before it fails)."""
    return tuple(int(d) for d in _npy_header(path)[0])


def _npy_header(path: Path) -> tuple:
    """A ``.npy`` header: (shape, fortran_order, dtype)."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                else np.lib.format.read_array_header_2_0)
        return read(f)


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


def read_image(path: str | os.PathLike, shape: Sequence[int] | None = None,
               channels: int | None = None) -> np.ndarray:
    """Read one image as floats in [0, 1], in the file's own encoding (see
    :func:`image_encoding` and :func:`bigT.colour.decode` for linear light).

    Parameters
    ----------
    path : path to a ``.png``, ``.tif``/``.tiff`` or ``.npy`` file.
    shape : (int, int), optional
        The (H, W) the image must have (the store's image shape).
    channels : {1, 3}, optional
        The transport's channels: a grey image where 3 are needed, or a colour one
        where 1 is, is refused (:func:`check_channels`). Any, when None.

    Returns
    -------
    ndarray, shape (H, W) (grey) or (H, W, 3) (colour), float64
    """
    return check_image(read_raw_image(path, shape), path, shape, channels)


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
        pixels = _decode_png(path) if suffix == ".png" else None
        if pixels is not None:
            return pixels
        if _deep_colour_png(path):
            return _read_deep_colour_png(path)
        return _iio_call("imread", path)
    except FileNotFoundError:
        raise ImageError("no such file", path) from None
    except ImageError:
        raise
    except Exception as exc:  # imageio/pillow/numpy raise many types on a damaged file
        raise ImageError(f"cannot read the image ({short_reason(exc, path)})", path) from None


def write_image(path: str | os.PathLike, image: np.ndarray, *, bits: int | None = None,
                clean: bool = True, sync_folder: bool = True) -> Path:
    """Write one grey or RGB image; the format follows the suffix (see the module table).

    Parameters
    ----------
    path : destination; its folder is created when missing.
    image : ndarray, shape (H, W) (grey) or (H, W, 3) (RGB), float
        Values in the encoding the file is to hold (:func:`bigT.colour.encode`).
    bits : {8, 16}, optional
        PNG bit depth (default :data:`DEFAULT_PNG_BITS`); ignored for other formats.
    clean, sync_folder : bool
        As :func:`bigT.atomic.atomic_output`'s: False where the caller cleans and
        fsyncs the folder once for many files (:meth:`ImageSink.synced_once`).
    """
    path = Path(path)
    image = np.asarray(image)
    if image.dtype not in (np.float32, np.float64):  # float32 frames are taken as they are
        image = image.astype(np.float64)
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ImageError("write_image takes one grey (H, W) or RGB (H, W, 3) image, got "
                         f"shape {image.shape}", path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        pixels = image.astype(np.float32)
    elif suffix in (".tif", ".tiff"):
        pixels = image.astype(np.float32)
    elif suffix == ".png":
        bits = DEFAULT_PNG_BITS if bits is None else int(bits)
        if bits not in (8, 16):
            raise ImageError(f"PNG bit depth must be 8 or 16, got {bits}", path)
        pixels = _quantised(image, bits)
    else:
        raise ImageError(f"unknown image format {suffix!r} (use {', '.join(IMAGE_SUFFIXES)})", path)
    if suffix == ".png":
        return write_png_codes(path, pixels, clean=clean, sync_folder=sync_folder)
    with atomic_output(path, "the image", clean=clean, sync_folder=sync_folder) as tmp:
        if suffix == ".npy":
            with open(tmp, "wb") as f:  # given a name, numpy appends ".npy" to ".NPY"
                np.save(f, pixels)
        else:
            _iio_call("imwrite", tmp, pixels)
    return path


def write_png_codes(path: str | os.PathLike, codes: np.ndarray, *, clean: bool = True,
                    sync_folder: bool = True) -> Path:
    """Write one PNG of integer codes as they are (:func:`write_image`'s PNG of the
    values ``codes / top``, byte for byte).

    Parameters
    ----------
    path : destination (a ``.png``); its folder is created when missing.
    codes : ndarray, shape (H, W) or (H, W, 3), uint8 or uint16
    clean, sync_folder : as :func:`write_image`'s
    """
    path = Path(path)
    with atomic_output(path, "the image", clean=clean, sync_folder=sync_folder) as tmp:
        Path(tmp).write_bytes(encode_png(codes, path))
    return path


def _quantised(image: np.ndarray, bits: int) -> np.ndarray:
    """The codes of a PNG of ``bits`` (8 or 16) for values in [0, 1]: NaN and values
    below 0 give 0, values above 1 the top code, the others ``rint(value * top)`` in
    float64 (where the product of a float32 value is exact).

    Parameters
    ----------
    image : ndarray, any shape, float32 or float64

    Returns
    -------
    ndarray, the same shape, uint8 or uint16
    """
    # fmax/fmin drop NaN for the other operand: NaN -> 0 and +-inf -> 0 or 1, as
    # nan_to_num then clip did, in 5 passes over the frame instead of 9
    scaled = np.fmax(image, 0.0, dtype=np.float64)  # a float64 copy
    np.fmin(scaled, 1.0, out=scaled)
    scaled *= 255 if bits == 8 else 65535
    return np.rint(scaled, out=scaled).astype(np.uint8 if bits == 8 else np.uint16)


#: zlib level and row filter of the PNG files bigT writes: level 1 with every row
#: filtered "up" (the difference from the row above). On 384x512 16-bit frames,
#: compensated (noisy) and desired (smooth) alike, this is 2-3x quicker than level 1 with
#: libpng's adaptive choice of filter per row and than Pillow's level 6 (bigT's writer
#: before), and its files are no larger than either (within 1 %, and 4 % smaller than
#: Pillow's on compensated frames); RLE and Huffman-only strategies are quicker still on
#: noisy frames but make smooth ones 18x larger.
PNG_COMPRESSION = 1


def encode_png(pixels: np.ndarray, path="<array>") -> bytes:
    """The PNG file of ``pixels``, all their bits, by OpenCV's encoder (which releases
    the GIL: frames are encoded on several threads at once).

    Parameters
    ----------
    pixels : ndarray, shape (H, W) (grey) or (H, W, 3) (RGB), uint8 or uint16
    path : the file it is for (error messages)
    """
    import cv2  # OpenCV: ~0.1 s, only when an image is written

    if pixels.ndim == 3:  # OpenCV's channel order is B, G, R
        pixels = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR)
    flags = [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]
    up = getattr(cv2, "IMWRITE_PNG_FILTER_UP", None)  # OpenCV >= 4.10; before, libpng's choice
    if up is not None:
        flags += [cv2.IMWRITE_PNG_FILTER, up]
    ok, data = cv2.imencode(".png", pixels, flags)
    if not ok:
        raise ImageError(f"cannot encode a PNG of {pixels.dtype} values of shape "
                         f"{pixels.shape}", path)
    return data.tobytes()


#: Pillow's modes of the PNG files :func:`_decode_png` reads itself, and the channels
#: each holds: what imageio would return for them, without imageio's overhead.
_PILLOW_PNG_MODES = {"L": 1, "I;16": 1, "LA": 2, "RGB": 3, "RGBA": 4}


def _decode_png(path: Path) -> np.ndarray | None:
    """The pixels of a grey, grey + alpha, RGB or RGBA PNG of 8 bits (or a 16-bit
    grey one), as imageio reads them, by Pillow's decoder directly (it releases the
    GIL: frames are decoded on several threads at once; imageio's plugin costs as
    much again around it); a 16-bit colour PNG by OpenCV, with all its bits. None for
    the other kinds (palettes, 1-bit, ...), which imageio reads as before."""
    if _deep_colour_png(path):
        return _decode_deep_colour_png(path)  # a damaged one: ImageError, in one line
    try:
        from PIL import PngImagePlugin  # Pillow: only when a file is read

        with PngImagePlugin.PngImageFile(os.fspath(path)) as im:
            channels = _PILLOW_PNG_MODES.get(im.mode)
            if channels is None:
                return None
            im.load()
            pixels = np.array(im)  # writable, as imageio returns it (asarray: read-only)
    except Exception:  # noqa: BLE001 - a damaged file: the reader of old says why, as before
        return None
    expected = (im.size[1], im.size[0]) + (() if channels == 1 else (channels,))
    return pixels if pixels.shape == expected else None


def _decode_deep_colour_png(path: Path) -> np.ndarray | None:
    """A 16-bit RGB or RGBA PNG by OpenCV, (H, W, 3 or 4) uint16 in R, G, B (A)
    order; None where OpenCV reads it otherwise (a transparent colour key adds an
    alpha channel; ffmpeg then reads it, as before) or not at all (ffmpeg says why)."""
    import cv2  # OpenCV: ~0.1 s, only for a 16-bit colour PNG

    bits, colour_type = _png_header(path)
    samples = _DEEP_PNG_FORMATS[colour_type][1]
    _check_png_chunks(path)  # libpng would print its complaint on stderr, then fail
    pixels = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
    if (pixels is None or pixels.dtype != np.uint16 or pixels.ndim != 3
            or pixels.shape[2] != samples or samples not in (3, 4)):
        return None
    return cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB if samples == 3 else cv2.COLOR_BGRA2RGBA)


def _check_png_chunks(path: Path) -> None:
    """ImageError naming ``path`` when a PNG's chunks fail their CRCs or end early
    (Pillow's ``verify``, which decodes no pixels): a damaged file is one line, not
    libpng's stderr message followed by a decoder's error."""
    from PIL import Image  # Pillow: imported by the PNG readers already

    try:
        with Image.open(path) as im:
            im.verify()
    except Exception as exc:  # noqa: BLE001 - Pillow raises SyntaxError, OSError...
        raise ImageError(f"damaged PNG ({short_reason(exc, path)})", path) from None


#: PNG colour types (the IHDR's) with more than one sample per pixel, and the ffmpeg
#: pixel format that keeps all 16 bits of each: grey + alpha, RGB, RGBA.
_DEEP_PNG_FORMATS = {4: ("ya16le", 2), 2: ("rgb48le", 3), 6: ("rgba64le", 4)}


def _png_header(path: Path) -> tuple[int, int] | None:
    """(bit depth, colour type) of a PNG's IHDR, None when the file has none."""
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) < 26 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return head[24], head[25]


def _deep_colour_png(path: Path) -> bool:
    """A PNG of 16 bits per sample and more than one sample per pixel: Pillow reads
    those as 8 bits (silently), so ffmpeg reads them."""
    header = _png_header(path) if path.suffix.lower() == ".png" else None
    return header is not None and header[0] == 16 and header[1] in _DEEP_PNG_FORMATS


def _ffmpeg(args: list[str], path, stdin: bytes | None = None) -> bytes:
    """ffmpeg's stdout for ``args``; its complaint as a one-line ImageError otherwise."""
    import imageio_ffmpeg  # locates its ffmpeg binary: only for a 16-bit colour PNG

    run = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", *args],
                         input=stdin, capture_output=True)
    if run.returncode != 0:
        why = " ".join(run.stderr.decode("utf-8", "replace").split())[-200:]
        raise ImageError(f"ffmpeg cannot convert the 16-bit PNG ({why or run.returncode})", path)
    return run.stdout


def _read_deep_colour_png(path: Path) -> np.ndarray:
    """A 16-bit grey + alpha, RGB or RGBA PNG, all its bits: (H, W, C) uint16."""
    pix_fmt, samples = _DEEP_PNG_FORMATS[_png_header(path)[1]]
    H, W = declared_shape(path)[:2]
    raw = _ffmpeg(["-i", os.fspath(path), "-frames:v", "1", "-f", "rawvideo",
                   "-pix_fmt", pix_fmt, "-"], path)
    if len(raw) != H * W * samples * 2:
        raise ImageError(f"ffmpeg decoded {len(raw)} bytes, not the {H}x{W} image the "
                         "header declares", path)
    return np.frombuffer(raw, "<u2").reshape(H, W, samples).astype(np.uint16)


#: PNG colour types whose samples are the image's values themselves: grey and RGB
#: (a palette's are indices, an alpha channel must be checked and dropped).
_PLAIN_PNG_TYPES = (0, 2)


def png_code_dtype(files: Sequence[Path]) -> np.dtype | None:
    """The integer type (uint8 or uint16) every one of ``files`` holds its values in,
    when each is a grey or RGB PNG of that depth (from their headers, 26 bytes each);
    None otherwise (a palette, an alpha channel, 1 to 4 bits, another format, depths
    that differ): then only the float frames give their values."""
    depths = set()
    for f in files:
        try:
            header = _png_header(Path(f)) if Path(f).suffix.lower() == ".png" else None
        except OSError:  # gone or unreadable: the float frames' reader says so, in one line
            return None
        if header is None or header[0] not in (8, 16) or header[1] not in _PLAIN_PNG_TYPES:
            return None
        depths.add(header[0])
    if len(depths) != 1:
        return None
    return np.dtype(np.uint8 if depths.pop() == 8 else np.uint16)


def png_bits(path: str | os.PathLike) -> int | None:
    """Bit depth of a PNG file (8 or 16), None for other formats."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        return None
    header = _png_header(path)
    if header is not None and header[0] in (8, 16):  # the IHDR says it (Pillow would
        return header[0]                              # say 8 for 16-bit colour)
    import imageio.v3 as iio  # ~0.2 s, only when a file is read

    return 8 if iio.improps(path).dtype == np.uint8 else 16


def stored_type(path: str | os.PathLike) -> np.dtype | None:
    """The pixel type an image file stores (uint8, uint16, a float type...), read from
    its header; None when the header cannot be parsed."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            return np.dtype(_npy_header(path)[2])
        if suffix == ".png":
            return np.dtype(np.uint8 if png_bits(path) == 8 else np.uint16)
        return np.dtype(_iio_call("improps", path).dtype)
    except FileNotFoundError:
        raise ImageError("no such file", path) from None
    except Exception:  # not a parsable header: the decoder reports it
        return None


def image_encoding(path: str | os.PathLike, channels: int, requested: str | None = None) -> str:
    """The encoding of the image file ``path`` (:func:`bigT.colour.default_encoding`:
    ``requested`` when given, sRGB for an 8-bit colour file, else linear).

    Parameters
    ----------
    path : an image file.
    channels : {1, 3}, the image's channels.
    requested : one of :data:`bigT.colour.ENCODINGS`, optional (``--encoding``).
    """
    if requested is not None:
        return colour.check_encoding(requested)
    return colour.default_encoding(stored_type(path), channels)


class ImageSource:
    """One image file or a folder of frames, read in batches. A folder's frames are
    checked from their headers when the source is made (size and channels), so a
    folder with one bad frame is refused before any output is written.

    Parameters
    ----------
    path : an image file or a folder of image files.
    shape : (int, int), optional
        The (H, W) every frame must have.
    channels : {1, 3}
        The transport's channels, which every frame must have (grey by default, as
        bigT's transports were before colour).

    Attributes
    ----------
    files : list of Path, the frames in order.
    is_folder : bool
    frame_shape : (H, W) or (H, W, 3) when ``shape`` is known, else None.
    """

    def __init__(self, path: str | os.PathLike, shape: Sequence[int] | None = None,
                 channels: int = 1):
        self.path = Path(path)
        self.shape = None if shape is None else tuple(int(s) for s in shape)
        if channels not in TRANSPORT_CHANNELS:
            raise ImageError(f"a transport has 1 (grey) or 3 (RGB) channels, not {channels!r}")
        self.channels = int(channels)
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
        if self.is_folder:
            self._check_headers()

    def _check_headers(self) -> None:
        """Each frame's declared shape against the transport's; a frame whose header
        does not settle it (unparsable, an alpha channel, a palette) is read, which
        raises the one-line ImageError naming it if it does not fit."""
        for file in self.files:
            declared = declared_shape(file)
            if declared is None or not self._fits(declared):
                self.read(file)

    def _fits(self, declared: tuple[int, ...]) -> bool:
        size_fits = self.shape is None or tuple(declared[:2]) == self.shape
        channels = 1 if declared[2:] in ((), (1,)) else declared[2]
        return len(declared) in (2, 3) and size_fits and channels == self.channels

    def __len__(self) -> int:
        return len(self.files)

    @property
    def frame_shape(self) -> tuple[int, ...] | None:
        if self.shape is None:
            return None
        return self.shape if self.channels == 1 else (*self.shape, self.channels)

    def read(self, file: Path, dtype=np.float64) -> np.ndarray:
        """One frame: (H, W) or (H, W, 3), float64 (or float32: the float64 frame's
        values cast, one pass fewer), checked against shape and channels."""
        return _checked_image(read_raw_image(file, self.shape), file, self.shape,
                              self.channels, dtype)

    def read_codes(self, file: Path, dtype) -> np.ndarray:
        """One frame's integer codes as stored: (H, W) or (H, W, 3) of ``dtype`` (a
        file of :func:`png_code_dtype`'s), checked as :meth:`read` checks it; its
        values are ``codes / top`` (:func:`bigT.compensation.codes.code_values`)."""
        image = _grey_or_rgb(read_raw_image(file, self.shape), file, self.channels)
        if image.dtype != np.dtype(dtype):
            raise ImageError(f"the file holds {image.dtype} values where its header "
                             f"promised {np.dtype(dtype)}", file)
        return _checked_shape(image, file, self.shape)

    def batches(self, size: int) -> Iterator[tuple[list[Path], np.ndarray]]:
        """Yield (files, frames) with frames of shape (k, H, W) (grey) or (k, H, W, 3)
        (colour), float64, k <= size."""
        size = max(1, int(size))
        for start in range(0, len(self.files), size):
            files = self.files[start:start + size]
            yield files, np.stack([self.read(f) for f in files])

    def read_all(self) -> np.ndarray:
        """All frames, shape (K, H, W) or (K, H, W, 3)."""
        return np.stack([self.read(f) for f in self.files])


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

    Attributes
    ----------
    channels : {1, 3}
        The source's: each frame written is (H, W) or (H, W, 3) accordingly.
    """

    def __init__(self, path: str | os.PathLike, source: ImageSource, *, suffix: str | None = None,
                 bits: int | None = None, inputs=()):
        self.path = Path(path)
        self.source = source
        self.suffix = suffix
        self.bits = bits
        self.channels = int(getattr(source, "channels", 1))
        self._synced_once = False  # inside synced_once: the folder fsynced on its exit
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
        """Write each frame (shape (k, H, W), or (k, H, W, 3) for a colour sink) where
        its input frame's name says (:meth:`target`); returns the paths written.
        Safe to call from several threads at once, for different frames."""
        out = []
        once = self._synced_once
        for src, frame in zip(files, frames):
            bits = self.bits if self.bits is not None else png_bits(src)
            out.append(write_image(self.target(src), frame, bits=bits, clean=not once,
                                   sync_folder=not once))
        return out

    def takes_codes(self, dtype) -> bool:
        """True when :meth:`write_codes` writes what :meth:`write` would for codes of
        ``dtype`` (uint8 or uint16) read from the source's PNG frames: PNG files of the
        same depth out (no other suffix nor depth asked for)."""
        bits = 8 * np.dtype(dtype).itemsize
        return (self.suffix is None and self.bits in (None, bits)
                and all(self.target(f).suffix.lower() == ".png" for f in self.source.files))

    def write_codes(self, files: Sequence[Path], codes: np.ndarray) -> list[Path]:
        """:meth:`write` of integer codes (k, H, W) or (k, H, W, 3), uint8 or uint16, as
        they are (the PNG :meth:`write` makes of ``codes / top``, byte for byte; see
        :meth:`takes_codes`). Safe to call from several threads at once."""
        once = self._synced_once
        return [write_png_codes(self.target(src), frame, clean=not once, sync_folder=not once)
                for src, frame in zip(files, codes)]

    @contextlib.contextmanager
    def synced_once(self) -> Iterator["ImageSink"]:
        """Within: the frames of a folder written with one fsync of the folder, on exit.

        Each file is still written aside, fsynced and renamed into place
        (:func:`bigT.atomic.atomic_output`), so a crash or a power cut at any point
        leaves every frame whole or absent, never torn; what waits for the exit is
        only the durability of the renames (frames written just before a power cut
        may be absent). The temporary files that killed writers left are deleted once,
        on entry, rather than by a scan of the folder per frame (which grows with the
        folder: quadratic in its frames). One fsync of the folder instead of one per
        frame: each is a journal commit (two a frame before, with the file's)."""
        targets = self.targets()
        folders = sorted({t.parent for t in targets})
        for folder, suffix in sorted({(t.parent, t.suffix) for t in targets}):
            if folder.is_dir():
                remove_dead_writers_files(folder, suffix)
        self._synced_once = True
        try:
            yield self
        finally:
            self._synced_once = False
            for folder in folders:  # the renames done within: durable from here
                if folder.is_dir():
                    fsync_dir(folder)
