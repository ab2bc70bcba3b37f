"""Compensating files: an image, a folder of frames or a video in, the projector's
frames out, streamed through X (held in memory when it fits).

What ``bigT compensate X in.mp4 -o out.mp4`` does, as a library call, in two steps so
that a caller can say what is about to happen before the long part starts::

    with FileCompensation(X, "in.mp4", "out.mp4") as job:   # inputs checked, X loaded
        print(job.describe())
        report = job.run()
    print(report.describe())

Nothing is written before every input check has passed; a video output is written
whole or not at all (:class:`~bigT.compensation.video.VideoSink`).

Colour: a colour store (``channels == 3``) takes RGB images and colour video, a grey one
grey images; the other kind is refused in one line naming the file. The values read
are decoded to linear light before the products and the results encoded back the same
way (:mod:`bigT.compensation.encoding`, ``encoding=``: an 8-bit colour input is sRGB
unless told ``"linear"``; grey inputs are linear, as they always were).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .. import config
from ..atomic import refuse_overwriting_inputs
from ..errors import ImageError, Option
from ..images import (ImageSink, ImageSource, declared_shape, is_image_file, png_code_dtype,
                      read_image)
from ..schedule.stream import cache_budget, scheduler_runner
from ..storage import as_store
from .core import CompensationReport, choose_path, relight
from .encoding import FrameEncoding, source_encoding
from .pipeline import CodecPool, EncodedBehind, decoded_ahead, with_encoding_times
from .projection import Projection, image_sizes, projection_for
from .projector import ResponseClipping
from .realtime import (Compensator, Residency, StreamReport, image_batches, run_stream,
                       video_batches)
from .simulation import (SimulationReport, clipped_dict, clipped_summary, simulate_batches,
                         simulation_figures)
from .video import DEFAULT_FPS, VideoSink, VideoSource, is_video_file


@dataclass(frozen=True)
class FileCompensationReport:
    """What :meth:`FileCompensation.run` did.

    Attributes
    ----------
    output : Path, the video, image or folder written
    batch : int, frames per pass
    stream : StreamReport, frames, seconds and latency of the run
    residency : Residency, whether X was held in memory, and why
    compensation : CompensationReport, the path taken and the clipped values (per
        channel too)
    clip : (lo, hi) or None
    encoding : FrameEncoding, of the input, and so of the projector input written
        without a projector response
    projector : ResponseClipping or None
        With a projector response: the values it could not emit, per channel
    projector_bits : int or None, the projector's depth the values were written in
    """

    output: Path
    batch: int
    stream: StreamReport
    residency: Residency
    compensation: CompensationReport
    clip: tuple | None
    encoding: FrameEncoding = FrameEncoding("linear", "grey input")
    projector: ResponseClipping | None = None
    projector_bits: int | None = None

    def describe(self) -> str:
        s = self.stream
        lines = [f"{s.frames} frame(s) in {s.compute_seconds:.2f} s of products "
                 f"({s.frames / max(s.compute_seconds, 1e-9):.1f} frames/s, batch "
                 f"{self.batch}); {s.seconds:.2f} s in all",
                 s.summary(self.residency)]
        if self.clip is not None:
            c = self.compensation
            lines.append(clipped_summary(c.clipped_low, c.clipped_high, c.pixels, self.clip,
                                         c.clipped_shares_by_channel))
        lines += written_lines(self.output, self.encoding, self.projector, self.projector_bits)
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The report as JSON-ready values (``compensate --json``)."""
        s, c = self.stream, self.compensation
        return {"output": str(self.output), "frames": s.frames, "batch": self.batch,
                "seconds": s.seconds, "compute_seconds": s.compute_seconds,
                "frames_per_second": s.frames_per_second,
                "latency_ms": s.latency_ms(), "overlap": s.overlap,
                "path": c.choice.path, "path_reason": c.choice.reason,
                "resident": self.residency.resident, "precision": self.residency.precision,
                "residency_reason": self.residency.reason,
                "encoding": self.encoding.name, "encoding_reason": self.encoding.reason,
                "clip": None if self.clip is None else list(self.clip), **clipped_dict(c),
                **projector_dict(self.projector, self.projector_bits)}


def written_lines(output, encoding: FrameEncoding, projector: ResponseClipping | None,
                  bits: int | None) -> list[str]:
    """The closing lines: what was written, and what the projector clipped."""
    if projector is not None:
        return [projector.describe(),
                f"wrote the projector's values ({bits}-bit, through its response) -> {output}"]
    encoded = "" if encoding.linear else f" ({encoding.name}-encoded, as the input)"
    return [f"wrote projector input{encoded} -> {output} (linear light, no projector "
            "response)"]


