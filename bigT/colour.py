"""Image encodings: how the values of an image file relate to light.

Light transport is linear in *light*: T maps projector radiance to camera irradiance.
The values of an image file are often not light but an encoding of it. bigT names the
encoding of every image it reads or writes, one of :data:`ENCODINGS`:

``"linear"``
    The value is the light, scaled to [0, 1] by the file's full scale (what bigT has
    always done, and still does for every grey image).
``"srgb"``
    The value is sRGB-encoded (IEC 61966-2-1): light ``L`` is stored as
    ``12.92 L`` below a small threshold and ``1.055 L**(1/2.4) - 0.055`` above, the curve
    nearly every 8-bit colour photograph, screen capture and video frame is stored in.

The policy (:func:`default_encoding`): an 8-bit colour image is sRGB-encoded unless the
user says ``"linear"``; 16-bit and floating-point images, and every grey image, are
linear unless the user says otherwise. Compensation works in linear light:
:func:`decode` turns values read into light, :func:`encode` turns the projector's light
back into the values written, both elementwise on arrays of any shape, and each the
inverse of the other on the whole real line (to float rounding; see
:data:`SRGB_LINEAR_KNEE` for the 2.4e-9 of the standard's own gap at its knee), so values outside [0, 1] (an unclipped
simulated image) go through unharmed: below the knee (negative values included) the
straight part, above it (values above 1 included) the power part.

Foundation layer: numpy only.
"""

from __future__ import annotations

import numpy as np

from .errors import ImageError

#: The encodings bigT knows, by the name the API and the command line use.
ENCODINGS = ("srgb", "linear")

#: Encoded value at which the sRGB curve turns from its straight part to its power part
#: (IEC 61966-2-1).
SRGB_ENCODED_KNEE = 0.04045
#: Slope of the straight part near black.
SRGB_SLOPE = 12.92
#: The power part: encoded = (1 + offset) L**(1 / gamma) - offset.
SRGB_GAMMA = 2.4
SRGB_OFFSET = 0.055
#: Linear value at which :func:`encode` turns from the straight part to the power part:
#: the image of the encoded knee, 0.04045 / 12.92 = 0.00313080495..., where the standard
#: writes it rounded to 0.0031308 (the two differ by 5e-12, so each encodes the same
#: values to within 3e-8, a 300th of a 16-bit level). The standard's two parts do not
#: quite meet; with this knee every value :func:`decode` gives is encoded by the part it
#: came from, so encode(decode(v)) == v to float rounding for every v: a file read and
#: written back keeps its values. The other way round, decode(encode(L)) == L to float
#: rounding but for L in the gap between the parts (0.0031308050 to 0.0031308073),
#: which comes back within 2.4e-9.
SRGB_LINEAR_KNEE = SRGB_ENCODED_KNEE / SRGB_SLOPE


def check_encoding(encoding: str) -> str:
    """``encoding`` when it is one of :data:`ENCODINGS`.

    Raises
    ------
    ImageError
        Naming the encodings known.
    """
    if encoding not in ENCODINGS:
        raise ImageError(f"unknown image encoding {encoding!r} (use {' or '.join(ENCODINGS)})")
    return encoding


def decode(values: np.ndarray, encoding: str) -> np.ndarray:
    """Linear light from encoded values.

    Parameters
    ----------
    values : ndarray, any shape
        Values on the file's [0, 1] scale (as :func:`bigT.images.read_image` returns).
    encoding : one of :data:`ENCODINGS`

    Returns
    -------
    ndarray, the shape of ``values``, float64
        A new array (never ``values`` itself).
    """
    v = np.array(values, dtype=np.float64)  # a copy: the result is the caller's to keep
    if check_encoding(encoding) == "linear":
        return v
    power = v > SRGB_ENCODED_KNEE
    v[power] = ((v[power] + SRGB_OFFSET) / (1.0 + SRGB_OFFSET)) ** SRGB_GAMMA
    v[~power] /= SRGB_SLOPE
    return v


def encode(linear: np.ndarray, encoding: str) -> np.ndarray:
    """Encoded values from linear light: the inverse of :func:`decode`.

    Parameters
    ----------
    linear : ndarray, any shape
    encoding : one of :data:`ENCODINGS`

    Returns
    -------
    ndarray, the shape of ``linear``, float64, a new array
        Values on the file's [0, 1] scale, ready for :func:`bigT.images.write_image`.
    """
    v = np.array(linear, dtype=np.float64)
    if check_encoding(encoding) == "linear":
        return v
    power = v > SRGB_LINEAR_KNEE
    v[power] = (1.0 + SRGB_OFFSET) * v[power] ** (1.0 / SRGB_GAMMA) - SRGB_OFFSET
    v[~power] *= SRGB_SLOPE
    return v


def default_encoding(bits, channels: int, requested: str | None = None) -> str:
    """The encoding of an image, by bigT's policy.

    Parameters
    ----------
    bits : int, numpy dtype, or None
        How the image is stored: 8 or 16 (bits per sample), or the stored pixel type
        (``uint8``, ``uint16``, a float type); None for floats or unknown.
    channels : int
        1 (grey) or 3 (colour).
    requested : one of :data:`ENCODINGS`, optional
        What the user said (``--encoding``); it always wins.

    Returns
    -------
    str
        ``requested`` when given; else ``"srgb"`` for an 8-bit colour image, else
        ``"linear"`` (16-bit and float images, and grey images: bigT's grey behaviour
        is unchanged).
    """
    if requested is not None:
        return check_encoding(requested)
    return "srgb" if channels == 3 and _eight_bit(bits) else "linear"


def _eight_bit(bits) -> bool:
    """True for 8 bits per sample, given as a count or as the stored pixel type."""
    if bits is None:
        return False
    if isinstance(bits, (int, np.integer)):
        return int(bits) == 8
    return np.dtype(bits) == np.uint8
