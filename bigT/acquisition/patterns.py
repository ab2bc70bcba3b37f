"""Pattern images (what the projector shows) and the Gray code (encode, decode).

Every pattern is a binary image at the projector's resolution, lit where a super-pixel
of the manifest's grid is lit; in a colour set, an RGB image lit in the pattern's
primary only (or in all three: black, white, the Gray code). The Gray code follows OpenCV's
``structured_light.GrayCodePattern``: the code of a grid coordinate x is
``x ^ (x >> 1)``, bits most significant first, every pattern followed by its inverse;
a camera pixel reads bit b as 1 where the pattern is brighter than its inverse, and is
left undecoded where the all-white and all-black captures differ by too little (a
shadow) or any bit's pattern and inverse differ by too little (ambiguous), the roles of
OpenCV's ``blackThreshold`` and ``whiteThreshold``. OpenCV's are absolute (40 and 5 of
255), which leaves a dim capture (a dark surface, a short exposure, a 16-bit camera
using a tenth of its range) all in shadow; here they are relative: a shadow is a contrast
within the noise, an ambiguous bit one whose difference is within the noise or a small
share of the pixel's own contrast (white - black).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..images import write_image
from ..progress import progress_bar
from .manifest import Manifest, Pattern, write_manifest

#: A pixel is in shadow unless white - black exceeds this many standard deviations of
#: the difference of two captures (sqrt 2 x a pixel's noise).
GRAYCODE_SHADOW_SIGMAS = 6.0
#: A bit is ambiguous unless |pattern - inverse| exceeds this many standard deviations
#: of the difference of two captures ...
GRAYCODE_AMBIGUITY_SIGMAS = 3.0
#: ... and this share of the pixel's contrast white - black (OpenCV's 5 of its least
#: contrast, 40, is 0.125). A pixel lit by the projector directly differs by most of its
#: contrast (0.48 or more on the corner scene), one seen by interreflected light alone
#: differs by little on the finest bits, whose stripes light its surroundings evenly.
GRAYCODE_AMBIGUITY_SHARE = 0.1


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
    if pattern.kind in ("white", "ramp"):  # a ramp lights all, at its level
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
    ndarray, float64 in {0, 1} (a ramp pattern: its level): shape manifest.projector
        (grey set), or
        (*manifest.projector, 3) (colour set: lit in the pattern's primary only, or in all
        three when it has none)
    """
    s = manifest.superpixel
    if pattern.kind == "ramp":  # uniform at its level
        image = np.full(manifest.projector, float(pattern.level))
    else:
        lit = lit_superpixels(manifest, pattern)
        image = np.repeat(np.repeat(lit, s, axis=0), s, axis=1).astype(np.float64)
    if manifest.channels == 1:
        return image
    primaries = np.ones(3) if pattern.primary is None else np.eye(3)[pattern.primary_index]
    return image[:, :, None] * primaries


def write_patterns(folder, manifest: Manifest, *, progress: bool | None = None) -> Path:
    """Write every pattern as an 8-bit PNG (RGB for a colour set) and ``manifest.json``
    (last, so a folder with a manifest is complete) into ``folder``.

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


def decode_graycode(manifest: Manifest, read, *, noise: float = 0.0,
                    shadow_sigmas: float = GRAYCODE_SHADOW_SIGMAS,
                    ambiguity_sigmas: float = GRAYCODE_AMBIGUITY_SIGMAS,
                    ambiguity_share: float = GRAYCODE_AMBIGUITY_SHARE) -> np.ndarray:
    """The projector super-pixel each camera pixel sees, from the Gray-code captures.

    Parameters
    ----------
    manifest : Manifest with ``graycode``
    read : callable
        ``read(pattern) -> ndarray (Hc, Wc)``: the linear capture of a pattern (black
        level not subtracted; only differences are used). Called once per pattern, so
        at most four captures are in memory at a time.
    noise : float
        Standard deviation of one pixel of one capture (quantisation included); 0 for
        noiseless captures (then any positive contrast counts).
    shadow_sigmas, ambiguity_sigmas, ambiguity_share : float
        A pixel is decoded where ``white - black > shadow_sigmas * sqrt(2) * noise`` and,
        for every bit, ``|pattern - inverse| > max(ambiguity_sigmas * sqrt(2) * noise,
        ambiguity_share * (white - black))`` (see the module docstring).

    Returns
    -------
    ndarray, shape (Hc, Wc), int64
        Row-major super-pixel index, -1 where the pixel is undecoded (shadow, an
        ambiguous bit, or a code beyond the grid).
    """
    white, black = read(manifest.single("white")), read(manifest.single("black"))
    contrast = white - black
    del white
    difference_noise = np.sqrt(2.0) * noise  # of a difference of two captures
    valid = contrast > shadow_sigmas * difference_noise
    ambiguous = np.maximum(ambiguity_sigmas * difference_noise, ambiguity_share * contrast)
    coords = {}
    for axis in ("col", "row"):
        bits = manifest.graycode_bits(axis)
        code = np.zeros(contrast.shape, dtype=np.int64)
        for bit in range(bits):
            on, off = (read(_graycode_pattern(manifest, axis, bit, inv)) for inv in (False, True))
            valid &= np.abs(on - off) > ambiguous
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