def projector_dict(projector: ResponseClipping | None, bits: int | None) -> dict:
    """The projector encoding's part of a JSON report."""
    if projector is None:
        return {"projector_response": False}
    return {"projector_response": True, "projector_bits": bits,
            "projector_clipped": projector.to_dict()}


class FileCompensation:
    """One compensation of files, checked and set up on entry, run by :meth:`run`.

    Parameters
    ----------
    X : BlockCSR, path, or None
        The inverse (None with ``path="matrix-free"``).
    desired : path
        An image (.png, .tif, .npy), a folder of them, or a video.
    output : path
        An image or folder of the same kind, or a video (a video input always gives a
        video; a folder may give one).
    T : BlockCSR or path, optional
        The transport, for the matrix-free path.
    path : {"auto", "explicit", "matrix-free"}
    terms : int, optional, of the matrix-free path (default X's).
    clip : (lo, hi) or None
    batch : int, frames per pass over X.
    bits : int, optional, of the images or video written (default the input's, else 8).
    fps : float, optional, of a video made from a folder (default 30).
    encoding : {"auto", "srgb", "linear"}
        Of the input's values, and so of the projector input written
        (:func:`~bigT.compensation.encoding.source_encoding`; "auto": sRGB for an 8-bit
        colour input, else linear).
    resident : bool
        Hold X in memory when it fits ``memory_limit`` (never on a cluster).
    memory_limit : int, optional
        Bytes X may take in memory (default: a share of the available memory).
    precision : {"float32", "float16"}, of X held in memory.
    cache_bytes : int, optional
        Tile cache of a streamed X (default ``config.COMPENSATE_CACHE_BYTES``).
    scheduler : as :func:`bigT.schedule.runner.open_runner`, optional.
    projector_response : ``"auto"``, None, a path or a ProjectorResponse
        The projector's response the output is encoded through
        (:mod:`bigT.compensation.projector`); ``"auto"`` (default): the one stored
        with T (the matrix-free T, else the one X's record names), else none: linear
        light written in the input's encoding, as before. With one, ``clip`` (0, 1) is
        its range (light above black, 0 = black, 1 = full scale): what lies outside is
        clipped by the encoding and counted per channel in the report.
    projector_bits : 8 or 16, the projector's depth (default 8; only with a response).
        The values written are the codes over 2^bits - 1 (a PNG or video of that depth
        holds the codes themselves).
    dither : ``"none"``, ``"ordered"`` or ``"random"``, of the projector's codes
    seed : int, of ``"random"`` dither
    smooth : bool, bilinear super-pixels on the projector (a rig's T)

    The rig's resolutions (:mod:`bigT.compensation.rig`): when the T found holds the
    correspondence of ``bigT acquire build``, the desired images are the camera's
    (or the super-pixels' own) and the output is the projector's full image.
    """

    def __init__(self, X, desired, output, *, T=None, path: str = "auto",
                 terms: int | None = None, clip=(0, 1), batch: int = config.DEFAULT_BATCH,
                 bits: int | None = None, fps: float | None = None, resident: bool = True,
                 memory_limit: int | None = None, precision: str = "float32",
                 cache_bytes: int | None = None, scheduler=None, encoding: str = "auto",
                 projector_response="auto", projector_bits: int | None = None,
                 dither: str = "none", seed: int = 0, smooth: bool = False):
        self.X = None if X is None else as_store(X, "X")
        self.T = None if T is None else as_store(T, "T")
        self.choice = choose_path(self.X, self.T if path != "explicit" else None, terms, path)
        store = self.X if self.choice.path == "explicit" else self.T
        self.shape = image_shape_of(store)
        self.channels = channels_of(store)
        check_same_images(self.shape, (self.X, "X"), (self.T, "T"))
        self.batch = int(batch)
        self.video_in = is_video_file(desired)
        self.projection, self.source = _projected_source(
            desired, self.video_in, self.X, self.T, self.shape, self.channels,
            response=projector_response, bits=projector_bits, dither=dither, seed=seed,
            smooth=smooth)
        self.clip = _projector_clip(clip, self.projection)
        self.encoding = source_encoding(self.source, self.channels, encoding)
        self.output = Path(output)
        stores = store_paths(self.X, self.T)
        self._sink = _sink_for(self.source, self.output, self.video_in,
                               _output_bits(bits, self.projection), fps, stores,
                               self.channels, self.projection.output_shape(self.shape))
        self._options = dict(memory_limit=memory_limit, precision=precision,
                             resident=resident and scheduler is None,
                             cache_bytes=cache_budget(cache_bytes))
        self._scheduler = scheduler
        self._stack: contextlib.ExitStack | None = None
        self._image_code_dtype = False  # not known yet (image_code_dtype)
        self.runner = None
        self.compensator: Compensator | None = None

    def __enter__(self) -> "FileCompensation":
        with contextlib.ExitStack() as stack:
            self.runner = stack.enter_context(scheduler_runner(self._scheduler))
            self.compensator = Compensator(self.X, self.T, self.choice, self.clip,
                                           runner=self.runner, **self._options)
            self._stack = stack.pop_all()
        return self

    def __exit__(self, *exc) -> bool:
        if self._stack is not None:
            self._stack.close()
        return False

    @property
    def frames(self) -> int | None:
        """Frames to compensate (a video's is its header's estimate; None if unknown)."""
        return len(self.source) or None

    @property
    def residency(self) -> Residency:
        return self._entered().residency

    def describe(self) -> str:
        """What is about to run: the input, the stores, the path (before entering: X
        is not read yet)."""
        src = self.source
        count = self.frames
        sizes = self.projection.describe_sizes()
        image = sizes or (f"image {self.shape[0]}x{self.shape[1]}" if self.shape else None)
        head = (f"{'~' if self.video_in else ''}{count if count else 'the'} frame(s) from "
                f"{src.path}" + (f", {image}" if image else "")
                + (f", video {src.info.codec} {src.info.pix_fmt} at {src.info.fps:g} frames/s"
                   if self.video_in else ""))
        lines = [head]
        for st, name in ((self.X, "X"), (self.T if self.choice.path == "matrix-free" else None,
                                         "T")):
            if st is not None:
                lines.append(describe_store(st, name))
        lines.append(describe_path(self.choice))
        if self.channels == 3 or not self.encoding.linear:
            lines.append(self.encoding.describe())
        lines.append(self.projection.describe_encoding(self.encoding))
        return "\n".join(lines)

    def describe_residency(self) -> str:
        """Where X is held for the run, and why (in memory, or streamed from disk)."""
        count = self.frames
        return self.residency.describe(min(self.batch, count or self.batch))

    def run(self, *, overlap: bool = True, on_batch: Callable[[int], None] | None = None,
            codes: bool = True) -> FileCompensationReport:
        """Compensate every frame and write the output.

        Parameters
        ----------
        overlap : bool
            Read the next batch and write the last one while this one is computed.
        on_batch : callable, optional
            Called with the number of frames of each batch done (a progress bar).
        codes : bool
            Integer codes through the products where they give the same output
            (:attr:`takes_codes`, :attr:`image_code_dtype`); False: the float frames
            always (the reference those paths are tested against).
        """
        comp = self._entered()
        encoding, projection = self.encoding, self.projection
        if codes and self.takes_codes:
            stream = self._run_codes(comp, overlap, on_batch)
        elif codes and self.image_code_dtype is not None:
            stream = self._run_image_codes(comp, overlap, on_batch)
        else:
            stream = self._run_frames(comp, overlap, on_batch)
        encoder = projection.encoder
        return FileCompensationReport(
            self._sink.path, self.batch, stream, comp.residency, comp.report, self.clip,
            encoding, None if encoder is None else encoder.clipping,
            None if encoder is None else encoder.bits)

    @property
    def takes_codes(self) -> bool:
        """True when the video's integer codes go through the products as they are
        (:meth:`Compensator.compensate_codes`): a video in and out, X in memory, linear
        light, no projector response nor rig geometry around the products."""
        comp = self._entered()
        projection = self.projection
        return (self.video_in and self._sink.video is not None and comp.takes_codes
                and self.encoding.linear and projection.geometry is None
                and projection.encoder is None)

    @property
    def image_code_dtype(self) -> np.dtype | None:
        """The integer type (uint8 or uint16) of PNG frames whose codes go through the
        products as they are and come out as the codes of PNG files of the same depth
        (:meth:`Compensator.compensate_codes` with ``images``: the files the float
        frames would give, byte for byte, without the float frames): X in memory,
        linear light, no projector response nor rig geometry, every frame a grey or
        RGB PNG of one depth (:func:`~bigT.images.png_code_dtype`) written at that
        depth. None otherwise: the float frames run."""
        comp = self._entered()
        projection, sink = self.projection, self._sink
        if (self.video_in or not sink.images or not comp.takes_codes
                or not self.encoding.linear or projection.geometry is not None
                or projection.encoder is not None):
            return None
        if self._image_code_dtype is False:  # the headers, read once
            dtype = png_code_dtype(self.source.files)
            self._image_code_dtype = (dtype if dtype is not None
                                      and sink.image_sink.takes_codes(dtype) else None)
        return self._image_code_dtype

    def _run_image_codes(self, comp: Compensator, overlap: bool, on_batch) -> StreamReport:
        """PNG codes decoded (on the codec pool with overlap) -> the products -> PNG
        codes encoded: :meth:`_run_frames` of a plain PNG folder, its float frames,
        their conversions and quantisation left out (two passes over a frame fewer
        than six)."""
        dtype, source = self.image_code_dtype, self.source
        t0 = time.perf_counter()
        with contextlib.ExitStack() as stack:
            stack.enter_context(self._sink)  # closes (a folder's fsync) after the pool
            read = lambda file: source.read_codes(file, dtype)  # noqa: E731
            batches, write, behind = self._image_stages(
                stack, comp, overlap, self._sink.image_sink.write_codes, read)
            stream = run_stream(batches,
                                lambda codes: comp.compensate_codes(codes, dtype, images=True),
                                write, batch=self.batch, overlap=overlap, on_batch=on_batch)
            written = behind.finish() if behind is not None else None
        if written is not None:  # the seconds up to the folder's fsync, on closing
            stream = with_encoding_times(stream, written, time.perf_counter() - t0)
        return stream

    def _run_codes(self, comp: Compensator, overlap: bool, on_batch) -> StreamReport:
        """Codes decoded by ffmpeg -> the products -> codes encoded by ffmpeg (the
        decoder and encoder in their own processes, beside the products)."""
        video = self._sink.video
        with self._sink:
            dtype = video.code_dtype
            return run_stream(self.source.code_batches(self.batch),
                              lambda codes: comp.compensate_codes(codes, dtype),
                              lambda names, codes: video.write_codes(codes),
                              batch=self.batch, overlap=overlap, on_batch=on_batch)

    def _run_frames(self, comp: Compensator, overlap: bool, on_batch) -> StreamReport:
        """Frames of light -> the products -> frames of light, with the encodings and
        the projector's maps around them."""
        encoding, projection = self.encoding, self.projection
        t0 = time.perf_counter()
        with contextlib.ExitStack() as stack:
            # the sink first: it closes (a folder's fsync) after the pool's last file
            write = stack.enter_context(self._sink)
            # a video's frames are decoded and encoded by ffmpeg, in its own processes
            if self.video_in:
                batches, behind = video_batches(self.source, self.batch), None
            else:
                batches, write, behind = self._image_stages(stack, comp, overlap, write)
            # averaged onto the super-pixels in the reader's thread, expanded onto the
            # projector in the writer's, beside the products
            stream = run_stream(
                in_light(batches, encoding, projection), comp,
                lambda names, frames: write(names, projection.to_values(frames, encoding)),
                batch=self.batch, overlap=overlap, on_batch=on_batch)
            written = behind.finish() if behind is not None else None
        if written is not None:  # the seconds up to the folder's fsync, on closing
            stream = with_encoding_times(stream, written, time.perf_counter() - t0)
        return stream

    def _image_stages(self, stack: contextlib.ExitStack, comp: Compensator, overlap: bool,
                      write, read=None):
        """(batches, write, behind) of the image files read: with ``overlap``, decoded
        ahead on a codec pool entered on ``stack`` (the products on the cores it
        leaves) and, where the output is image files, encoded behind (``behind``, to
        finish); else read in this thread (``behind`` None). ``read`` reads one file
        (default the float32 frame)."""
        pool = stack.enter_context(CodecPool()) if overlap else None
        if pool is None:
            return image_batches(self.source, self.batch, read), write, None
        stack.enter_context(comp.products_on(pool.product_threads(comp.threads)))
        batches = decoded_ahead(pool, self.source, self.batch, read=read)
        if not self._sink.images:  # a video out: ffmpeg encodes
            return batches, write, None
        behind = EncodedBehind(pool, write)
        return batches, behind.write, behind

    def _entered(self) -> Compensator:
        if self.compensator is None:
            raise RuntimeError("use FileCompensation as a context manager: "
                               "`with FileCompensation(...) as job: job.run()`")
        return self.compensator


