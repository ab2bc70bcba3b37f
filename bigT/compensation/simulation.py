"""Compensation with its outcome simulated: what the camera would see, and how far it is
from the desired images (paper §6.1.3, Fig. 10).

:func:`simulate` compensates desired images (l_in = clip(X l_desired), eqs. 44-45) and
relights both the projector inputs and the desired images themselves through the
transport T, so it reports the error of the compensated view against the uncompensated
one, the flatness of constant targets (the paper's (max - min) / mean), the share of
projector values clipped (per channel for colour), and PSNR, SSIM and CIEDE2000 ΔE
(:mod:`bigT.metrics`, scikit-image): the numbers ``bigT compensate --simulate`` prints, as
a :class:`SimulationReport`. :func:`simulate_batches` is the same for frames that come
batch by batch (a folder of images too large to hold), handing each batch's outputs to a
callback.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np

from .. import config
from .. import colour
from ..errors import ImageError
from ..figures import number, scan_lines, side_by_side
from ..metrics import ColourMetrics, image_metrics
from ..schedule.stream import (cache_budget, compute_dtype, forget_tiles, scheduler_runner,
                               stream_matmul)
from ..storage import as_store
from ..storage.frames import as_frames, pixel_order_of, to_frames, to_vectors
from .core import (
    CHANNEL_NAMES,
    ClippedFrames,
    CompensationReport,
    PathChoice,
    choose_path,
    compensate_frames,
    fluctuation,
    relative_error,
    scan_line,
)

__all__ = ["simulate", "simulate_batches", "simulation_figures", "Simulation",
           "SimulationReport", "Flatness", "SimulatedFrame"]


@dataclass(frozen=True)
class Flatness:
    """The paper's flatness measure (max - min) / mean of constant targets (§6.1.3),
    averaged over the constant frames, without and with compensation.

    Attributes
    ----------
    frames : int
        Frames whose desired image is one positive value.
    image_uncompensated, image_compensated : float
        Over the whole seen image, T l_desired and T l_in.
    line_uncompensated, line_compensated : float
        Over its centre scan line (row H // 2, the paper's Fig. 10).
    """

    frames: int
    image_uncompensated: float
    image_compensated: float
    line_uncompensated: float
    line_compensated: float


@dataclass(frozen=True)
class SimulatedFrame:
    """One frame through the simulation, each an (H, W) float64 image ((H, W, 3) for
    colour), in linear light.

    Attributes
    ----------
    name : str or None
        The frame's file name when it came from a folder.
    desired : l_desired
    uncompensated : T l_desired, what the camera sees without compensation
    projector : l_in = clip(X l_desired), the projector input
    seen : T l_in, what the camera sees with compensation
    """

    name: str | None
    desired: np.ndarray
    uncompensated: np.ndarray
    projector: np.ndarray
    seen: np.ndarray


@dataclass(frozen=True)
class SimulationReport(ClippedFrames):
    """What :func:`simulate` found.

    Attributes
    ----------
    path : PathChoice
        The compensation path taken and why.
    frames : int
    seconds : float
        Wall time of the compensation products (the T passes of the simulation not
        included).
    clip : (lo, hi) or None
        The projector range the inputs were clipped to.
    clipped_low, clipped_high, pixels : int
        Projector values below ``lo``, above ``hi``, and all of them (H W a grey frame,
        3 H W a colour one).
    error, error_uncompensated : float
        ||T l_in - l_desired|| / ||l_desired|| and ||T l_desired - l_desired|| /
        ||l_desired||, Frobenius over all frames, in linear light.
    flatness : Flatness or None
        None when no desired frame is constant.
    first : SimulatedFrame
        The first frame, for figures.
    clipped_low_by_channel, clipped_high_by_channel : tuple of int
        The clipped values per channel (R, G, B; one entry for grey).
    metrics, metrics_uncompensated : ColourMetrics or None
        PSNR, SSIM, CIEDE2000 ΔE mean / p95 (and the relative error) of T l_in and of
        T l_desired against l_desired (:func:`frame_metrics`), None when not asked for.
    encoding : str
        The encoding the metrics saw the images in (the input files'; PSNR and SSIM
        depend on it, ΔE does not).
    """

    path: PathChoice
    frames: int
    seconds: float
    clip: tuple | None
    clipped_low: int
    clipped_high: int
    pixels: int
    error: float
    error_uncompensated: float
    flatness: Flatness | None
    first: SimulatedFrame
    clipped_low_by_channel: tuple = ()
    clipped_high_by_channel: tuple = ()
    metrics: ColourMetrics | None = None
    metrics_uncompensated: ColourMetrics | None = None
    encoding: str = "linear"

    def describe(self) -> str:
        """The error, flatness and clipping, one fact a line (what the CLI prints)."""
        lines = [f"relative error ||T l_in - l_desired|| / ||l_desired||: {self.error:.4f} "
                 f"compensated, {self.error_uncompensated:.4f} uncompensated (T l_desired)"]
        f = self.flatness
        if f is None:
            lines.append("fluctuation: n/a (no constant target frame)")
        else:
            lines.append(f"constant target ({f.frames} frame(s)), fluctuation (max-min)/mean: "
                         f"image {f.image_uncompensated:.3f} -> {f.image_compensated:.3f}, "
                         f"centre scan line {f.line_uncompensated:.3f} -> "
                         f"{f.line_compensated:.3f} (uncompensated -> compensated)")
        if self.metrics is not None:
            lines.append(f"seen, against the desired images ({self.encoding} values; ΔE in "
                         "CIELAB, mean over frames):")
            lines.append(f"  uncompensated: {self.metrics_uncompensated.describe()}")
            lines.append(f"  compensated:   {self.metrics.describe()}")
        if self.clip is not None:
            lines.append(clipped_summary(self.clipped_low, self.clipped_high, self.pixels,
                                         self.clip, self.clipped_shares_by_channel))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The numbers as JSON-ready values (``compensate --simulate --json``)."""
        flat = self.flatness
        return {
            "path": self.path.path, "path_reason": self.path.reason, "frames": self.frames,
            "seconds": self.seconds, "clip": None if self.clip is None else list(self.clip),
            "error": self.error, "error_uncompensated": self.error_uncompensated,
            "flatness": None if flat is None else flat.__dict__.copy(),
            **clipped_dict(self),
            "encoding": self.encoding,
            "metrics": _metrics_dict(self.metrics),
            "metrics_uncompensated": _metrics_dict(self.metrics_uncompensated)}


@dataclass(frozen=True)
class Simulation:
    """:func:`simulate`'s result: the images and the report.

    Attributes
    ----------
    projector : ndarray, the shape of the desired images: l_in
    seen : ndarray, the same shape: T l_in
    report : SimulationReport
    """

    projector: np.ndarray
    seen: np.ndarray
    report: SimulationReport


def clipped_summary(low: int, high: int, pixels: int, clip, by_channel=()) -> str:
    """``clipped projector pixels: 1.20 % (below 0: ..., above 1: ...)``; for colour
    (three ``by_channel`` pairs of shares below / above) ``clipped projector values``,
    then each channel's shares."""
    share = (lambda count: 100 * count / max(pixels, 1))
    what = "values" if len(by_channel) > 1 else "pixels"
    text = (f"clipped projector {what}: {share(low + high):.2f} % "
            f"(below {clip[0]}: {share(low):.2f} %, above {clip[1]}: {share(high):.2f} %)")
    if len(by_channel) > 1:
        text += "; per channel below / above: " + ", ".join(
            f"{name} {100 * lo:.2f} / {100 * hi:.2f} %"
            for name, (lo, hi) in zip(CHANNEL_NAMES, by_channel))
    return text


def clipped_dict(report) -> dict:
    """The clipping counts and shares of a report (a :class:`ClippedFrames`), per channel
    too, as JSON-ready values."""
    names = CHANNEL_NAMES if len(report.clipped_low_by_channel) == 3 else ("grey",)
    return {"clipped_low": report.clipped_low, "clipped_high": report.clipped_high,
            "values": report.pixels, "clipped_fraction": report.clipped_fraction,
            "clipped_by_channel": {
                name: {"below": low, "above": high, "share_below": s_lo, "share_above": s_hi}
                for name, low, high, (s_lo, s_hi) in zip(
                    names, report.clipped_low_by_channel, report.clipped_high_by_channel,
                    report.clipped_shares_by_channel)}}


def _metrics_dict(metrics: ColourMetrics | None) -> dict | None:
    # inf (PSNR of identical images) is not JSON: null
    if metrics is None:
        return None
    return {k: (v if v is None or np.isfinite(v) else None) for k, v in metrics.__dict__.items()}


def frame_metrics(seen: np.ndarray, desired: np.ndarray, encoding: str = "linear"
                  ) -> list[ColourMetrics]:
    """:func:`bigT.metrics.image_metrics` of each frame.

    Parameters
    ----------
    seen, desired : ndarray, shape (K, H, W) or (K, H, W, 3), linear light
    encoding : one of :data:`bigT.colour.ENCODINGS`
        The encoding the images are compared in: the input files' (PSNR and SSIM are
        of the values a user's files hold; ΔE is of the colours, whatever the encoding).

    Returns
    -------
    list of ColourMetrics, one per frame
    """
    seen_values = colour.encode(seen, encoding)
    desired_values = colour.encode(desired, encoding)
    return [image_metrics(s, d, encoding_for_lab=encoding)
            for s, d in zip(seen_values, desired_values)]


def mean_metrics(per_frame: Sequence[ColourMetrics]) -> ColourMetrics:
    """The frames' metrics averaged field by field (the mean PSNR over frames, as video
    compensation is reported; the p95 of ΔE is the mean of the frames' p95)."""
    fields = ColourMetrics.__dataclass_fields__
    values = {}
    for name in fields:
        column = [getattr(m, name) for m in per_frame]
        values[name] = None if any(v is None for v in column) else float(np.mean(column))
    return ColourMetrics(**values)


class _Sums:
    """The running sums behind the report's errors, flatness and metrics (each frame's
    :class:`ColourMetrics` when ``encoding`` is given)."""

    def __init__(self, encoding: str | None):
        self.err = self.err0 = self.ref = 0.0
        self.flat: list[tuple[float, float, float, float]] = []
        self.first: SimulatedFrame | None = None
        self.encoding = encoding
        self.metrics: list[ColourMetrics] = []
        self.metrics0: list[ColourMetrics] = []

    def add(self, names, desired, uncompensated, projector, seen) -> None:
        self.err += float(np.sum((seen - desired) ** 2))
        self.err0 += float(np.sum((uncompensated - desired) ** 2))
        self.ref += float(np.sum(desired ** 2))
        for d, a, b in zip(desired, uncompensated, seen):
            if np.ptp(d) == 0 and d.flat[0] > 0:
                self.flat.append((fluctuation(a), fluctuation(b), fluctuation(scan_line(a)),
                                  fluctuation(scan_line(b))))
        if self.encoding is not None:
            self.metrics += frame_metrics(seen, desired, self.encoding)
            self.metrics0 += frame_metrics(uncompensated, desired, self.encoding)
        if self.first is None:
            name = None if names is None else str(getattr(names[0], "name", names[0]))
            self.first = SimulatedFrame(name, desired[0], uncompensated[0], projector[0],
                                        seen[0])

    def flatness(self) -> Flatness | None:
        if not self.flat:
            return None
        return Flatness(len(self.flat), *(float(v) for v in np.mean(self.flat, axis=0)))


def simulate_batches(batches: Iterable[tuple[Sequence | None, np.ndarray]], X, T, *,
                     clip=(0, 1), path: str = "explicit", matrix_free=None,
                     terms: int | None = None, cache_bytes: int | None = None,
                     scheduler=None, progress: bool = False,
                     on_batch: Callable | None = None,
                     metrics: str | None = "linear",
                     project: Callable | None = None) -> SimulationReport:
    """:func:`simulate` for frames that come one batch at a time.

    Parameters
    ----------
    batches : iterable of (names, frames)
        ``frames`` of shape (K, H, W) float64 ((K, H, W, 3) for a colour T), linear
        light; ``names`` (K file names, or None) are handed on to ``on_batch``. Each batch costs one pass over X (or ``terms`` over
        T on the matrix-free path) and one over T for the simulation.
    X, T, clip, path, matrix_free, terms, cache_bytes, scheduler, progress
        As :func:`simulate`.
    on_batch : callable, optional
        ``on_batch(names, projector, seen)`` after each batch, both the frames' shape:
        where a caller writes them.
    metrics : one of :data:`bigT.colour.ENCODINGS`, or None
        Report PSNR, SSIM and CIEDE2000 ΔE (:func:`frame_metrics`, averaged over the
        frames) of the images encoded so (the input files' encoding); None: skip them
        (scikit-image's ΔE takes ~0.1 s a 384x512 frame).
    project : callable, optional
        ``project(l_in) -> (written, sent)``: the projector's image as it is written and
        the light it sends, on T's images, which is what T relights
        (:meth:`bigT.compensation.projection.Projection.sent`: a projector's response,
        a rig's resolutions). Default: both are l_in, a linear projector. ``on_batch``
        gets ``written``; the report's first frame holds ``sent``.

    Returns
    -------
    SimulationReport
    """
    X = None if X is None else as_store(X, "X")
    T = as_store(T, "T")
    T_series = T if matrix_free is None else as_store(matrix_free, "T")
    choice = choose_path(X, T_series if path != "explicit" else None, terms, path)
    counts = CompensationReport(choice)
    sums = _Sums(None if metrics is None else colour.check_encoding(metrics))
    cache = cache_budget(cache_bytes)
    seconds = 0.0
    with scheduler_runner(scheduler) as runner:
        try:
            for names, frames in batches:
                t0 = time.perf_counter()
                projector = compensate_frames(frames, X=X, T=T_series, choice=choice,
                                              clip=clip, report=counts, progress=progress,
                                              cache_bytes=cache, runner=runner)
                seconds += time.perf_counter() - t0
                counts.frames += len(frames)
                written, sent = (projector, projector) if project is None else project(projector)
                seen, uncompensated = _relight_both(T, sent, frames, cache, runner, progress)
                sums.add(names, frames, uncompensated, sent, seen)
                if on_batch is not None:
                    on_batch(names, written, seen)
        finally:
            forget_tiles(runner, X, T, T_series)
    if sums.first is None:
        raise ImageError("no frames to simulate")
    ref = np.sqrt(sums.ref)
    return SimulationReport(
        path=choice, frames=counts.frames, seconds=seconds, clip=clip,
        clipped_low=counts.clipped_low, clipped_high=counts.clipped_high,
        pixels=counts.pixels, error=float(np.sqrt(sums.err) / ref),
        error_uncompensated=float(np.sqrt(sums.err0) / ref), flatness=sums.flatness(),
        first=sums.first, clipped_low_by_channel=counts.clipped_low_by_channel,
        clipped_high_by_channel=counts.clipped_high_by_channel,
        metrics=mean_metrics(sums.metrics) if sums.metrics else None,
        metrics_uncompensated=mean_metrics(sums.metrics0) if sums.metrics0 else None,
        encoding="linear" if metrics is None else metrics)


def _relight_both(T, projector, desired, cache, runner, progress):
    """(T l_in, T l_desired), both the frames' shape, in one pass over T."""
    order = pixel_order_of(T, desired.shape[1:])
    both = np.concatenate([projector, desired]).astype(desired.dtype, copy=False)
    seen_all = to_frames(stream_matmul(T, to_vectors(both, order, compute_dtype(T)),
                                       progress=progress, desc="T pass", cache_bytes=cache,
                                       runner=runner), order)
    return seen_all[:len(desired)], seen_all[len(desired):]


def simulate(X, images, T, *, clip=(0, 1), batch: int = config.DEFAULT_BATCH,
             path: str = "explicit", matrix_free=None, terms: int | None = None,
             cache_bytes: int | None = None, scheduler=None,
             progress: bool = False, metrics: str | None = "linear") -> Simulation:
    """Compensate ``images`` and simulate what the camera sees, with or without.

    A function beside :func:`~bigT.compensation.compensate` rather than a flag of it:
    ``compensate`` returns the projector input; this returns a result object (as
    ``scipy.optimize.minimize`` does) holding the inputs, the simulated views and the
    numbers that judge them.

    Parameters
    ----------
    X : BlockCSR or path, shape (n, n), or None
        The (stratified) inverse; None for ``path="matrix-free"``.
    images : ndarray, shape (H, W) or (K, H, W); (H, W, 3) or (K, H, W, 3) for a colour T
        Desired camera images, linear light.
    T : BlockCSR or path, shape (n, n)
        The transport the camera is simulated with (``T l``).
    clip : (lo, hi) or None
        Projector range (default (0, 1); None: no clipping).
    batch : int
        Frames per pass over the matrices.
    path : {"explicit", "matrix-free", "auto"}
        As :func:`~bigT.compensation.choose_path`: X, or the series applied with T.
    matrix_free : BlockCSR or path, optional
        The transport of the matrix-free path (default: ``T``).
    terms : int, optional
        Series terms of the matrix-free path (default: X's, else
        ``config.DEFAULT_COMPENSATION_TERMS``).
    cache_bytes : int, optional
        Decoded tiles kept between batches (default ``config.COMPENSATE_CACHE_BYTES``).
    scheduler : None, "local:N", an address or a distributed.Client
        Where the tile rows run; default local threads.
    progress : bool
        Progress bars over tile rows.
    metrics : one of :data:`bigT.colour.ENCODINGS`, or None
        The encoding PSNR, SSIM and ΔE see the images in (default "linear": the values
        given); None: no metrics.

    Returns
    -------
    Simulation
        ``projector`` (l_in) and ``seen`` (T l_in), the shape of ``images``, and the
        :class:`SimulationReport`.
    """
    T = as_store(T, "T")
    frames, single, _ = as_frames(images, T)
    projector, seen = np.empty_like(frames), np.empty_like(frames)
    step = max(1, int(batch))
    done = [0]

    def keep(names, l_in, view):
        projector[done[0]:done[0] + len(l_in)] = l_in
        seen[done[0]:done[0] + len(l_in)] = view
        done[0] += len(l_in)

    batches = ((None, frames[s:s + step]) for s in range(0, len(frames), step))
    report = simulate_batches(batches, X, T, clip=clip, path=path, matrix_free=matrix_free,
                              terms=terms, cache_bytes=cache_bytes, scheduler=scheduler,
                              progress=progress, on_batch=keep, metrics=metrics)
    if single:
        return Simulation(projector[0], seen[0], report)
    return Simulation(projector, seen, report)


#: Relative luminance of linear Rec. 709 / sRGB primaries (IEC 61966-2-1): the scan line
#: of a colour frame.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)


#: The compensation paths in a figure's words.
_PATH_WORDS = {"explicit": "with the stored inverse X", "matrix-free": "from T's terms (no X)"}


def _shown(image: np.ndarray) -> np.ndarray:
    """An image as the figures show it: grey as it is; colour sRGB-encoded and clipped
    to [0, 1] (what a screen shows of linear light)."""
    if image.ndim == 2:
        return image
    return np.clip(colour.encode(image, "srgb"), 0.0, 1.0)


def _line(image: np.ndarray) -> np.ndarray:
    """The centre scan line: of the image, or of its luminance for colour."""
    if image.ndim == 3:
        image = image @ np.asarray(LUMINANCE_WEIGHTS)
    return scan_line(image)


def simulation_figures(report: SimulationReport, compare_path, scanline_path, *,
                       tag: str = ""):
    """The first frame's figures: desired | seen without | projector input | seen with
    compensation side by side, and their centre scan lines (the paper's Fig. 10); a
    colour frame is shown sRGB-encoded and its scan line is of the luminance.

    Parameters
    ----------
    report : SimulationReport
    compare_path, scanline_path : str or os.PathLike
        The two PNGs to write.
    tag : str
        Appended to both titles (``" (frame 003.png)"``).

    Returns
    -------
    (Path, Path)
    """
    f = report.first
    compare = side_by_side(
        compare_path, [_shown(im) for im in (f.desired, f.uncompensated, f.projector, f.seen)],
        ["desired", "seen without compensation", "projector input", "seen with compensation"],
        suptitle=f"compensation {_PATH_WORDS.get(report.path.path, report.path.path)}{tag}; "
        f"relative error of what is seen: {number(relative_error(f.seen, f.desired))} with, "
        f"{number(relative_error(f.uncompensated, f.desired))} without")
    lines = {"without compensation": _line(f.uncompensated),
             "with compensation": _line(f.seen), "projector input": _line(f.projector)}
    desired_line = _line(f.desired)
    constant = float(desired_line[0]) if np.ptp(f.desired) == 0 else None
    if constant is None:
        lines["desired"] = desired_line
    what = "luminance, " if f.desired.ndim == 3 else ""
    scan = scan_lines(scanline_path, lines,
                      title=f"centre scan line ({what}row {f.desired.shape[0] // 2}){tag}",
                      target=constant)
    return compare, scan
