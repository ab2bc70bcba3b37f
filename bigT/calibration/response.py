"""The projector's response: what linear light it emits for the value it is sent, fitted
from a ramp of uniform frames, inverted to encode a linear image into the integer
values the projector is sent (docs/CALIBRATION.md has the derivations).

Per channel (one for grey, three for colour), the ramp's mean linear camera signals
m(v) at levels v = 0 .. 1 are

1. checked: monotone within the noise (a fall by more than 3 sqrt(2) noise between two
   consecutive levels is refused, naming the channel and the levels), and not flat;
2. made monotone by isotonic regression (``scipy.optimize.isotonic_regression``: the
   least-squares monotone fit, pooling the noisy near-black levels a gamma curve hardly
   separates);
3. normalised: r(v) = m(v) / m(1), so that r(1) = 1. The transport T is measured with
   patterns at full scale: its column p is the light of projector pixel p sent 1 (less
   the black capture). With r(1) = 1, linear light 1 is that same full-scale light, so
   T's units and the response's agree whatever the camera's exposure or the scene's
   albedo (both scale m and cancel in the ratio). The black level b = r(0) > 0 -- the
   light a projector leaks when sent 0 -- is kept: a model without it would ask for
   light below black near 0 and mis-place every dark value;
4. interpolated by the monotone piecewise-cubic Hermite interpolant
   (``scipy.interpolate.PchipInterpolator``), monotone wherever the data are.

The inverse maps linear light back to the projector's value by interpolation on a
dense table of the fitted curve (65,537 levels, far finer than a 16-bit code). Values
below black or above full scale cannot be emitted: they are clipped, and
:meth:`ProjectorResponse.clipping` counts them.

Light above black. ``acquire build`` subtracts the black capture from every capture,
so T maps light *above* the projector's black, in units of a full-scale pattern's:
x = (r(v) - b) / (1 - b). The methods take ``above_black=True`` to work in those units,
the ones ``compensate``'s T^-1 l produces: x = 0 is sent as 0, x = 1 as 1.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import CalibrationError
from . import dither as dithering
from ._files import number_array, read_document, string_list
from ._monotone import invert_table

#: Fewest levels of a ramp (the issue's 17: 1/16 steps, so a gamma curve's interpolation
#: error stays below a few 1e-3 of full scale, tests/calibration measure it).
MIN_RAMP_LEVELS = 17
#: Most levels a ramp (or a response file) may have.
MAX_RAMP_LEVELS = 4097
#: Smallest ratio m(1) / m(0) of a ramp's brightest to darkest mean (black-subtracted
#: ramps, m(0) near 0, pass): below it the ramp is flat (projector off, camera
#: saturated or blind) and refused.
MIN_DYNAMIC_RANGE = 2.0
#: A ramp whose span m(1) - m(0) is under this many noise tolerances is flat too.
MIN_SPAN_IN_TOLERANCES = 10.0
#: Noise assumed, as a fraction of the channel's span, when the caller gives none.
DEFAULT_NOISE_FRACTION = 0.002
#: Levels of the dense table the inverse interpolates on.
INVERSE_TABLE_LEVELS = 65537
#: Channel names by channel count, as messages and files spell them.
CHANNEL_NAMES = {1: ("grey",), 3: ("R", "G", "B")}
FORMAT_KIND = "bigT.projector_response"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class Clipping:
    """How many values of a linear image the projector cannot emit, per channel.

    Attributes
    ----------
    below : tuple of int, values below the projector's black (sent as 0)
    above : tuple of int, values above full scale (sent as the top code)
    size : int, values per channel
    """

    below: tuple[int, ...]
    above: tuple[int, ...]
    size: int

    def describe(self) -> str:
        """``"3 values below black, 12 above full scale (of 4800 per channel)"``."""
        return (f"{sum(self.below)} values below black, {sum(self.above)} above full "
                f"scale (of {self.size} per channel)")


@dataclass(frozen=True, eq=False)
class ProjectorResponse:
    """A projector's fitted response, one curve per channel.

    Attributes
    ----------
    levels : ndarray, shape (L,), float64
        The ramp's input values, strictly increasing from 0 to 1.
    output : ndarray, shape (L, C), float64
        The fitted (monotone) linear light at each level, normalised so that
        ``output[-1] == 1``; ``output[0]`` is the black level.
    measured : ndarray, shape (L, C), float64
        The ramp's means as measured, on the same normalisation (drawn as points).
    channels : tuple of str, ``("grey",)`` or ``("R", "G", "B")``
    """

    levels: np.ndarray
    output: np.ndarray
    measured: np.ndarray
    channels: tuple[str, ...] = field(default=("grey",))

    def __post_init__(self):
        for name in ("levels", "output", "measured"):
            array = np.array(getattr(self, name), dtype=np.float64)
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def black(self) -> np.ndarray:
        """The black level r(0) per channel, shape (C,), relative to full scale."""
        return self.output[0]

    @property
    def n_channels(self) -> int:
        return len(self.channels)

    @cached_property
    def _curves(self):
        from scipy.interpolate import PchipInterpolator  # scipy.interpolate: ~0.1 s

        return [PchipInterpolator(self.levels, self.output[:, c]) for c in range(self.n_channels)]

    @cached_property
    def _inverse_table(self) -> tuple[np.ndarray, np.ndarray]:
        grid = np.linspace(0.0, 1.0, INVERSE_TABLE_LEVELS)
        light = np.stack([self._evaluate(grid, c) for c in range(self.n_channels)], axis=1)
        return grid, np.maximum.accumulate(light, axis=0)  # rounding never makes it fall

    def _evaluate(self, values: np.ndarray, c: int) -> np.ndarray:
        # PCHIP of monotone data is monotone; the clip only removes rounding below 0
        return np.maximum(self._curves[c](np.clip(values, 0.0, 1.0)), 0.0)

    def _per_channel(self, array: np.ndarray, function) -> np.ndarray:
        """``function(values, c)`` applied to each channel of ``array`` (any shape for
        one channel, (..., C) for C)."""
        array = np.asarray(array, dtype=np.float64)
        if self.n_channels == 1:
            return function(array, 0)
        if array.ndim == 0 or array.shape[-1] != self.n_channels:
            raise CalibrationError(f"an array of shape {array.shape} given to a "
                                   f"{self.n_channels}-channel projector response: its last "
                                   f"axis must have {self.n_channels} entries")
        return np.stack([function(array[..., c], c) for c in range(self.n_channels)], axis=-1)

    def to_linear(self, values, *, above_black: bool = False) -> np.ndarray:
        """The linear light the projector emits for ``values``.

        Parameters
        ----------
        values : array_like, any shape (one channel) or (..., C)
            Projector values in [0, 1] (clipped to it).
        above_black : bool
            Light above black, (r(v) - b) / (1 - b), the units of a T built from
            black-subtracted captures; else r(v) with r(1) = 1 and r(0) = b.

        Returns
        -------
        ndarray of float64, the shape of ``values``
        """
        def forward(v, c):
            light = self._evaluate(v, c)
            return self._to_excess(light, c) if above_black else light

        return self._per_channel(values, forward)

    def _to_excess(self, light, c):
        b = self.black[c]
        return (light - b) / (1.0 - b)

    def _target(self, linear, c, above_black):
        """The absolute light r asked for, clipped to what the projector emits."""
        b = self.black[c]
        light = b + linear * (1.0 - b) if above_black else linear
        return np.clip(light, b, 1.0)

    def inverse(self, linear, *, above_black: bool = False) -> np.ndarray:
        """The projector value whose light is ``linear`` (monotone inverse).

        Parameters
        ----------
        linear : array_like, any shape (one channel) or (..., C)
            Linear light; below black or above full scale it is clipped
            (:meth:`clipping` counts those values).
        above_black : bool, as for :meth:`to_linear`

        Returns
        -------
        ndarray of float64 in [0, 1], the shape of ``linear``
        """
        grid, table = self._inverse_table

        def backward(l, c):
            return invert_table(self._target(l, c, above_black), table[:, c], grid)

        return self._per_channel(linear, backward)

    def clipping(self, linear, *, above_black: bool = False) -> Clipping:
        """How many values of ``linear`` lie below black or above full scale, per
        channel (what :meth:`inverse` and :meth:`encode` clip)."""
        linear = np.asarray(linear, dtype=np.float64)
        below, above = [], []

        def count(l, c):
            b = 0.0 if above_black else self.black[c]
            below.append(int(np.count_nonzero(l < b)))
            above.append(int(np.count_nonzero(l > 1.0)))
            return l

        self._per_channel(linear, count)
        size = linear.size // self.n_channels
        return Clipping(tuple(below), tuple(above), size)

    def encode(self, linear, bits: int = 8, dither: bool | str = False, seed: int = 0, *,
               above_black: bool = False) -> np.ndarray:
        """The integer image to send the projector so that it emits ``linear``.

        Parameters
        ----------
        linear : array_like, shape (H, W) or (K, H, W) for one channel, (..., 3) for colour
            Linear light (clipped to what the projector emits, see :meth:`clipping`).
        bits : 8 or 16, the projector's input depth: codes 0 .. 2^bits - 1
        dither : False, True, ``"none"``, ``"ordered"`` or ``"random"``
            False/``"none"`` rounds to the nearest code of the inverse. Otherwise the
            value is placed between the two codes k, k + 1 that bracket it, at the
            fraction p of the way *in light* (r(k), r(k + 1)), and sent as k + 1 where p
            exceeds the pixel's threshold (:mod:`bigT.calibration.dither`): the
            expected light is the one asked, exactly. True means ``"ordered"`` (the
            8 x 8 Bayer matrix: the same in every frame, no flicker in video).
        seed : int, the threshold generator's seed for ``"random"``
        above_black : bool, as for :meth:`to_linear`

        Returns
        -------
        ndarray of uint8 (bits 8) or uint16 (bits 16), the shape of ``linear``
        """
        if bits not in (8, 16):
            raise CalibrationError(f"the projector's bit depth must be 8 or 16, not {bits!r}")
        kind = _dither_kind(dither)
        top = (1 << bits) - 1
        codes = self.inverse(linear, above_black=above_black) * top
        if kind == "none":
            return np.rint(codes).astype(np.uint8 if bits == 8 else np.uint16)
        linear = np.asarray(linear, dtype=np.float64)
        spatial = linear.shape if self.n_channels == 1 else linear.shape[:-1]
        threshold = dithering.thresholds(kind, spatial, seed)
        if self.n_channels > 1:
            threshold = threshold[..., None]
        lower = np.clip(np.floor(codes), 0, top - 1)

        def fraction(l, c):  # where the wanted light lies between codes k and k + 1
            k = lower if self.n_channels == 1 else lower[..., c]
            dark, bright = self._evaluate(k / top, c), self._evaluate((k + 1) / top, c)
            step = bright - dark
            wanted = self._target(l, c, above_black)
            return np.divide(wanted - dark, step, out=np.zeros_like(step), where=step > 0)

        up = self._per_channel(linear, fraction) > threshold
        return (lower + up).astype(np.uint8 if bits == 8 else np.uint16)

    def to_document(self) -> dict:
        """The JSON document :meth:`save` writes (docs/CALIBRATION.md)."""
        return {"format": FORMAT_KIND, "version": FORMAT_VERSION,
                "channels": list(self.channels),
                "levels": self.levels.tolist(),
                "output": self.output.tolist(),
                "measured": self.measured.tolist()}

    def save(self, path: str | os.PathLike) -> Path:
        """Write the response as JSON, whole or not at all."""
        import json

        from ..atomic import atomic_output

        path = Path(path)
        text = json.dumps(self.to_document(), indent=1, allow_nan=False)
        with atomic_output(path, "the projector response") as tmp:
            tmp.write_text(text, encoding="utf-8")
        return path

    def draw(self, path: str | os.PathLike, title: str | None = None) -> Path:
        """A PNG of the measured points and the fitted curve, per channel."""
        from ..figures import pyplot, save_figure

        plt = pyplot()
        fig, ax = plt.subplots(figsize=(5.6, 4.2))
        grid = np.linspace(0.0, 1.0, 513)
        colours = {"grey": "k", "R": "tab:red", "G": "tab:green", "B": "tab:blue"}
        for c, name in enumerate(self.channels):
            colour = colours[name]
            ax.plot(grid, self._evaluate(grid, c), color=colour, lw=1.3,
                    label=f"{name} fitted (black {self.black[c]:.3g})")
            ax.plot(self.levels, self.measured[:, c], "o", color=colour, ms=3.5,
                    mfc="none", label=f"{name} measured")
        ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--", label="linear")
        ax.set_xlabel("projector value")
        ax.set_ylabel("linear light (1 = full scale)")
        ax.set_title(title or f"projector response, {len(self.levels)} levels", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
        fig.tight_layout()
        return save_figure(fig, path)


def _dither_kind(dither) -> str:
    if dither is True:
        return "ordered"
    if dither is False or dither is None:
        return "none"
    if dither not in dithering.DITHER_KINDS:
        raise CalibrationError(f"unknown dither {dither!r} "
                               f"(use {', '.join(dithering.DITHER_KINDS)})")
    return dither


def fit_projector_response(levels, captures_mean, *, noise=None,
                           channels: tuple[str, ...] | None = None) -> ProjectorResponse:
    """Fit a projector's response from the captures of a ramp of uniform frames.

    Parameters
    ----------
    levels : array_like, shape (L,)
        The values the ramp's frames were sent, strictly increasing from 0 to 1,
        L >= :data:`MIN_RAMP_LEVELS`.
    captures_mean : array_like, shape (L,) or (L, C)
        Each frame's mean *linear* camera signal (the camera's response undone), per
        channel, with the camera's own dark level removed (a lens-capped frame, a RAW
        black level) but not the projector's black: m(0) is the projector's black.
        A ramp from which the black capture was subtracted also fits (black 0).
    noise : float or array_like broadcastable to (L, C), optional
        Standard deviation of each mean. Default :data:`DEFAULT_NOISE_FRACTION` of the
        channel's span. A fall between consecutive levels of more than 3 sqrt(2) noise
        is not noise.
    channels : tuple of str, optional
        Default ``("grey",)`` for one channel, ``("R", "G", "B")`` for three.

    Returns
    -------
    ProjectorResponse

    Raises
    ------
    CalibrationError
        Too few levels, levels not from 0 to 1, a ramp not monotone beyond the noise or
        flat, in one line naming the channel (and the levels).
    """
    levels, means = _check_ramp(levels, captures_mean)
    C = means.shape[1]
    channels = tuple(channels) if channels is not None else CHANNEL_NAMES.get(C)
    if channels is None or len(channels) != C:
        raise CalibrationError(f"a ramp of {C} channels needs {C} channel names, "
                               f"not {channels!r}")
    span = means[-1] - means[0]
    noise = (DEFAULT_NOISE_FRACTION * np.abs(span) if noise is None
             else np.broadcast_to(np.asarray(noise, dtype=np.float64), means.shape))
    tolerance = 3.0 * np.sqrt(2.0) * np.broadcast_to(noise, means.shape)
    for c in range(C):
        _check_channel(levels, means[:, c], tolerance[:, c], channels[c])
    fitted = _monotone_fit(means, noise)
    full = fitted[-1].copy()
    return ProjectorResponse(levels, np.maximum(fitted / full, 0.0), means / full, channels)


def _check_ramp(levels, captures_mean) -> tuple[np.ndarray, np.ndarray]:
    levels = np.asarray(levels, dtype=np.float64)
    means = np.asarray(captures_mean, dtype=np.float64)
    if means.ndim == 1:
        means = means[:, None]
    if levels.ndim != 1 or means.ndim != 2 or means.shape[0] != levels.size:
        raise CalibrationError(f"a ramp of {levels.shape} levels and {means.shape} means: "
                               "need (L,) levels and (L,) or (L, C) means")
    if not MIN_RAMP_LEVELS <= levels.size <= MAX_RAMP_LEVELS:
        raise CalibrationError(f"a ramp of {levels.size} levels: it needs "
                               f"{MIN_RAMP_LEVELS} to {MAX_RAMP_LEVELS}")
    if means.shape[1] not in CHANNEL_NAMES:
        raise CalibrationError(f"a ramp of {means.shape[1]} channels: 1 (grey) or 3 (RGB)")
    if not (np.isfinite(levels).all() and np.isfinite(means).all()):
        raise CalibrationError("the ramp's levels or means hold a NaN or an infinity")
    if levels[0] != 0.0 or levels[-1] != 1.0 or np.any(np.diff(levels) <= 0):
        raise CalibrationError("the ramp's levels must increase strictly from 0 to 1 "
                               f"(they run {levels[0]:.4g} .. {levels[-1]:.4g})")
    return levels, means


def _check_channel(levels, means, tolerance, name) -> None:
    """Refuse a channel's ramp that falls beyond the noise or is flat."""
    falls = means[:-1] - means[1:] - tolerance[1:]
    if np.any(falls > 0):
        i = int(np.argmax(falls))
        raise CalibrationError(
            f"ramp not monotone in channel {name} between levels {levels[i]:.4g} and "
            f"{levels[i + 1]:.4g} (the mean falls by {means[i] - means[i + 1]:.3g}, more "
            f"than the noise allows: {tolerance[i + 1]:.3g})")
    span = means[-1] - means[0]
    flat_by_noise = span < MIN_SPAN_IN_TOLERANCES * float(np.max(tolerance))
    flat_by_ratio = means[0] > 0 and means[-1] < MIN_DYNAMIC_RANGE * means[0]
    if span <= 0 or flat_by_noise or flat_by_ratio:
        ratio = f"{means[-1] / means[0]:.3g}x" if means[0] > 0 else "no brighter than"
        raise CalibrationError(
            f"ramp flat in channel {name}: full scale is {ratio} the black level (needs "
            f"{MIN_DYNAMIC_RANGE:g}x and a span of {MIN_SPAN_IN_TOLERANCES:g} noise "
            "tolerances; projector off, or the camera saturated or blind?)")