def compensate_files(X, desired, output, **options) -> FileCompensationReport:
    """Compensate an image, a folder of frames or a video in one call
    (:class:`FileCompensation`, its options, entered and run)."""
    with FileCompensation(X, desired, output, **options) as job:
        return job.run()


def image_shape_of(store) -> tuple[int, int] | None:
    """The (H, W) of the images a store maps (None when it records no pixel order)."""
    order = getattr(store, "pixel_order", None)
    return None if order is None else order.image_shape


def channels_of(store) -> int:
    """1 for a grey store (or one that maps no images), 3 for a colour one."""
    return int(getattr(store, "channels", 1) or 1)


def in_light(batches, encoding: FrameEncoding, projection: Projection | None = None):
    """(names, frames) batches with the frames decoded to linear light, and a camera's
    averaged onto T's super-pixels (closing this generator closes ``batches``: a
    video's decoder stops)."""
    try:
        for names, frames in batches:
            light = encoding.to_light(frames)
            yield names, light if projection is None else projection.to_superpixels(light)
    finally:
        close = getattr(batches, "close", None)
        if close is not None:
            close()


def store_paths(*stores) -> list:
    """The directories of the stores given (None skipped), each with the root it was
    opened through (a versioned store's redirect): what no output may destroy."""
    return [p for st in stores if st is not None
            for p in (st.path, getattr(st, "redirected_from", None)) if p is not None]


