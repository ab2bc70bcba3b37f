"""A captures folder read against its pattern manifest: :class:`Captures`.

One camera image per pattern, named as the pattern (any of the image suffixes of
:mod:`bigT.images`, or a RAW camera file), or an exposure bracket per pattern
(``white@0.01.png``, :mod:`.brackets`); values are made linear through the camera's
response (:class:`bigT.calibration.CameraResponse`: linear, sRGB, a gamma, a table, or
one recovered from the brackets of the white and ramp patterns; RAW files are linear
already), a bracket merged into linear radiance (:func:`bigT.calibration.merge_bracket`),
and the black capture is subtracted. Every capture (bracket) is read when it is needed
and dropped after, so the captures are never all in memory.

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

from ..calibration import CameraResponse, merge_bracket, parse_camera_response
from ..errors import AcquisitionError, CalibrationError
from ..images import IMAGE_SUFFIXES, check_image, is_image_file, read_raw_image
from .brackets import (RAW_SUFFIXES, Bracket, Shot, bracket, check_same_exposures,
                       split_name)
from .manifest import Manifest, Pattern

#: ``--camera-response`` spellings that recover the response from the brackets.
RECOVER = "recover"
#: Side of the square of ranked pixels a response recovery fits (:func:`recovery_samples`;
#: Robertson uses them all: a subsample keeps it quick).
RECOVERY_SIDE = 64


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
    gamma : float, the camera's encoding gamma (1: linear captures); the same as
        ``camera_response="gamma:G"``, kept for ``--gamma``
    black_file : path, optional
        A black-level image to subtract instead of the capture of the ``black`` pattern
        (on the captures' scale: values in 0-1 for floats; single exposures only).
    camera_response : CameraResponse or str, optional
        The camera's response: a :class:`CameraResponse`, a ``--camera-response``
        spelling (``linear``, ``srgb``, ``gamma:G``, a ``.npy``/``.json`` table) or
        ``recover`` / ``recover:robertson`` (recovered from the brackets of the white and
        ramp patterns, Debevec by default). Default: ``gamma``'s (linear).

    Raises
    ------
    AcquisitionError
        A capture missing or one without a pattern (naming the first few), two files
        for one pattern; captures of different sizes or bit depths, a colour capture of
        a grey pattern set or the reverse, a black frame in raw counts (naming the file);
        a bracket's exposure time missing, disagreeing with its EXIF, missing for one
        pattern or out of order; a response that cannot be recovered.
    """

    manifest: Manifest
    folder: Path
    gamma: float = 1.0
    black_file: Path | None = None
    camera_response: CameraResponse | str | None = None
    files: dict[str, Path] = field(init=False)
    brackets: dict[str, Bracket] = field(init=False)
    exposures: tuple[float, ...] | None = field(init=False)
    response: CameraResponse = field(init=False)
    format: CaptureFormat = field(init=False)
    saturated: dict[str, int] = field(init=False, default_factory=dict)

    def __post_init__(self):
        self.folder = Path(self.folder)
        if not self.folder.is_dir():
            raise AcquisitionError("no such captures folder", self.folder)
        self.brackets, self.exposures = _match_files(self.manifest, self.folder)
        self.files = {stem: b.paths[0] for stem, b in self.brackets.items()}
        if self.black_file and self.bracketed:
            raise AcquisitionError(
                "{option} is for single-exposure captures; with exposure brackets the black "
                "pattern's bracket is the black level", self.black_file, option="black")
        self._noise: dict[int | None, float] = {}  # channel (None: grey view) -> sigma
        self.response = self._response()
        raw_black = self._reference_format()
        # the black pattern's capture is needed by the noise estimate, every signal
        # (without --black) and the Gray-code decoding: read once, kept
        black_pattern = self.manifest.single("black")
        self._black_capture = (self._merged(black_pattern) if self.bracketed else
                               self._linear(self.path(black_pattern), raw=raw_black))
        self._black_level = self._black_capture
        if self.black_file:
            # a black frame may be an average of many, so of any pixel type
            raw = self._stored(self.black_file)
            self._black_level = self._linear(self.black_file, any_type=True, raw=raw)
            self._check_black_scale(raw.dtype)

    def _reference_format(self) -> np.ndarray:
        """Set :attr:`format`: the black capture's size and pixel type, unless the white
        capture and a third agree on another (then the black capture is the odd one, and
        is named when converted). Returns the black capture as stored."""
        def format_of(pattern):
            path = self.path(pattern)
            raw = self._stored(path)
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

    @property
    def bracketed(self) -> bool:
        """Exposure brackets (``white@0.01.png``), not one capture per pattern."""
        return self.exposures is not None

    def _stored(self, path: Path) -> np.ndarray:
        """A capture file's pixels as stored, with the pattern set's channels: a RAW file
        demosaiced to linear RGB (its channels' mean for a grey pattern set)."""
        if path.suffix.lower() in RAW_SUFFIXES:
            from ..calibration import read_raw  # rawpy: optional, only for RAW files

            raw = read_raw(path)
            if self.manifest.channels == 1:
                raw = raw.mean(axis=2)
        else:
            raw = read_raw_image(path)
        return _checked_channels(raw, path, self.manifest.channels)

    def _response(self) -> CameraResponse:
        """The camera response: ``camera_response`` (parsed, or recovered from the
        brackets), else ``gamma``'s."""
        spec = self.camera_response
        if isinstance(spec, CameraResponse):
            return spec
        if spec is not None and str(spec).strip().lower().startswith(RECOVER):
            return self._recover(str(spec).strip().lower())
        try:
            if spec is not None:
                if self.gamma != 1.0:
                    raise CalibrationError("give the camera's response once: a gamma G "
                                           "is {option}",
                                           option=("camera_response", "gamma:G"))
                return parse_camera_response(spec)
            return (CameraResponse() if self.gamma == 1.0 else
                    CameraResponse("gamma", gamma=float(self.gamma)))
        except CalibrationError as exc:
            raise AcquisitionError(exc.template, exc.path,
                                   option=exc.option or "camera_response") from None

    def _recover(self, spec: str) -> CameraResponse:
        """The response recovered (OpenCV) from the brackets of the white and ramp
        patterns (:func:`recovery_samples`)."""
        from ..calibration import recover_camera_response

        method = spec.partition(":")[2] or "debevec"
        if not self.bracketed:
            raise AcquisitionError(
                "{option} recover needs exposure brackets (pattern@seconds.png); these "
                "captures have one exposure each", self.folder, option="camera_response")
        patterns = [self.manifest.single("white")] + self.manifest.ramp()
        stacks = [np.stack([self._stored(path) for path in self.brackets[p.stem].paths])
                  for p in patterns]
        frames = recovery_samples(stacks)
        try:
            return recover_camera_response(list(frames), self.exposures, method,
                                           pattern="white")
        except CalibrationError as exc:
            raise AcquisitionError(f"cannot recover the camera response: {exc.template}",
                                   self.folder, option="camera_response") from None

    def _linear(self, path: Path, any_type: bool = False,
                raw: np.ndarray | None = None) -> np.ndarray:
        raw = self._stored(path) if raw is None else raw
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
        if path.suffix.lower() in RAW_SUFFIXES or self.response.kind == "linear":
            return image  # RAW files are linear already
        return self.response.to_linear(image)

    def _merged(self, pattern: Pattern) -> np.ndarray:
        """A pattern's bracket merged into linear radiance (per second)."""
        b = self.brackets[pattern.stem]
        raws = []
        for path in b.paths:
            raw = self._stored(path)
            check_image(raw, path)  # NaN and Inf refused, naming the file
            if raw.dtype.name != self.format.dtype or raw.shape[:2] != self.format.shape:
                raise AcquisitionError(
                    f"capture of {raw.shape[0]}x{raw.shape[1]} {raw.dtype.name} pixels; the "
                    f"others are {self.format.shape[0]}x{self.format.shape[1]} "
                    f"{self.format.dtype}", path)
            raws.append(raw)
        # RAW files are linear already
        response = CameraResponse() if b.shots[0].raw else self.response
        try:
            return merge_bracket(raws, b.times, response, pattern=pattern.stem)
        except CalibrationError as exc:
            raise AcquisitionError(exc.template, self.folder) from None

    def linear(self, pattern: Pattern) -> np.ndarray:
        """The capture of ``pattern``, linear, black level not subtracted.

        Returns
        -------
        ndarray, shape (Hc, Wc) or (Hc, Wc, 3) (colour), float64 (the black pattern's is
        kept: do not modify)
        """
        if pattern.kind == "black":
            return self._black_capture
        return self._merged(pattern) if self.bracketed else self._linear(self.path(pattern))

    def saturated_mask(self, pattern: Pattern) -> np.ndarray:
        """Pixels of ``pattern``'s capture at full scale in any channel, shape (Hc, Wc),
        bool; none for float captures and brackets (whose merge leaves saturated
        samples out)."""
        top = self.format.full_scale
        if top is None or self.bracketed:
            return np.zeros(self.shape, dtype=bool)
        at_top = self._stored(self.path(pattern)) == top
        return at_top if at_top.ndim == 2 else at_top.any(axis=2)

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
        """One step of the stored values (1/255, 1/65535), 0 for float captures. Of
        brackets, in merged units: the step of the camera response's linear value at
        mid-scale over the longest exposure (where the faint light is read)."""
        top = self.format.full_scale
        if not top:
            return 0.0
        if not self.bracketed:
            return 1.0 / top
        mid = np.array([0.5 - 0.5 / top, 0.5 + 0.5 / top])
        if self.response.n_channels > 1:
            mid = np.repeat(mid[:, None], self.response.n_channels, axis=1)
        step = np.diff(self.response.to_linear(mid), axis=0).max()
        return float(step) / self.exposures[-1]

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
        files = sorted(p for b in self.brackets.values() for p in b.paths) + (
            [Path(self.black_file)] if self.black_file else [])
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


