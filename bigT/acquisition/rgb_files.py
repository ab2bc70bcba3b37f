"""RGB image files of a colour acquisition: patterns written, captures read.

Interim, until :mod:`bigT.images` reads and writes colour images (``read_raw_image``,
``check_image`` and ``write_image`` taking (H, W, 3), being added beside this work):
then :func:`read_raw` becomes ``images.read_raw_image``, :func:`to_unit` becomes
``images.check_image`` and :func:`write` becomes ``images.write_image``, and this module
goes. Grey images already go through :mod:`bigT.images` here. The one format imageio
cannot do through Pillow is the 16-bit RGB PNG (Pillow reads one as 8 bits without a
word, and cannot write one): ffmpeg, which imageio-ffmpeg ships, does it both ways.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np

from ..atomic import atomic_output
from ..errors import ImageError
from ..images import check_image, declared_shape, read_raw_image, write_image

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: The IHDR colour type of an RGB PNG (no alpha).
PNG_RGB = 2


def read_raw(path) -> np.ndarray:
    """The pixels of an image file as stored: (H, W) or (H, W, C), uint8, uint16 or
    floats (``images.read_raw_image``, all 16 bits of a 16-bit RGB PNG kept)."""
    path = Path(path)
    if _is_16_bit_rgb_png(path):
        return _read_16_bit_rgb_png(path)
    return read_raw_image(path)


def to_unit(raw: np.ndarray, path) -> np.ndarray:
    """A stored image as float64 values in [0, 1] (integers scaled by their full scale,
    floats as they are), NaN and Inf refused (ImageError naming ``path``).

    Returns
    -------
    ndarray, shape (H, W) for a grey image, (H, W, 3) for an RGB one
    """
    if raw.ndim == 3 and raw.shape[2] == 3:
        # check_image takes a grey image: the channels, each an (H, W) image, one by one
        return np.stack([check_image(raw[:, :, c], path) for c in range(3)], axis=2)
    return check_image(raw, path)


def write(path, image: np.ndarray, *, bits: int = 16) -> Path:
    """Write one grey (H, W) or RGB (H, W, 3) image, as ``images.write_image`` does a
    grey one (PNG of ``bits`` bits, clipped to [0, 1]; TIFF and ``.npy`` as float32)."""
    image = np.asarray(image, dtype=np.float64)
    if image.ndim == 2:
        return write_image(path, image, bits=bits)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".png":
        top = 255 if bits == 8 else 65535
        pixels = np.rint(np.clip(image, 0.0, 1.0) * top).astype(np.uint8 if bits == 8
                                                                  else np.uint16)
    else:
        pixels = image.astype(np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path, "the image") as tmp:
        if suffix == ".npy":
            with open(tmp, "wb") as f:  # given a name, numpy appends ".npy" to ".NPY"
                np.save(f, pixels)
        elif pixels.dtype == np.uint16 and suffix == ".png":
            Path(tmp).write_bytes(_png_16_bit_rgb_bytes(pixels, path))
        else:
            import imageio.v3 as iio  # ~0.2 s, only when an RGB file is written

            iio.imwrite(tmp, pixels, extension=suffix)
    return path


def _is_16_bit_rgb_png(path: Path) -> bool:
    if path.suffix.lower() != ".png":
        return False
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except FileNotFoundError:
        raise ImageError("no such file", path) from None
    return (len(head) == 26 and head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR"
            and head[24] == 16 and head[25] == PNG_RGB)


def _ffmpeg(args: list[str], path, stdin: bytes | None = None) -> bytes:
    """ffmpeg's stdout for ``args``; its complaint as a one-line ImageError otherwise."""
    import imageio_ffmpeg  # locates its ffmpeg binary: only for a 16-bit RGB PNG

    run = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", *args],
                         input=stdin, capture_output=True)
    if run.returncode != 0:
        why = " ".join(run.stderr.decode("utf-8", "replace").split())[-200:]
        raise ImageError(f"ffmpeg cannot convert the 16-bit PNG ({why or run.returncode})",
                         path)
    return run.stdout


def _read_16_bit_rgb_png(path: Path) -> np.ndarray:
    """(H, W, 3) uint16, all 16 bits."""
    H, W = declared_shape(path)[:2]
    raw = _ffmpeg(["-i", os.fspath(path), "-frames:v", "1", "-f", "rawvideo",
                   "-pix_fmt", "rgb48le", "-"], path)
    if len(raw) != H * W * 3 * 2:
        raise ImageError(f"ffmpeg decoded {len(raw)} bytes, not the {H}x{W} RGB image the "
                         "header declares", path)
    return np.frombuffer(raw, "<u2").reshape(H, W, 3).astype(np.uint16)


def _png_16_bit_rgb_bytes(pixels: np.ndarray, path) -> bytes:
    """The PNG file of an (H, W, 3) uint16 image."""
    H, W, _ = pixels.shape
    return _ffmpeg(["-f", "rawvideo", "-pix_fmt", "rgb48le", "-s", f"{W}x{H}", "-i", "-",
                    "-frames:v", "1", "-c:v", "png", "-pix_fmt", "rgb48be", "-f",
                    "image2pipe", "-"], path, stdin=pixels.astype("<u2").tobytes())