def check_same_images(shape, *stores) -> None:
    """ImageError unless every ``(store, name)`` given maps images of ``shape`` (or
    records none), all grey or all colour."""
    kinds = {channels_of(store) for store, _ in stores if store is not None}
    for store, name in stores:
        if store is not None and shape is not None and image_shape_of(store) not in (None, shape):
            raise ImageError(f"{name} maps images of shape {image_shape_of(store)} but the "
                             f"compensation store maps {shape}", store.path)
        if store is not None and len(kinds) > 1:
            raise ImageError(f"{name} is a {'colour' if channels_of(store) == 3 else 'grey'} "
                             "transport but the other store is not: give stores of one kind",
                             store.path)


@dataclass(frozen=True)
class FileSimulationReport:
    """What :meth:`FileSimulation.run` did: the simulation's numbers, where each
    output went, and the wall time with the simulation's passes over T.

    Attributes
    ----------
    simulation : SimulationReport
    projector, seen : Path, the projector input and the camera's simulated view written
    figures : (Path, Path), the side-by-side comparison and the scan lines (PNG)
    batch : int
    seconds : float, wall time of the whole run
    projector_clipping : ResponseClipping or None, with a projector response: the values
        it could not emit
    projector_bits : int or None, the projector's depth, with a response
    """

    simulation: SimulationReport
    projector: Path
    seen: Path
    figures: tuple[Path, Path]
    batch: int
    seconds: float
    projector_clipping: ResponseClipping | None = None
    projector_bits: int | None = None

    def to_dict(self) -> dict:
        """The report as JSON-ready values (``compensate --simulate --json``)."""
        return {**self.simulation.to_dict(), "batch": self.batch,
                "seconds_in_all": self.seconds, "projector": str(self.projector),
                "seen": str(self.seen), "figures": [str(f) for f in self.figures],
                **projector_dict(self.projector_clipping, self.projector_bits)}

    def describe(self) -> str:
        r = self.simulation
        seen = ("simulated camera (T times the projector's light for its values)"
                if self.projector_clipping is not None else "simulated camera (T l_in)")
        return "\n".join([
            f"{r.frames} frame(s) in {r.seconds:.2f} s of products "
            f"({r.frames_per_second:.1f} frames/s, batch {self.batch}); {self.seconds:.2f} s "
            "in all (the simulation's passes over T included)",
            *written_lines(self.projector, FrameEncoding("linear", ""),
                           self.projector_clipping, self.projector_bits)[-1:],
            f"{seen} -> {self.seen}",
            *r.describe().splitlines(),
            *([self.projector_clipping.describe()] if self.projector_clipping else []),
            f"figures -> {self.figures[0]}, {self.figures[1]}"])


