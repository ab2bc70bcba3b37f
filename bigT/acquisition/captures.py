"""A captures folder read against its pattern manifest: :class:`Captures`.

One camera image per pattern, named as the pattern (any of the image suffixes of
:mod:`bigT.images`); values are made linear (``gamma`` undoes a known camera gamma:
linear = stored ** gamma) and the black capture is subtracted. Every capture is read
when it is needed and dropped after, so the captures are never all in memory.

A colour pattern set (``channels: 3``) has RGB captures, (Hc, Wc, 3); a grey one grey
captures; the other kind is refused in one line naming the file. Where geometry alone
matters (the correspondence) a colour capture is seen through its *grey view*, the mean
of its channels; the noise is estimated for that view and for each channel.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import AcquisitionError
from ..images import IMAGE_SUFFIXES, check_image, is_image_file, read_raw_image
from .manifest import Manifest, Pattern


@dataclass(frozen=True)
class CaptureFormat:
    """What every capture of a folder must share.

    Attributes
    ----------
    shape : (int, int), the camera's (Hc, Wc)
    dtype : str, the stored pixel type (``uint8``, ``uint16``, ``float32``...)
    channels : {1, 3}, grey or RGB
    """

    shape: tuple[int, int]
    dtype: str
    channels: int = 1

    @property
    def full_scale(self) -> int | None:
        """The largest value an integer capture can hold (saturation), None for floats."""
        kind = np.dtype(self.dtype)
        return int(np.iinfo(kind).max) if kind.kind in "ui" else None


@dataclass
class Captures:
    """The captures of ``folder`` for the patterns of ``manifest``.

    Parameters
    ----------
    manifest : Manifest
    folder : path of the captures folder
    gamma : float, the camera's encoding gamma (1: linear captures)
    black_file : path, optional
        A black-level image to subtract instead of the capture of the ``black`` pattern
        (on the captures' scale: values in 0-1 for floats).

    Raises
    ------
    AcquisitionError
        A capture missing or one without a pattern (naming the first few), two files
        for one pattern; captures of different sizes or bit depths, a colour capture of
        a grey pattern set or the reverse, a black frame in raw counts (naming the file).
    """

    manifest: Manifest
    folder: Path
    gamma: float = 1.0
    black_file: Path | None = None
    files: dict[str, Path] = field(init=False)
    format: CaptureFormat = field(init=False)
    saturated: dict[str, int] = field(init=False, default_factory=dict)

    def __post_init__(self):
        self.folder = Path(self.folder)
        if not self.folder.is_dir():
            raise AcquisitionError("no such captures folder", self.folder)
        self.files = _match_files(self.manifest, self.folder)
        self._noise: dict[int | None, float] = {}  # channel (None: grey view) -> sigma
        raw_black = self._reference_format()
        # the black pattern's capture is needed by the noise estimate, every signal
        # (without --black) and the Gray-code decoding: read once, kept
        self._black_capture = self._linear(self.path(self.manifest.single("black")),
                                           raw=raw_black)
        self._black_level = self._black_capture
        if self.black_file:
            # a black frame may be an average of many, so of any pixel type
            raw = _checked_channels(read_raw_image(self.black_file), self.black_file,
                                    self.manifest.channels)
            self._black_level = self._linear(self.black_file, any_type=True, raw=raw)
            self._check_black_scale(raw.dtype)

    def _reference_format(self) -> np.ndarray:
        """Set :attr:`format`: the black capture's size and pixel type, unless the white
        capture and a third agree on another (then the black capture is the odd one, and
        is named when converted). Returns the black capture as stored."""
        def format_of(pattern):
            path = self.path(pattern)
            raw = _checked_channels(read_raw_image(path), path, self.manifest.channels)
            return CaptureFormat(tuple(check_image(raw, path).shape[:2]), raw.dtype.name,
                                 self.manifest.channels), raw

        black, raw_black = format_of(self.manifest.single("black"))
        white, _ = format_of(self.manifest.single("white"))
        others = [p for p in self.manifest.patterns if p.kind not in ("black", "white")]
        self.format = black
        if white != black and others and format_of(others[0])[0] == white:
            self.format = white
        return raw_black

    def _check_black_scale(self, dtype: np.dtype) -> None:
        """A ``--black`` frame of floats above the integer captures' full scale holds raw
        counts (the mean of 8- or 16-bit frames taken in numpy keeps their scale): every
        signal would come out negative and the white capture be blamed for being black."""
        top = self.format.full_scale
        level = self._black_level
        if top is not None and dtype.kind == "f" and level.max() > 1.0:
            raise AcquisitionError(
                f"black level up to {level.max():.6g}, above the {self.format.dtype} "
                f"captures' full scale of 1: a float black frame holds values on the "
                f"captures' 0-1 scale, not raw counts (divide it by {top})", self.black_file)

    @property
    def shape(self) -> tuple[int, int]:
        """The camera's (Hc, Wc)."""
        return self.format.shape

    @property
    def channels(self) -> int:
        """1 (grey captures) or 3 (RGB)."""
        return self.format.channels

    def path(self, pattern: Pattern) -> Path:
        return self.files[pattern.stem]

    def _linear(self, path: Path, any_type: bool = False,
                raw: np.ndarray | None = None) -> np.ndarray:
        raw = _checked_channels(read_raw_image(path) if raw is None else raw, path,
                                self.manifest.channels)
        if raw.dtype.name != self.format.dtype and not any_type:
            raise AcquisitionError(
                f"pixel type {raw.dtype.name} differs from the other captures' "
                f"{self.format.dtype} (mixed bit depths: capture every pattern the same way)",
                path)
        image = check_image(raw, path)
        if image.shape[:2] != self.format.shape:
            raise AcquisitionError(
                f"capture of {image.shape[0]}x{image.shape[1]} pixels; the others are "
                f"{self.format.shape[0]}x{self.format.shape[1]}", path)
        top = self.format.full_scale
        if top is not None and not any_type:
            at_top = raw == top
            count = int(np.count_nonzero(at_top if at_top.ndim == 2 else at_top.any(axis=2)))
            if count:
                self.saturated[path.name] = count
        if self.gamma != 1.0:
            image = np.power(np.maximum(image, 0.0), self.gamma)
        return image

    def linear(self, pattern: Pattern) -> np.ndarray:
        """The capture of ``pattern``, linear, black level not subtracted.

        Returns
        -------
        ndarray, shape (Hc, Wc) or (Hc, Wc, 3) (colour), float64 (the black pattern's is
        kept: do not modify)
        """
        if pattern.kind == "black":
            return self._black_capture
        return self._linear(self.path(pattern))

    def linear_grey(self, pattern: Pattern) -> np.ndarray:
        """:meth:`linear` through the grey view (the mean of a colour capture's
        channels), shape (Hc, Wc): what the geometry (Gray code) reads."""
        return grey_view(self.linear(pattern))

    @property
    def black(self) -> np.ndarray:
        """The black level, shape (Hc, Wc) or (Hc, Wc, 3): ``--black`` or the black
        pattern's capture."""
        return self._black_level

    def signal(self, pattern: Pattern) -> np.ndarray:
        """The capture of ``pattern`` less the black level. Negative values (noise) are
        kept: clipping them before the group means would bias every dark entry of T up.

        Returns
        -------
        ndarray, shape (Hc, Wc) or (Hc, Wc, 3) (colour), float64
        """
        return self.linear(pattern) - self.black

    def signal_grey(self, pattern: Pattern) -> np.ndarray:
        """:meth:`signal` through the grey view, shape (Hc, Wc)."""
        return grey_view(self.signal(pattern))

    def pixel_noise(self, channel: int | None = None) -> float:
        """Robust standard deviation of one pixel's noise, from the black pattern's
        capture (a separate black frame may be an average, so it is not used): 1.4826 x
        the median absolute deviation of the differences of horizontal neighbours, over
        sqrt 2. Differences, because a smooth black level (a ramp, vignetting of stray
        light) is no noise but spreads the values themselves; a difference of two pixels
        holds two pixels' noise, hence sqrt 2. 0 for a noiseless camera. A signal holds
        the noise twice, the black level it is measured against being noisy too.

        ``channel`` (0, 1, 2) of colour captures, or their grey view when None (each a
        measurement of its own: the channels' noises need not be alike nor independent).
        """
        if channel not in self._noise:
            b = self._black_capture
            b = grey_view(b) if channel is None else b[:, :, channel]
            d = np.diff(b, axis=1 if b.shape[1] > 1 else 0)
            self._noise[channel] = (
                float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))
                if d.size else 0.0)
        return self._noise[channel]

    @property
    def quantum(self) -> float:
        """One step of the stored values (1/255, 1/65535), 0 for float captures."""
        top = self.format.full_scale
        return 1.0 / top if top else 0.0

    def noise(self, channel: int | None = None) -> float:
        """A pixel's noise with the quantisation's: sqrt(sigma^2 + q^2 / 12), q one
        :attr:`quantum`. The median estimate of :meth:`pixel_noise` is 0 when the noise
        is under one step (an 8-bit black capture of few distinct values), yet every
        capture is still off by up to half a step: the rounding's variance is q^2/12
        (kept whole for the grey view of colour, whose mean of three roundings varies
        less: an upper bound). ``channel`` as for :meth:`pixel_noise`."""
        return float(np.sqrt(self.pixel_noise(channel) ** 2 + self.quantum ** 2 / 12.0))

    def channel_noise(self) -> np.ndarray:
        """:meth:`noise` of each channel, shape (channels,): the grey captures' one value,
        or R, G, B."""
        if self.channels == 1:
            return np.array([self.noise()])
        return np.array([self.noise(c) for c in range(self.channels)])

    def fingerprint(self) -> str:
        """Name, size and modification time of every capture file (and ``--black``),
        hashed: a resumed build must read the very captures the interrupted one read."""
        h = hashlib.sha256()
        files = sorted(self.files.values()) + ([Path(self.black_file)] if self.black_file
                                               else [])
        for path in files:
            st = path.stat()
            h.update(f"{path.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
        return h.hexdigest()[:32]

    def pixel_floor(self, summed: int = 1) -> float:
        """A pixel's signal (grey view) at or below this is noise: 3 standard deviations
        of a signal, and at least two steps of the stored values (a black frame averaged
        to a float level differs from the quantised captures by up to one step).

        ``summed``: the signal is the sum of that many captures' signals (the three
        primaries of a colour super-pixel), each less the same black level: k captures'
        noise and k times the black's, variance (k + k^2) sigma^2 (2 sigma^2 for one)."""
        k = int(summed)
        return max(3.0 * np.sqrt(k + k * k) * self.pixel_noise(), 2.0 * k * self.quantum)

    def saturation_warning(self) -> str | None:
        """One line naming the captures with pixels at full scale, or None."""
        if not self.saturated:
            return None
        names = sorted(self.saturated)
        shown = ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
        return (f"{sum(self.saturated.values())} saturated pixels in {len(names)} captures "
                f"({shown}): T is underestimated there; lower the exposure and capture again")


def _match_files(manifest: Manifest, folder: Path) -> dict[str, Path]:
    """Pattern stem -> capture file; every pattern once, no image file without one."""
    stems = {p.stem for p in manifest.patterns}
    found: dict[str, Path] = {}
    extra = []
    for path in sorted(folder.iterdir()):
        if not (path.is_file() and is_image_file(path)):
            continue
        if path.stem not in stems:
            extra.append(path.name)
        elif path.stem in found:
            raise AcquisitionError(f"two captures of pattern {path.stem}: "
                                   f"{found[path.stem].name} and {path.name}", folder)
        else:
            found[path.stem] = path
    missing = [p.file for p in manifest.patterns if p.stem not in found]
    if missing:
        raise AcquisitionError(
            f"{len(missing)} of {len(manifest.patterns)} captures missing ({_some(missing)}); "
            f"each pattern needs a capture of the same name ({'/'.join(IMAGE_SUFFIXES)})", folder)
    if extra:
        raise AcquisitionError(
            f"{len(extra)} image files match no pattern of the manifest ({_some(extra)}); "
            "are these the captures of another pattern set?", folder)
    return found


def grey_view(image: np.ndarray) -> np.ndarray:
    """An (H, W) image as it is, an (H, W, 3) one as the mean of its channels."""
    return image if image.ndim == 2 else image.mean(axis=2)


def _checked_channels(raw: np.ndarray, path: Path, channels: int) -> np.ndarray:
    """``raw`` ((H, W, 1) as (H, W)) when it has the pattern set's ``channels``; a
    capture of the other kind refused as such (before its pixel type is compared: an
    8-bit RGB capture among 16-bit grey ones is colour, not a bit depth)."""
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[:, :, 0]
    found = 1 if raw.ndim == 2 else raw.shape[2]
    if found == channels:
        return raw
    if found not in (1, 3):
        raise AcquisitionError(f"a capture of {found} channels: bigT reads grey (1 channel) "
                               "or RGB (3 channels) captures", path)
    if channels == 1:
        raise AcquisitionError(
            f"a colour capture ({found} channels) of a grey pattern set: capture every "
            "pattern in grayscale (one channel), or write the patterns with --channels 3", path)
    raise AcquisitionError(
        "a grey capture of a colour pattern set (channels 3): capture every pattern in "
        "RGB", path)


def _some(names: list[str], k: int = 3) -> str:
    return ", ".join(names[:k]) + (f", ... ({len(names) - k} more)" if len(names) > k else "")


__all__ = ["Captures", "CaptureFormat", "grey_view"]