def _monotone_fit(means: np.ndarray, noise) -> np.ndarray:
    """The least-squares non-decreasing fit of each channel, weighted by 1/noise^2."""
    from scipy.optimize import isotonic_regression  # scipy.optimize: ~0.2 s

    noise = np.broadcast_to(np.asarray(noise, dtype=np.float64), means.shape)
    weights = 1.0 / np.maximum(noise, 1e-300) ** 2
    return np.stack([isotonic_regression(means[:, c], weights=weights[:, c]).x
                     for c in range(means.shape[1])], axis=1)


def load_projector_response(path: str | os.PathLike) -> ProjectorResponse:
    """Read a response :meth:`ProjectorResponse.save` wrote (or one measured elsewhere
    in the same format, docs/CALIBRATION.md).

    Raises
    ------
    CalibrationError
        A file too large, not JSON, of another kind, with fields of the wrong type or
        shape, levels not from 0 to 1, or an output that falls; naming the file.
    """
    doc = read_document(path, FORMAT_KIND, FORMAT_VERSION)
    channels = string_list(doc, "channels", path, tuple(CHANNEL_NAMES.values()))
    levels = number_array(doc, "levels", 1, path)
    output = number_array(doc, "output", 2, path)
    measured = number_array(doc, "measured", 2, path) if "measured" in doc else output
    L, C = levels.size, len(channels)
    if not 2 <= L <= MAX_RAMP_LEVELS:
        raise CalibrationError(f"{L} levels: a response has 2 to {MAX_RAMP_LEVELS}", path)
    if output.shape != (L, C) or measured.shape != (L, C):
        raise CalibrationError(f"\"output\" {output.shape} and \"measured\" "
                               f"{measured.shape} must both be ({L}, {C}): levels by channels",
                               path)
    if levels[0] != 0.0 or levels[-1] != 1.0 or np.any(np.diff(levels) <= 0):
        raise CalibrationError("\"levels\" must increase strictly from 0 to 1", path)
    if np.any(np.diff(output, axis=0) < 0) or np.any(output < 0):
        raise CalibrationError("\"output\" falls or is negative: not a monotone response", path)
    if not np.allclose(output[-1], 1.0, rtol=0, atol=1e-9):
        raise CalibrationError("\"output\" must be 1 at level 1 (normalised to full scale)",
                               path)
    return ProjectorResponse(levels, output, measured, channels)