class FileSimulation:
    """Compensation of an image or a folder of frames with what the camera then sees
    simulated through T (what ``bigT compensate --simulate T`` runs), checked when made.

    Parameters
    ----------
    X : BlockCSR, path, or None (with the matrix-free path)
    desired : path, an image or a folder of frames (not a video)
    output : path; the camera's view goes beside it (``out_seen.png``), and the figures
        (``out_compare.png``, ``out_scanline.png``)
    T : BlockCSR or path, the transport the camera's view is simulated with
    path, matrix_free, terms : of the compensation (:func:`choose_path`); ``matrix_free``
        is the transport the matrix-free path streams (default ``T``)
    clip, batch, bits, cache_bytes, scheduler, encoding : as :class:`FileCompensation`;
        the camera's view is written in the input's encoding too, and the metrics are of
        the images in it
    metrics : bool, PSNR, SSIM and ΔE in the report (:func:`simulate_batches`)
    projector_response, projector_bits, dither, seed, smooth : as
        :class:`FileCompensation` (``"auto"``: the response stored with ``T``). With a
        response, the camera's view is simulated through the same projector: T times
        the light its codes send (the loop closes through its nonlinearity). With a
        rig's T, the camera's view is written at the camera's resolution for a camera
        input.
    """

    def __init__(self, X, desired, output, T, *, path: str = "auto", matrix_free=None,
                 terms: int | None = None, clip=(0, 1), batch: int = config.DEFAULT_BATCH,
                 bits: int | None = None, cache_bytes: int | None = None, scheduler=None,
                 encoding: str = "auto", metrics: bool = True, projector_response="auto",
                 projector_bits: int | None = None, dither: str = "none", seed: int = 0,
                 smooth: bool = False):
        self.X = None if X is None else as_store(X, "X")
        self.T = as_store(T, "T")
        self.Tm = self.T if matrix_free is None else as_store(matrix_free, "T")
        self.choice = choose_path(self.X, self.Tm if path != "explicit" else None, terms, path)
        store = self.X if self.choice.path == "explicit" else self.Tm
        self.shape = image_shape_of(store)
        self.channels = channels_of(store)
        check_same_images(self.shape, (self.X, "X"), (self.Tm, "T"),
                          (self.T, "T (the simulated camera's)"))
        if is_video_file(desired):
            raise ImageError("a simulation takes an image or a folder of frames, not a video",
                             desired)
        self.projection, self.source = _projected_source(
            desired, False, self.X, self.T, self.shape, self.channels,
            response=projector_response, bits=projector_bits, dither=dither, seed=seed,
            smooth=smooth)
        self.encoding = source_encoding(self.source, self.channels, encoding)
        self.metrics = bool(metrics)
        out = Path(output)
        stores = store_paths(self.X, self.T, self.Tm)
        self.figures = (sibling_path(out, "compare", ".png"), sibling_path(out, "scanline", ".png"))
        refuse_overwriting_inputs(self.figures, [desired, *stores])
        out_bits = _output_bits(bits, self.projection)
        self._sink = ImageSink(out, self.source, bits=out_bits, inputs=stores)
        self._seen = ImageSink(sibling_path(out, "seen"), self.source, bits=bits, inputs=stores)
        self.clip, self.batch = _projector_clip(clip, self.projection), int(batch)
        self._options = dict(cache_bytes=cache_bytes, scheduler=scheduler)

    def describe(self) -> str:
        """The input, the stores (each once) and the path."""
        sizes = self.projection.describe_sizes()
        image = sizes or (f"image {self.shape[0]}x{self.shape[1]}" if self.shape else None)
        lines = [f"{len(self.source)} frame(s) from {self.source.path}"
                 + (f", {image}" if image else "")]
        shown = []
        for st, name in ((self.X, "X"), (self.Tm if self.choice.path == "matrix-free"
                                         else None, "T"), (self.T, "T")):
            if st is not None and all(st is not o for o in shown):
                lines.append(describe_store(st, name))
                shown.append(st)
        lines.append(describe_path(self.choice))
        if self.channels == 3 or not self.encoding.linear:
            lines.append(self.encoding.describe())
        lines.append(self.projection.describe_encoding(self.encoding))
        if self.projection.encoder is not None:
            lines.append("the camera's view is simulated through the same projector: T times "
                         "the light its codes send")
        return "\n".join(lines)

    def run(self, *, progress: bool = False,
            on_batch: Callable[[int], None] | None = None) -> FileSimulationReport:
        """Compensate and simulate every frame, write both and the figures."""
        encoding, projection = self.encoding, self.projection

        def write(files, written, seen):
            self._sink.write(files, written if projection.encoder is not None
                             else encoding.from_light(written))
            self._seen.write(files, encoding.from_light(projection.seen_on_camera(seen)))
            if on_batch is not None:
                on_batch(len(files))

        t0 = time.perf_counter()
        report = simulate_batches(
            in_light(self.source.batches(self.batch), encoding, projection), self.X, self.T,
            clip=self.clip, path=self.choice.path, matrix_free=self.Tm,
            terms=self.choice.terms, progress=progress, on_batch=write,
            metrics=encoding.name if self.metrics else None, project=projection.sent,
            **self._options)
        seconds = time.perf_counter() - t0
        tag = f" (frame {report.first.name})" if self.source.is_folder else ""
        figures = simulation_figures(report, *self.figures, tag=tag)
        encoder = projection.encoder
        return FileSimulationReport(report, self._sink.path, self._seen.path, tuple(figures),
                                    self.batch, seconds,
                                    None if encoder is None else encoder.clipping,
                                    None if encoder is None else encoder.bits)