def recovery_samples(stacks: list[np.ndarray], side: int = RECOVERY_SIDE) -> np.ndarray:
    """The pixels a response recovery fits, as a small bracket of its own.

    OpenCV's Debevec fit samples 70 pixels on a grid of the image it is given: given
    the captures themselves, most samples land where nothing is lit (code 0 in every
    exposure) or where everything saturates, and the curve comes out wrong. Here the
    pixels of the white and ramp brackets that are neither black in the longest
    exposure nor saturated in the shortest are ranked by their light (the sum of their
    codes over the bracket) and ``side`` x ``side`` of them taken evenly through the
    ranks, darkest first: every sample informs the fit, and the samples span every
    radiance the ramp holds.

    Parameters
    ----------
    stacks : list of ndarray, each (K, H, W) or (K, H, W, 3): a pattern's K exposures

    Returns
    -------
    ndarray, shape (K, side, side) or (K, side, side, 3), the captures' type
    """
    K = stacks[0].shape[0]
    pixels = np.concatenate([s.reshape(K, -1, *s.shape[3:]) for s in stacks], axis=1)
    top = np.iinfo(pixels.dtype).max if pixels.dtype.kind in "ui" else 1.0
    grey = pixels.reshape(K, pixels.shape[1], -1).astype(np.float64).mean(axis=2)
    informative = (grey[-1] > 0) & (grey[0] < top)
    if informative.any():
        pixels, grey = pixels[:, informative], grey[:, informative]
    ranked = np.argsort(grey.sum(axis=0), kind="stable")
    chosen = ranked[np.linspace(0, len(ranked) - 1, side * side).round().astype(int)]
    return pixels[:, chosen].reshape(K, side, side, *pixels.shape[2:])


