"""The projector's integer values: compensation's linear output encoded through the
inverse of the projector's measured response (docs/CALIBRATION.md, issue #29).

``compensate`` computes l_in = X l_desired in *linear light above the projector's black,
in units of a full-scale pattern's* -- T's units, as ``acquire build`` measured it. A
real projector's light is a curve of the value it is sent (gamma near 2.2, a black
level, a shoulder), so the image to send is r^-1(l_in) quantised to the projector's
8 or 16 bits (:meth:`bigT.calibration.ProjectorResponse.encode` with
``above_black=True``: 0 is sent as 0, 1 as the top code; light below black or above
full scale cannot be emitted, it is clipped and counted).

:class:`ProjectorEncoder` gives exactly the codes of ``ProjectorResponse.encode``, from
lookup tables (one per channel) built once: the code a light rounds to is the number of
half-code boundaries below it (``np.searchsorted`` on the response's own dense table,
the one its inverse interpolates on), about 3x faster than inverting value by value
(65 against 210 ms a 384x512 colour frame, 8-bit ordered, on this machine), which
a video's frames need. :meth:`ProjectorEncoder.emitted` is the other way: the light
(above black) the projector sends for codes, what ``compensate --simulate`` relights
through T so that the loop closes through the same projector.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ..calibration import ProjectorResponse, load_projector_response
from ..calibration.dither import DITHER_KINDS, thresholds
from ..calibration.response import INVERSE_TABLE_LEVELS
from ..errors import ImageError

#: Bit depths a projector takes.
PROJECTOR_BITS = (8, 16)


@dataclass(frozen=True)
class ResponseClipping:
    """Values the projector could not emit, per channel, over a run.

    Attributes
    ----------
    below, above : tuple of int, per channel: below the projector's black (sent as 0),
        above its full scale (sent as the top code)
    values : int, values per channel encoded
    channels : tuple of str, ``("grey",)`` or ``("R", "G", "B")``
    """

    below: tuple[int, ...]
    above: tuple[int, ...]
    values: int
    channels: tuple[str, ...]

    def describe(self) -> str:
        """``projector response clipped 1.20 % of values (below black / above full
        scale, per channel: R 1.00 / 0.20 %, ...)``."""
        share = (lambda count: 100 * count / max(self.values, 1))
        total = 100 * (sum(self.below) + sum(self.above)) / max(self.values * len(self.channels), 1)
        parts = ", ".join(f"{name} {self.below[c]} ({share(self.below[c]):.2f} %) / "
                          f"{self.above[c]} ({share(self.above[c]):.2f} %)"
                          for c, name in enumerate(self.channels))
        return (f"clipped by the projector's response: {total:.2f} % of values; below black "
                f"/ above full scale, per channel: {parts} (of {self.values} per channel)")

    def to_dict(self) -> dict:
        return {name: {"below_black": self.below[c], "above_full_scale": self.above[c]}
                for c, name in enumerate(self.channels)} | {"values": self.values}


class ProjectorEncoder:
    """Linear light above black -> the projector's integer codes, and back.

    Parameters
    ----------
    response : ProjectorResponse
    bits : 8 or 16, the projector's input depth
    dither : ``"none"``, ``"ordered"`` or ``"random"`` (:mod:`bigT.calibration.dither`)
    seed : int, of ``"random"`` (frame k of a run draws with ``seed + k``: no two frames
        share a pattern)
    source : str, where the response came from (the header names it)

    Attributes
    ----------
    clipping : ResponseClipping, what the encodings so far clipped
    """

    def __init__(self, response: ProjectorResponse, bits: int = 8, dither: str = "none",
                 seed: int = 0, source: str = "given"):
        if bits not in PROJECTOR_BITS:
            raise ImageError(f"the projector's bit depth must be 8 or 16, not {bits!r}")
        if dither not in DITHER_KINDS:
            raise ImageError(f"unknown dither {dither!r} (use {', '.join(DITHER_KINDS)})")
        self.response, self.bits, self.dither, self.seed = response, int(bits), dither, int(seed)
        self.source = source
        self.top = (1 << self.bits) - 1
        C = response.n_channels
        self._below, self._above = np.zeros(C, np.int64), np.zeros(C, np.int64)
        self._values = 0
        self._frames = 0

    @property
    def channels(self) -> int:
        return self.response.n_channels

    @property
    def dtype(self):
        return np.uint8 if self.bits == 8 else np.uint16

    def describe(self) -> str:
        """``projector response FILE (black 0.02, 8-bit, dithered ordered)``."""
        black = "/".join(f"{b:.3g}" for b in self.response.black)
        dither = "not dithered" if self.dither == "none" else f"dithered {self.dither}"
        return (f"projector response {self.source} (black {black}, {self.bits}-bit, "
                f"{dither}): writing the projector's values, the linear light encoded "
                "through its inverse")

    # --- the tables ----------------------------------------------------------------

    @cached_property
    def _light_of_codes(self) -> np.ndarray:
        """(2^bits, C): the absolute light r(k / top) of every code (r(0) the black)."""
        # k / top exactly as ProjectorResponse.encode divides (linspace may differ by an ulp)
        return self._forward(np.arange(self.top + 1) / self.top)

    @cached_property
    def _boundaries(self) -> tuple[np.ndarray, np.ndarray]:
        """(top, C) each: the light of the inverse's table at the half-code points
        (j - 1/2) / top and at the codes j / top, j = 1..top. The code a light l rounds
        to is the count of half-code points below it; the code below it (dither), the
        count of code points below it."""
        grid = np.linspace(0.0, 1.0, INVERSE_TABLE_LEVELS)
        table = np.maximum.accumulate(self._forward(grid), axis=0)
        j = np.arange(1, self.top + 1, dtype=np.float64)

        def at(values):  # the inverse's piecewise-linear table, as it interpolates
            return np.stack([np.interp(values, grid, table[:, c])
                             for c in range(self.channels)], axis=1)

        return at((j - 0.5) / self.top), at(j / self.top)

    def _forward(self, values: np.ndarray) -> np.ndarray:
        """(N,) values -> (N, C) absolute light r(v)."""
        if self.channels == 1:
            return self.response.to_linear(values)[:, None]
        return self.response.to_linear(np.repeat(values[:, None], self.channels, axis=1))

    # --- encoding ------------------------------------------------------------------

    def wanted(self, linear: np.ndarray, c: int) -> np.ndarray:
        """Absolute light asked of channel c for light above black ``linear``, clipped
        to what the projector emits (as ``ProjectorResponse.inverse(above_black=True)``)."""
        b = float(self.response.black[c])
        return np.clip(b + np.asarray(linear, dtype=np.float64) * (1.0 - b), b, 1.0)

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Frames of linear light above black -> the projector's codes.

        Parameters
        ----------
        frames : ndarray, shape (K, H, W) (grey) or (K, H, W, 3) (colour)

        Returns
        -------
        ndarray of uint8 (8 bits) or uint16 (16 bits), the shape of ``frames``; the
        values clipped are counted into :attr:`clipping`
        """
        frames = np.asarray(frames)
        colour = self.channels > 1
        if frames.ndim < 3 or (colour and frames.shape[-1] != self.channels):
            raise ImageError(f"frames of shape {frames.shape} given to a "
                             f"{self.channels}-channel projector response")
        spatial = frames.shape[:-1] if colour else frames.shape
        threshold = None
        if self.dither != "none":
            seed = self.seed + self._frames if self.dither == "random" else self.seed
            threshold = thresholds(self.dither, spatial, seed)
        halves, points = self._boundaries
        light = self._light_of_codes
        out = np.empty(frames.shape, dtype=self.dtype)
        for c in range(self.channels):
            values = frames[..., c] if colour else frames
            self._count(values, c)
            wanted = self.wanted(values, c)
            if threshold is None:
                codes = np.searchsorted(halves[:, c], wanted, side="left")
            else:
                lower = np.minimum(np.searchsorted(points[:, c], wanted, side="left"),
                                   self.top - 1)
                dark, bright = light[lower, c], light[lower + 1, c]
                step = bright - dark
                p = np.divide(wanted - dark, step, out=np.zeros_like(step), where=step > 0)
                codes = lower + (p > threshold)
            if colour:
                out[..., c] = codes
            else:
                out[...] = codes
        self._values += int(np.prod(spatial, dtype=np.int64))
        self._frames += frames.shape[0]
        return out

    def _count(self, values: np.ndarray, c: int) -> None:
        self._below[c] += int(np.count_nonzero(values < 0))
        self._above[c] += int(np.count_nonzero(values > 1))

    @property
    def clipping(self) -> ResponseClipping:
        names = self.response.channels
        return ResponseClipping(tuple(int(v) for v in self._below),
                                tuple(int(v) for v in self._above), self._values, names)

    def to_unit(self, codes: np.ndarray) -> np.ndarray:
        """Codes as the [0, 1] values the image and video writers quantise back to the
        same codes at :attr:`bits` (code / (2^bits - 1), float32)."""
        return codes.astype(np.float32) / np.float32(self.top)

    def emitted(self, codes: np.ndarray) -> np.ndarray:
        """The light above black, in units of full scale, the projector sends for
        ``codes`` (the shape of ``codes``, float64): (r(k / top) - b) / (1 - b)."""
        light = self._light_of_codes
        if self.channels == 1:
            b = light[0, 0]
            return (light[codes, 0] - b) / (1.0 - b)
        out = np.empty(codes.shape, dtype=np.float64)
        for c in range(self.channels):
            b = light[0, c]
            out[..., c] = (light[codes[..., c], c] - b) / (1.0 - b)
        return out