def sibling_path(path: Path, tag: str, suffix: str | None = None) -> Path:
    """``out.png`` -> ``out_<tag>.png`` (``suffix`` to change it); ``dir`` -> ``dir_<tag>``."""
    if path.suffix:
        return path.with_name(f"{path.stem}_{tag}{suffix or path.suffix}")
    return path.with_name(f"{path.name}_{tag}{suffix or ''}")


@dataclass(frozen=True)
class RelightReport:
    """What :func:`relight_files` did.

    Attributes
    ----------
    output : Path, the image or folder written
    frames : int
    seconds : float, of the products
    above_one : float
        Share of the camera's values brighter than 1 (an 8/16-bit PNG clips them).
    clipped_in_output : bool, the output is PNG, so those values were clipped in it
    encoding : FrameEncoding, of the input's values and of the camera's view written
    """

    output: Path
    frames: int
    seconds: float
    above_one: float
    clipped_in_output: bool
    encoding: FrameEncoding = FrameEncoding("linear", "grey input")

    def describe(self) -> str:
        encoded = "" if self.encoding.linear else f" ({self.encoding.name}-encoded, as the input)"
        lines = [f"{self.frames} frame(s) in {self.seconds:.2f} s "
                 f"({self.frames / max(self.seconds, 1e-9):.1f} frames/s)",
                 f"wrote{encoded} -> {self.output}"]
        if self.above_one and self.clipped_in_output:
            lines.append(f"note: {100 * self.above_one:.2f} % of pixels exceed 1 and are "
                         "clipped in the PNG output; use .tif or .npy to keep them")
        return "\n".join(lines)


