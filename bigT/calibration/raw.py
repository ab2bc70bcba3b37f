"""Camera files beyond PNG and TIFF: RAW captures (linear already) and the exposure
time a file's EXIF records."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import ImageError, short_reason

#: The EXIF tag of the exposure time in seconds (a rational), and the IFD that holds it.
EXPOSURE_TIME_TAG = 33434
EXIF_IFD = 0x8769


def read_raw(path: str | os.PathLike) -> np.ndarray:
    """A RAW capture (DNG, CR2, NEF, ARW, ...) as linear values in [0, 1].

    LibRaw (through rawpy) demosaics it with no gamma (``gamma=(1, 1)``), no automatic
    brightening and 16 bits out, so a value is proportional to the light: a RAW capture
    needs no camera response (``linear``).

    Parameters
    ----------
    path : the RAW file

    Returns
    -------
    ndarray of float64, shape (H, W, 3)

    Raises
    ------
    ImageError
        rawpy not installed (``pip install rawpy``), a missing or unreadable file;
        naming the file.
    """
    path = Path(path)
    try:
        import rawpy  # LibRaw: optional (pip install rawpy), only for RAW captures
    except ImportError:
        raise ImageError("rawpy is not installed: pip install rawpy", path) from None
    if not path.is_file():
        raise ImageError("no such file", path)
    try:
        with rawpy.imread(os.fspath(path)) as raw:
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16)
    except Exception as exc:  # LibRaw raises its own types for every unreadable file
        raise ImageError(f"cannot read the RAW file ({short_reason(exc, path)})", path) from None
    return rgb.astype(np.float64) / 65535.0


def exposure_time_from_exif(path: str | os.PathLike) -> float | None:
    """The exposure time in seconds a JPEG's or TIFF's EXIF records, None when absent.

    Parameters
    ----------
    path : an image file Pillow opens

    Raises
    ------
    ImageError
        A missing file or one Pillow cannot open; naming the file.
    """
    from PIL import Image  # Pillow: only when EXIF is read

    path = Path(path)
    try:
        with Image.open(path) as image:
            exif = image.getexif()
    except FileNotFoundError:
        raise ImageError("no such file", path) from None
    except Exception as exc:  # Pillow raises several types on a damaged file
        raise ImageError(f"cannot read its EXIF ({short_reason(exc, path)})", path) from None
    # cameras write it in the Exif IFD; some TIFF writers in the main one
    value = exif.get_ifd(EXIF_IFD).get(EXPOSURE_TIME_TAG, exif.get(EXPOSURE_TIME_TAG))
    try:
        seconds = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return seconds if np.isfinite(seconds) and seconds > 0 else None
