"""Compensation with its outcome simulated: what the camera would see, and how far it is
from the desired images (paper §6.1.3, Fig. 10).

:func:`simulate` compensates desired images (l_in = clip(X l_desired), eqs. 44-45) and
relights both the projector inputs and the desired images themselves through the
transport T, so it reports the error of the compensated view against the uncompensated
one, the flatness of constant targets (the paper's (max - min) / mean), and the share of
projector pixels clipped: the numbers ``bigT compensate --simulate`` prints, as a
:class:`SimulationReport`. :func:`simulate_batches` is the same for frames that come
batch by batch (a folder of images too large to hold), handing each batch's outputs to a
callback.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np

from .. import config
from ..errors import ImageError
from ..figures import scan_lines, side_by_side
from ..schedule.stream import (cache_budget, compute_dtype, forget_tiles, scheduler_runner,
                               stream_matmul)
from ..storage import as_store
from ..storage.frames import as_frames, pixel_order_of, to_frames, to_vectors
from .core import (
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
    """One frame through the simulation, each an (H, W) float64 image.

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
        Projector pixels below ``lo``, above ``hi``, and all of them.
    error, error_uncompensated : float
        ||T l_in - l_desired|| / ||l_desired|| and ||T l_desired - l_desired|| /
        ||l_desired||, Frobenius over all frames.
    flatness : Flatness or None
        None when no desired frame is constant.
    first : SimulatedFrame
        The first frame, for figures.
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
        if self.clip is not None:
            lines.append(clipped_summary(self.clipped_low, self.clipped_high, self.pixels,
                                         self.clip))
        return "\n".join(lines)


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


def clipped_summary(low: int, high: int, pixels: int, clip) -> str:
    """``clipped projector pixels: 1.20 % (below 0: ..., above 1: ...)``."""
    share = (lambda count: 100 * count / max(pixels, 1))
    return (f"clipped projector pixels: {share(low + high):.2f} % "
            f"(below {clip[0]}: {share(low):.2f} %, above {clip[1]}: {share(high):.2f} %)")


class _Sums:
    """The running sums behind the report's errors and flatness."""

    def __init__(self):
        self.err = self.err0 = self.ref = 0.0
        self.flat: list[tuple[float, float, float, float]] = []
        self.first: SimulatedFrame | None = None

    def add(self, names, desired, uncompensated, projector, seen) -> None:
        self.err += float(np.sum((seen - desired) ** 2))
        self.err0 += float(np.sum((uncompensated - desired) ** 2))
        self.ref += float(np.sum(desired ** 2))
        for d, a, b in zip(desired, uncompensated, seen):
            if np.ptp(d) == 0 and d.flat[0] > 0:
                self.flat.append((fluctuation(a), fluctuation(b), fluctuation(scan_line(a)),
                                  fluctuation(scan_line(b))))
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
                     on_batch: Callable | None = None) -> SimulationReport:
    """:func:`simulate` for frames that come one batch at a time.

    Parameters
    ----------
    batches : iterable of (names, frames)
        ``frames`` of shape (K, H, W) float64; ``names`` (K file names, or None) are
        handed on to ``on_batch``. Each batch costs one pass over X (or ``terms`` over
        T on the matrix-free path) and one over T for the simulation.
    X, T, clip, path, matrix_free, terms, cache_bytes, scheduler, progress
        As :func:`simulate`.
    on_batch : callable, optional
        ``on_batch(names, projector, seen)`` after each batch, both (K, H, W): where a
        caller writes them.

    Returns
    -------
    SimulationReport
    """
    X = None if X is None else as_store(X, "X")
    T = as_store(T, "T")
    T_series = T if matrix_free is None else as_store(matrix_free, "T")
    choice = choose_path(X, T_series if path != "explicit" else None, terms, path)
    counts = CompensationReport(choice)
    sums = _Sums()
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
                seen, uncompensated = _relight_both(T, projector, frames, cache, runner,
                                                    progress)
                sums.add(names, frames, uncompensated, projector, seen)
                if on_batch is not None:
                    on_batch(names, projector, seen)
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
        first=sums.first)


def _relight_both(T, projector, desired, cache, runner, progress):
    """(T l_in, T l_desired), both (K, H, W), in one pass over T."""
    order = pixel_order_of(T, desired.shape[1:])
    both = np.concatenate([projector, desired])
    seen_all = to_frames(stream_matmul(T, to_vectors(both, order, compute_dtype(T)),
                                       progress=progress, desc="T pass", cache_bytes=cache,
                                       runner=runner), order)
    return seen_all[:len(desired)], seen_all[len(desired):]


def simulate(X, images, T, *, clip=(0, 1), batch: int = config.DEFAULT_BATCH,
             path: str = "explicit", matrix_free=None, terms: int | None = None,
             cache_bytes: int | None = None, scheduler=None,
             progress: bool = False) -> Simulation:
    """Compensate ``images`` and simulate what the camera sees, with or without.

    A function beside :func:`~bigT.compensation.compensate` rather than a flag of it:
    ``compensate`` returns the projector input; this returns a result object (as
    ``scipy.optimize.minimize`` does) holding the inputs, the simulated views and the
    numbers that judge them.

    Parameters
    ----------
    X : BlockCSR or path, shape (n, n), or None
        The (stratified) inverse; None for ``path="matrix-free"``.
    images : ndarray, shape (H, W) or (K, H, W)
        Desired camera images.
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
                              progress=progress, on_batch=keep)
    if single:
        return Simulation(projector[0], seen[0], report)
    return Simulation(projector, seen, report)


def simulation_figures(report: SimulationReport, compare_path, scanline_path, *,
                       tag: str = ""):
    """The first frame's figures: desired | seen without | projector input | seen with
    compensation side by side, and their centre scan lines (the paper's Fig. 10).

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
        compare_path, [f.desired, f.uncompensated, f.projector, f.seen],
        ["desired", "seen without compensation", "projector input", "seen with compensation"],
        suptitle=f"compensation, {report.path.path} path{tag}; error "
        f"{relative_error(f.seen, f.desired):.3f} vs "
        f"{relative_error(f.uncompensated, f.desired):.3f}")
    lines = {"without compensation": scan_line(f.uncompensated),
             "with compensation": scan_line(f.seen), "projector input": scan_line(f.projector)}
    constant = float(f.desired.flat[0]) if np.ptp(f.desired) == 0 else None
    if constant is None:
        lines["desired"] = scan_line(f.desired)
    scan = scan_lines(scanline_path, lines,
                      title=f"centre scan line (row {f.desired.shape[0] // 2}){tag}",
                      target=constant)
    return compare, scan