def relight_files(T, images, output, *, batch: int = config.DEFAULT_BATCH,
                  bits: int | None = None, scheduler=None, progress: bool = False,
                  on_start: Callable[[str], None] | None = None,
                  encoding: str = "auto") -> RelightReport:
    """What the camera sees, T l, for an image or a folder of them, written as images.

    Parameters
    ----------
    T : BlockCSR or path
    images : path, an image or a folder of them
    output : path, an image, or a folder for a folder
    batch : int, frames per pass over T
    bits : int, optional, of the images written
    scheduler : as :func:`bigT.schedule.runner.open_runner`, optional
    on_start : callable, optional
        Called with the runner's description once it runs on a cluster.
    encoding : {"auto", "srgb", "linear"}
        Of the projector images' values (as :class:`FileCompensation`'s); the camera's
        view is written in the same encoding.
    """
    T = as_store(T, "T")
    channels = channels_of(T)
    source = ImageSource(images, image_shape_of(T), channels)
    check_frame_shapes(source.files, image_shape_of(T), channels)
    light = source_encoding(source, channels, encoding)
    sink = ImageSink(output, source, bits=bits, inputs=store_paths(T))
    above = pixels = 0
    t0 = time.perf_counter()
    with scheduler_runner(scheduler) as runner:
        if runner is not None and on_start is not None:
            on_start(runner.describe())
        for files, frames in source.batches(batch):
            seen = relight(T, light.to_light(frames), batch=batch, progress=progress,
                           scheduler=runner)
            above += int(np.count_nonzero(seen > 1))
            pixels += seen.size
            sink.write(files, light.from_light(seen))
    png = any(sink.target(f).suffix.lower() == ".png" for f in source.files[:1])
    return RelightReport(sink.path, len(source), time.perf_counter() - t0,
                         above / max(pixels, 1), png, light)


def describe_store(store, name: str) -> str:
    """``X /path: 12,288 x 12,288, nnz 1,234 (100/row), 2 tile rows``."""
    return (f"{name} {store.path}: {store.shape[0]:,} x {store.shape[1]:,}, nnz {store.nnz:,} "
            f"({store.nnz / max(store.shape[0], 1):.0f}/row), {store.grid[0]} tile rows")


def describe_path(choice) -> str:
    """``path: explicit -- why``, with the terms of the matrix-free path."""
    return (f"path: {choice.path}" + (f" ({choice.terms} terms)" if choice.terms is not None
                                      else "") + f" -- {choice.reason}")


def check_frame_shapes(files, shape, channels: int = 1) -> None:
    """Every frame of a folder has the transport's (H, W) and channels: read from the
    headers, so a folder with one bad frame is refused before anything is written."""
    if shape is None:
        return
    fine = ((), (1,)) if channels == 1 else ((3,),)
    for f in files:
        found = declared_shape(f)  # None when unreadable: read_image says why
        if (found is None or len(found) not in (2, 3) or tuple(found[:2]) != tuple(shape)
                or tuple(found[2:]) not in fine):
            # the one-line ImageError naming the file (or an opaque alpha channel, fine)
            read_image(f, shape, channels)