def projector_encoder(response, *, bits: int | None = None, dither: str = "none",
                      seed: int = 0, found: Path | None = None) -> ProjectorEncoder | None:
    """The encoder a compensation uses, or None (linear light written, as before).

    Parameters
    ----------
    response : None, ``"auto"``, a path, or a ProjectorResponse
        ``"auto"``: the one stored with T, ``found`` (None: no response).
    bits : 8 or 16, default 8
    dither, seed : as :class:`ProjectorEncoder`
    found : Path, optional, the response stored with T (for ``"auto"``)
    """
    if response is None or (isinstance(response, str) and response == "auto" and found is None):
        return None
    if isinstance(response, ProjectorResponse):
        loaded, source = response, "given"
    else:
        path = found if isinstance(response, str) and response == "auto" else Path(response)
        loaded = _load_response(path)
        source = f"{path}, stored with T," if response == "auto" else str(path)
    return ProjectorEncoder(loaded, 8 if bits is None else bits, dither, seed, source)


def _load_response(path) -> ProjectorResponse:
    """:func:`load_projector_response` of a file, or of an object of the store in
    object storage (copied to a temporary file first: the calibration layer reads
    files)."""
    from ..storage import ObjectPath

    if not isinstance(path, ObjectPath):
        return load_projector_response(path)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="bigT-response-") as tmp:
        local = Path(tmp) / path.name
        local.write_bytes(path.read_bytes(RESPONSE_MAX_BYTES))
        return load_projector_response(local)


#: The largest projector response read from object storage (a 4096-level ramp of 3
#: channels is ~300 KB of JSON).
RESPONSE_MAX_BYTES = 16 << 20


__all__ = ["ProjectorEncoder", "ResponseClipping", "projector_encoder", "PROJECTOR_BITS"]
