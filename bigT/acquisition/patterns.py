"""Pattern images (what the projector shows) and the Gray code (encode, decode).

Every pattern is a binary image at the projector's resolution, lit where a super-pixel
of the manifest's grid is lit. The Gray code follows OpenCV's
``structured_light.GrayCodePattern``: the code of a grid coordinate x is
``x ^ (x >> 1)``, bits most significant first, every pattern followed by its inverse;
a camera pixel reads bit b as 1 where the pattern is brighter than its inverse, and is
left undecoded where the all-white and all-black captures differ by less than a black
threshold (a shadow) or any bit's pattern and inverse differ by less than a white
threshold (ambiguous), OpenCV's ``blackThreshold`` and ``whiteThreshold``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..images import write_image
from ..progress import progress_bar
from .manifest import Manifest, Pattern, write_manifest

#: OpenCV's defaults (40 and 5 on 8-bit values), as fractions of full scale.
GRAYCODE_BLACK_THRESHOLD = 40 / 255
GRAYCODE_WHITE_THRESHOLD = 5 / 255


def gray(x: np.ndarray) -> np.ndarray:
    """Gray code of non-negative integers."""
    return x ^ (x >> 1)


def gray_to_binary(g: np.ndarray, bits: int) -> np.ndarray:
    """Inverse of :func:`gray` for codes of ``bits`` bits."""
    x = g.copy()
    shift = 1
    while shift < bits:
        x ^= x >> shift
        shift <<= 1
    return x


def lit_superpixels(manifest: Manifest, pattern: Pattern) -> np.ndarray:
    """Which super-pixels ``pattern`` lights.

    Returns
    -------
    ndarray, shape manifest.grid, bool
    """
    gh, gw = manifest.grid
    rows, cols = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
    if pattern.kind == "black":
        return np.zeros((gh, gw), dtype=bool)
    if pattern.kind == "white":
        return np.ones((gh, gw), dtype=bool)
    if pattern.kind == "superpixel":
        return (rows * gw + cols) == pattern.index
    if pattern.kind == "row-stripe":
        return rows == pattern.band
    if pattern.kind == "col-stripe":
        return cols == pattern.band
    coord = cols if pattern.axis == "col" else rows
    bits = manifest.graycode_bits(pattern.axis)
    lit = (gray(coord) >> (bits - 1 - pattern.bit)) & 1 == 1
    return ~lit if pattern.inverted else lit


def pattern_image(manifest: Manifest, pattern: Pattern) -> np.ndarray:
    """The image the projector shows for ``pattern``.

    Returns
    -------
    ndarray, shape manifest.projector, float64 in {0, 1}
    """
    s = manifest.superpixel
    lit = lit_superpixels(manifest, pattern)
    return np.repeat(np.repeat(lit, s, axis=0), s, axis=1).astype(np.float64)


def write_patterns(folder, manifest: Manifest, *, progress: bool | None = None) -> Path:
    """Write every pattern as an 8-bit PNG and ``manifest.json`` (last, so a folder with
    a manifest is complete) into ``folder``.

    Returns
    -------
    pathlib.Path, the manifest file
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for pattern in progress_bar(manifest.patterns, progress=progress, desc="patterns",
                                unit="image"):
        write_image(folder / pattern.file, pattern_image(manifest, pattern), bits=8)
    return write_manifest(folder, manifest)


def decode_graycode(manifest: Manifest, read, *, black_threshold: float = GRAYCODE_BLACK_THRESHOLD,
                    white_threshold: float = GRAYCODE_WHITE_THRESHOLD) -> np.ndarray:
    """The projector super-pixel each camera pixel sees, from the Gray-code captures.

    Parameters
    ----------
    manifest : Manifest with ``graycode``
    read : callable
        ``read(pattern) -> ndarray (Hc, Wc)``: the linear capture of a pattern (black
        level not subtracted; only differences are used). Called once per pattern, so
        at most four captures are in memory at a time.
    black_threshold, white_threshold : float
        Shadow and ambiguity thresholds (see the module docstring).

    Returns
    -------
    ndarray, shape (Hc, Wc), int64
        Row-major super-pixel index, -1 where the pixel is undecoded (shadow, an
        ambiguous bit, or a code beyond the grid).
    """
    white, black = read(manifest.single("white")), read(manifest.single("black"))
    valid = (white - black) > black_threshold
    coords = {}
    for axis in ("col", "row"):
        bits = manifest.graycode_bits(axis)
        code = np.zeros(white.shape, dtype=np.int64)
        for bit in range(bits):
            on, off = (read(_graycode_pattern(manifest, axis, bit, inv)) for inv in (False, True))
            valid &= np.abs(on - off) >= white_threshold
            code = (code << 1) | (on > off)
        coords[axis] = gray_to_binary(code, bits)
    gh, gw = manifest.grid
    valid &= (coords["row"] < gh) & (coords["col"] < gw)
    return np.where(valid, coords["row"] * gw + coords["col"], -1)


def _graycode_pattern(manifest: Manifest, axis: str, bit: int, inverted: bool) -> Pattern:
    for p in manifest.of_kind("graycode"):
        if (p.axis, p.bit, p.inverted) == (axis, bit, inverted):
            return p
    raise KeyError((axis, bit, inverted))