class _Sink:
    """``write(names, frames)`` into a video (whole or nothing) or images
    (:class:`ImageSink`); checked when made (no output may destroy the source nor
    one of ``stores``), opened only by ``with``."""

    def __init__(self, source, out_path: Path, video: VideoSink | None, bits, stores=()):
        self._video = video
        if video is not None:
            refuse_overwriting_inputs([video.path], [source.path, *stores])
            self._images = None
            self.path = video.path
        else:
            self._images = ImageSink(out_path, source, bits=bits, inputs=stores)
            #: what is written: the video, the folder, or the one image
            self.path = self._images.path

    @property
    def images(self) -> bool:
        """True when frames are written as image files (each on its own)."""
        return self._video is None

    @property
    def video(self) -> VideoSink | None:
        """The video written, or None for images."""
        return self._video

    @property
    def image_sink(self) -> ImageSink | None:
        """The image files written (None for a video): its ``write_codes`` within
        ``with``."""
        return self._images

    def __enter__(self):
        if self._video is not None:
            video = self._video.__enter__()
            return lambda names, frames: video.write(frames)
        # each frame whole or absent, the folder fsynced once on exit
        self._synced = self._images.synced_once()
        return self._synced.__enter__().write

    def __exit__(self, *exc):
        if self._video is not None:
            return self._video.__exit__(*exc)
        self._synced.__exit__(*exc)
        return False


def _sink_for(source, out_path: Path, video_in: bool, bits, fps, stores=(),
              channels: int = 1, output_shape=None) -> _Sink:
    """The output of a compensation, its kind and format checked before X is read, and
    refused where it would destroy the source or one of ``stores``; ``output_shape``
    the (H, W) of the frames written (default the input's)."""
    if video_in or (source.is_folder and is_video_file(out_path)):
        fps = source.info.fps if video_in else (fps or DEFAULT_FPS)
        bits = bits or (source.info.bits if video_in else 8)
        shape = output_shape or (source.info.shape if video_in else _frame_shape(source))
        video = VideoSink(out_path, shape, fps, bits, channels=channels)
        return _Sink(source, out_path, video, bits, stores)
    if source.is_folder:
        if out_path.exists() and not out_path.is_dir():
            raise ImageError("the input is a folder, so the output must be a folder (or "
                             "a video) too", out_path)
    elif not out_path.is_dir() and not is_image_file(out_path):
        raise ImageError(f"unknown output format {out_path.suffix!r} (an image: .png, "
                         ".tif, .tiff, .npy)", out_path)
    return _Sink(source, out_path, None, bits, stores)


def _frame_shape(source):
    """(H, W) of a folder's frames: the store's, else the first frame's."""
    return source.shape or read_image(source.files[0]).shape[:2]


def _projected_source(desired, video_in: bool, X, T, grid, channels: int, **projector):
    """(Projection, the source of desired frames at the size it takes), every frame's
    size checked before X is read or anything written."""
    if video_in:
        probe = VideoSource(desired, None, channels=channels)
        sizes = [(tuple(probe.info.shape), probe.path)]
    else:
        probe = ImageSource(desired, None, channels)
        sizes = image_sizes(probe.files)
    projection = projection_for(X, T, grid, channels, frame_sizes=sizes, **projector)
    shape = projection.input_shape(grid)
    if video_in:
        if shape is not None and tuple(probe.info.shape) != tuple(shape):
            raise ImageError(f"frames of shape {probe.info.shape} do not match the "
                             f"transport's image shape {tuple(shape)}", probe.path)
        return projection, probe
    source = ImageSource(desired, shape, channels)
    check_frame_shapes(source.files, shape, channels)
    return projection, source


def _projector_clip(clip, projection: Projection):
    """The compensation's clip: with a projector response, (0, 1) is the response's own
    range (black to full scale), clipped and counted by the encoding instead."""
    if projection.encoder is not None and clip is not None and tuple(clip) == (0, 1):
        return None
    return clip


def _output_bits(bits, projection: Projection):
    """The depth of the images written: the projector's with a response (a different
    ``bits`` is refused), else ``bits``."""
    encoder = projection.encoder
    if encoder is None:
        return bits
    if bits is not None and bits != encoder.bits:
        raise ImageError(f"an output depth of {bits} bits disagrees with the projector's "
                         f"{encoder.bits}: its values are written at its own depth (give "
                         "{option})", option=Option("projector_bits", bits))
    return encoder.bits