def _match_files(manifest: Manifest, folder: Path
                 ) -> tuple[dict[str, Bracket], tuple[float, ...] | None]:
    """Pattern stem -> its bracket (one capture, no time, in the single-exposure
    layout), and the bracket's exposure times (None: single exposures). Every pattern
    captured, no image file without a pattern, one layout for the whole folder."""
    stems = {p.stem for p in manifest.patterns}
    found: dict[str, list[tuple[Path, str | None]]] = {}
    extra = []
    for path in sorted(folder.iterdir()):
        if not (path.is_file() and (is_image_file(path)
                                    or path.suffix.lower() in RAW_SUFFIXES)):
            continue
        stem, label = split_name(path)
        if stem not in stems:
            extra.append(path.name)
        else:
            found.setdefault(stem, []).append((path, label))
    missing = [p.file for p in manifest.patterns if p.stem not in found]
    if missing:
        raise AcquisitionError(
            f"{len(missing)} of {len(manifest.patterns)} captures missing ({_some(missing)}); "
            f"each pattern needs a capture of the same name ({'/'.join(IMAGE_SUFFIXES)}, or "
            "pattern@seconds for exposure brackets)", folder)
    if extra:
        raise AcquisitionError(
            f"{len(extra)} image files match no pattern of the manifest ({_some(extra)}); "
            "are these the captures of another pattern set?", folder)
    labelled = [f for files in found.values() for f in files if f[1] is not None]
    if not labelled:
        for stem, files in found.items():
            if len(files) > 1:
                raise AcquisitionError(f"two captures of pattern {stem}: {files[0][0].name} "
                                       f"and {files[1][0].name}", folder)
        return {stem: Bracket(stem, (Shot(files[0][0], 1.0),))
                for stem, files in found.items()}, None
    for stem, files in found.items():
        single = [path for path, label in files if label is None]
        if single:
            raise AcquisitionError(
                f"bracket of pattern {stem!r}: {single[0].name} has no exposure time while "
                f"other captures are brackets (name it {stem}@<seconds>{single[0].suffix}, "
                f"like {labelled[0][0].name})", folder)
    brackets = {stem: bracket(stem, files, folder) for stem, files in found.items()}
    return brackets, check_same_exposures(brackets, folder)


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
            "pattern in grayscale (one channel), or write the patterns with {option}", path,
            option=("channels", 3))
    raise AcquisitionError(
        "a grey capture of a colour pattern set (channels 3): capture every pattern in "
        "RGB", path)


def _some(names: list[str], k: int = 3) -> str:
    return ", ".join(names[:k]) + (f", ... ({len(names) - k} more)" if len(names) > k else "")


__all__ = ["Captures", "CaptureFormat", "grey_view"]
