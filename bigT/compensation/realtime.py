"""Compensation of a stream of frames (a video, a folder): read, compensate, write.

A projector shows 30-60 frames per second, so the frame rate and the latency of one
frame (read + compensate + write) are what count. Two parts:

* :class:`Compensator` turns a batch of desired frames into clipped projector frames:
  with X held in memory (:mod:`bigT.compensation.resident`) when it fits the memory
  budget, else with X (or T, matrix-free) streamed from disk tile row by tile row as
  :func:`~bigT.compensation.compensate` does.
* :func:`run_stream` moves the batches through it: by default a reader thread decodes
  the next batch and a writer thread encodes the last one while this one is
  compensated (the products, the decoders and the encoders all release the GIL);
  ``overlap=False`` does one batch at a time, each out before the next is read.

The latency of a frame is the time from the start of reading its batch to the end of
writing it (queueing included); :class:`StreamReport` keeps them all.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from .. import config
from ..storage import disk_bytes
from ..storage.frames import frames_to_matrix, matrix_to_frames, pixel_order_of
from .core import CompensationReport, PathChoice, compensate_frames
from .codes import gather_codes, scatter_codes
from .resident import (ResidentMatrix, default_memory_limit, load_bytes_needed,
                       load_resident, resident_bytes_needed)

MIB = float(1 << 20)


# --- compensators ---------------------------------------------------------------------

@dataclass(frozen=True)
class Residency:
    """Where X is read from, and how much of it a pass reads.

    Attributes
    ----------
    resident : bool, X held in memory.
    precision : str, "float32" or "float16" in memory; the store's dtype streamed.
    bytes_per_pass : int, bytes of X read by one pass (one batch): the arrays held in
        memory, or the decoded tiles streamed (float values + int32 indices + row
        pointers).
    disk_bytes : int or None, X's compressed tiles on disk (streamed only).
    limit : int, the memory budget it was held to.
    reason : str, why (in words).
    """

    resident: bool
    precision: str
    bytes_per_pass: int
    disk_bytes: int | None
    limit: int
    reason: str

    def describe(self, batch: int) -> str:
        """One line: where X is, its size, bytes read per frame at ``batch``."""
        per_frame = self.bytes_per_pass / max(1, batch)
        if self.resident:
            return (f"X held in memory: {self.bytes_per_pass / MIB:.1f} MiB ({self.precision} "
                    f"values, 16-bit column indices), {per_frame / MIB:.2f} MiB "
                    f"({per_frame:,.0f} bytes) of X read per frame at batch {batch}")
        disk = "" if self.disk_bytes is None else f" ({self.disk_bytes / MIB:.1f} MiB on disk)"
        return (f"X streamed from disk tile row by tile row ({self.reason}): "
                f"{self.bytes_per_pass / MIB:.1f} MiB of decoded tiles per pass{disk}, "
                f"{per_frame / MIB:.2f} MiB ({per_frame:,.0f} bytes) of X read per frame at "
                f"batch {batch}")


def _streamed_bytes(store) -> int:
    """Bytes of the decoded tiles of one pass over ``store`` (values, int32 indices,
    row pointers per tile)."""
    itemsize = np.dtype(store.dtype).itemsize
    return int(store.nnz * (itemsize + 4) + store.n_tiles_stored * (store.tile_size + 1) * 4)


def _disk_bytes(store) -> int:
    """X's files on disk (:func:`bigT.storage.disk_bytes`)."""
    return disk_bytes(store.path)


class Compensator:
    """Desired frames -> clipped projector frames, X in memory or streamed.

    Parameters
    ----------
    X : BlockCSR or None
    T : BlockCSR or None, the transport of the matrix-free path
    choice : PathChoice
    clip : (lo, hi) or None
    memory_limit : int, optional
        Bytes X may take in memory (default :func:`resident.default_memory_limit`);
        0 always streams.
    precision : {"float32", "float16"}, of X held in memory.
    resident : bool, False to stream X whatever its size (a cluster's runs).
    cache_bytes, runner : of the streamed path (:func:`compensate_frames`).
    """

    def __init__(self, X, T, choice: PathChoice, clip=(0, 1), *, memory_limit: int | None = None,
                 precision: str = "float32", resident: bool = True,
                 cache_bytes: int | None = None, runner=None):
        self.X, self.T, self.choice, self.clip = X, T, choice, clip
        self.cache_bytes, self.runner = cache_bytes, runner
        self.report = CompensationReport(choice)
        self.matrix: ResidentMatrix | None = None
        self.threads = max(1, int(config.KERNEL_THREADS or os.cpu_count() or 1))
        store = X if choice.path == "explicit" else T
        self.order = None
        self._perm: np.ndarray | None = None  # int32 pixel order of the codes path
        self._buffers: tuple[np.ndarray, np.ndarray] | None = None
        limit = default_memory_limit() if memory_limit is None else int(memory_limit)
        self.residency = self._place(store, limit, precision, resident)
        if self.residency.resident:
            self.matrix = load_resident(X, precision, memory_limit=limit)
            # the bytes it holds (resident_bytes_needed bounds its segments from above)
            self.residency = dataclasses.replace(self.residency,
                                                 bytes_per_pass=self.matrix.nbytes)

    def _place(self, store, limit, precision, resident) -> Residency:
        streamed = _streamed_bytes(store) * (self.choice.terms or 1)
        if self.choice.path != "explicit":
            return Residency(False, str(store.dtype), streamed, _disk_bytes(store), limit,
                             f"matrix-free, {self.choice.terms} passes over T")
        if not resident:
            return Residency(False, str(store.dtype), streamed, _disk_bytes(store), limit,
                             "asked for")
        need = load_bytes_needed(store, precision)
        if need > limit:
            return Residency(False, str(store.dtype), streamed, _disk_bytes(store), limit,
                             f"holding it needs {need / MIB:.0f} MiB, over the memory limit "
                             f"of {limit / MIB:.0f} MiB")
        return Residency(True, precision, resident_bytes_needed(store, precision), None, limit,
                         f"fits the memory limit of {limit / MIB:.0f} MiB")

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        """(K, *frame_shape) desired frames, linear light ((K, H, W), or (K, H, W, 3)
        for a colour X) -> projector frames of the same shape, clipped (float32 with X
        in memory, float64 streamed)."""
        if self.matrix is None:
            return compensate_frames(frames, X=self.X, T=self.T, choice=self.choice,
                                     clip=self.clip, report=self.report, progress=False,
                                     cache_bytes=self.cache_bytes, runner=self.runner)
        if self.order is None:
            self.order = pixel_order_of(self.X, frames.shape[1:])
        # float32 frames out: they are quantised to 8/16 bits or written as float32
        threads = self.threads
        B = frames_to_matrix(frames, self.order, np.float32, n_threads=threads)
        Y = self.matrix.matmul(B, n_threads=threads)
        out, below, above = matrix_to_frames(Y, self.order, self.clip, dtype=np.float32,
                                             n_threads=threads)
        self.report.add_clipped(Y, self.clip, self.order.channels, below, above, out.size)
        return out

    @contextlib.contextmanager
    def products_on(self, threads: int) -> Iterator[None]:
        """Within: the products (and the pixel gathers and scatters) on ``threads``
        threads (at least one). Their rows are split among the threads, each row summed
        whole by one: the frames are the same whatever the count."""
        before = self.threads
        self.threads = max(1, int(threads))
        try:
            yield
        finally:
            self.threads = before

    def _batch_buffers(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The (n, k) float32 batch and product of :meth:`compensate_codes`, kept from
        one call to the next (both are used up within a call): 66 MB each at full HD
        and k = 8, which a fresh allocation would fault in page by page every batch
        (measured 5 ms of system time a frame)."""
        if self._buffers is None or self._buffers[0].shape[1] != k:
            n_rows, n_cols = self.matrix.shape
            self._buffers = (np.empty((n_cols, k), np.float32),
                             np.empty((n_rows, k), np.float32))
        return self._buffers

    @property
    def takes_codes(self) -> bool:
        """True when :meth:`compensate_codes` runs: X held in memory."""
        return self.matrix is not None

    def compensate_codes(self, codes: np.ndarray, dtype, images: bool = False) -> np.ndarray:
        """(K, *frame_shape) integer codes of linear light (a video's uint8 or uint16)
        -> the projector's codes of ``dtype``, clipped and quantised: the frames
        :meth:`__call__` gives for ``codes / top``, quantised as the video sink does,
        in two passes over the frames instead of some eight
        (:mod:`bigT.compensation.codes`); with ``images``, the codes of PNG files read
        and written by :mod:`bigT.images` (its division and its quantisation). X must
        be held in memory."""
        if self.matrix is None:
            raise RuntimeError("compensate_codes needs X held in memory (takes_codes)")
        if self._perm is None:
            self.order = self.order or pixel_order_of(self.X, codes.shape[1:])
            # int32 indices: half the bytes of the int64 permutation read each pass
            self._perm = self.order.permutation.astype(np.int32)
        threads = self.threads
        B, Y = self._batch_buffers(codes.shape[0])
        gather_codes(codes, self._perm, threads, out=B, images=images)
        self.matrix.matmul(B, out=Y, n_threads=threads)
        out, below, above = scatter_codes(Y, self._perm, self.clip, self.order.frame_shape,
                                          dtype, threads, images=images)
        self.report.add_clipped(Y, self.clip, self.order.channels, below, above, out.size)
        return out


# --- the stream -----------------------------------------------------------------------

@dataclass(frozen=True)
class StreamReport:
    """What :func:`run_stream` measured.

    Attributes
    ----------
    frames : int
    batch : int, frames per batch asked for.
    seconds : float, wall time from the first read to the last write.
    compute_seconds : float, time in the compensator (products and pixel reordering).
    latencies : ndarray, shape (frames,), seconds from the start of reading each
        frame's batch to the end of writing it, waits in the queues included (a file
        is read as fast as the reader can: with ``overlap`` frames wait for the
        products).
    service : ndarray, shape (frames,), seconds of reading + compensating + writing
        each frame's batch, without the waits: the latency of a stream paced slower
        than the pipeline (a live source). Equal to ``latencies`` without ``overlap``
        but for the time between the stages.
    overlap : bool, reading and writing ran beside the products.
    """

    frames: int
    batch: int
    seconds: float
    compute_seconds: float
    latencies: np.ndarray = field(repr=False)
    service: np.ndarray = field(repr=False)
    overlap: bool

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("inf")

    def latency_ms(self, which: str = "latencies") -> dict:
        """{"mean", "p50", "p95", "max"} in milliseconds of ``which`` ("latencies" or
        "service"); NaN without frames."""
        if not self.frames:
            return dict.fromkeys(("mean", "p50", "p95", "max"), float("nan"))
        ms = 1e3 * getattr(self, which)
        return {"mean": float(ms.mean()), "p50": float(np.percentile(ms, 50)),
                "p95": float(np.percentile(ms, 95)), "max": float(ms.max())}

    def summary(self, residency: Residency | None = None) -> str:
        """One line for people: frames, rate, latency, where X was, bytes of X per frame."""
        lat = self.latency_ms()
        mode = "reading and writing overlapped" if self.overlap else "one batch at a time"
        text = (f"{self.frames} frame(s) in {self.seconds:.2f} s: {self.frames_per_second:.1f} "
                f"frames/s at batch {self.batch} ({mode}); latency per frame mean "
                f"{lat['mean']:.1f} ms, p50 {lat['p50']:.1f} ms, p95 {lat['p95']:.1f} ms")
        if self.overlap:
            own = self.latency_ms("service")
            text += (f" (read + compensate + write without queueing: p50 {own['p50']:.1f} ms, "
                     f"p95 {own['p95']:.1f} ms)")
        if residency is not None:
            per_frame = residency.bytes_per_pass / max(1, min(self.batch, self.frames or 1))
            where = (f"X in memory ({residency.bytes_per_pass / MIB:.0f} MiB, "
                     f"{residency.precision})" if residency.resident else "X streamed")
            rate = per_frame * self.frames_per_second / 1e9
            text += (f"; {where}, {per_frame / 1e6:.1f} MB of X read per frame "
                     f"({rate:.1f} GB/s)")
        return text


class _Stop(Exception):
    """Another stage failed: this one stops quietly."""


class _Stages:
    """The shared state of the reader, compensator and writer: the first error of any
    stage stops the others."""

    def __init__(self):
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self._lock = threading.Lock()

    def fail(self, exc: BaseException) -> None:
        with self._lock:
            if self.error is None and not isinstance(exc, _Stop):
                self.error = exc
        self.stop.set()

    def put(self, q: queue.Queue, item) -> None:
        while True:
            if self.stop.is_set():
                raise _Stop
            try:
                q.put(item, timeout=0.05)
                return
            except queue.Full:
                continue

    def get(self, q: queue.Queue):
        while True:
            if self.stop.is_set():
                raise _Stop
            try:
                return q.get(timeout=0.05)
            except queue.Empty:
                continue


_END = object()


def run_stream(batches: Iterable[tuple[Sequence, np.ndarray]],
               compute: Callable[[np.ndarray], np.ndarray],
               write: Callable[[Sequence, np.ndarray], None], *, batch: int,
               overlap: bool = True, depth: int | None = None,
               on_batch: Callable[[int], None] | None = None) -> StreamReport:
    """Read, compensate and write every batch, timing each frame.

    Parameters
    ----------
    batches : iterable of (names, frames); frames (k, H, W), names k labels.
        Iterated in the reader thread (with ``overlap``): decoding happens there.
    compute : frames (k, H, W) -> outputs (k, H, W); runs in the calling thread.
    write : (names, outputs) -> None; runs in the writer thread (with ``overlap``).
    batch : int, frames per batch (for the report).
    overlap : bool
        Reader and writer threads beside the products (default); False: each batch is
        read, compensated and written before the next is read.
    depth : int, batches queued between the stages (default
        ``config.COMPENSATE_QUEUE_DEPTH``).
    on_batch : called with the number of frames of each batch written (progress).

    Returns
    -------
    StreamReport
    """
    latencies: list[float] = []
    service: list[float] = []
    compute_time = [0.0]

    def timed_compute(stamp, frames):
        t = time.perf_counter()
        out = compute(frames)
        dt = time.perf_counter() - t
        compute_time[0] += dt
        return (*stamp, dt), out

    def finish(stamp, names, out):
        t = time.perf_counter()
        write(names, out)
        done = time.perf_counter()
        t_read, read_s, compute_s = stamp
        latencies.extend([done - t_read] * len(out))
        service.extend([read_s + compute_s + done - t] * len(out))
        if on_batch is not None:
            on_batch(len(out))

    t0 = time.perf_counter()
    if overlap:
        _overlapped(iter(batches), timed_compute, finish,
                    int(depth or config.COMPENSATE_QUEUE_DEPTH))
    else:
        it = iter(batches)
        while True:
            t_read = time.perf_counter()
            item = next(it, _END)
            if item is _END:
                break
            names, frames = item
            stamp, out = timed_compute((t_read, time.perf_counter() - t_read), frames)
            finish(stamp, names, out)
    seconds = time.perf_counter() - t0
    return StreamReport(len(latencies), int(batch), seconds, compute_time[0],
                        np.asarray(latencies), np.asarray(service), overlap)


def _overlapped(it: Iterator, compute, finish, depth: int) -> None:
    """The three stages on three threads (the products on the caller's)."""
    stages = _Stages()
    inbox: queue.Queue = queue.Queue(maxsize=depth)
    outbox: queue.Queue = queue.Queue(maxsize=depth)

    def reader():
        try:
            while True:
                t_read = time.perf_counter()
                item = next(it, _END)
                if item is _END:
                    break
                stages.put(inbox, ((t_read, time.perf_counter() - t_read), item))
            stages.put(inbox, _END)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            stages.fail(exc)

    def writer():
        try:
            while True:
                item = stages.get(outbox)
                if item is _END:
                    return
                finish(*item)
        except BaseException as exc:  # noqa: BLE001
            stages.fail(exc)

    threads = [threading.Thread(target=reader, name="bigT-read", daemon=True),
               threading.Thread(target=writer, name="bigT-write", daemon=True)]
    for t in threads:
        t.start()
    try:
        while True:
            item = stages.get(inbox)
            if item is _END:
                stages.put(outbox, _END)
                break
            stamp, (names, frames) = item
            stamp, out = compute(stamp, frames)
            stages.put(outbox, (stamp, names, out))
    except BaseException as exc:  # noqa: BLE001
        stages.fail(exc)
    finally:
        for t in threads:  # after an error all stop; else the writer drains its queue
            t.join()
        close = getattr(it, "close", None)
        if close is not None:
            close()  # a generator's decoder stops (its ffmpeg ends)
    if stages.error is not None:
        raise stages.error


def image_batches(source, size: int, read: Callable | None = None
                  ) -> Iterator[tuple[list, np.ndarray]]:
    """(files, frames) batches of a :class:`bigT.images.ImageSource`, frames float32
    (the values of its float64 batches cast, read in float32 straight), or what
    ``read(file)`` gives (the codes)."""
    files = list(source.files)
    size = max(1, int(size))
    read = read or (lambda f: source.read(f, np.float32))
    for start in range(0, len(files), size):
        chunk = files[start:start + size]
        yield chunk, np.stack([read(f) for f in chunk])


def video_batches(source, size: int) -> Iterator[tuple[list, np.ndarray]]:
    """(frame numbers, frames) batches of a :class:`~bigT.compensation.video.VideoSource`."""
    names: list[int] = []
    frames: list[np.ndarray] = []
    for i, frame in enumerate(source.frames()):
        names.append(i)
        frames.append(frame)
        if len(frames) == size:
            yield names, np.stack(frames)
            names, frames = [], []
    if frames:
        yield names, np.stack(frames)


__all__ = ["Compensator", "Residency", "StreamReport", "run_stream", "image_batches",
           "video_batches"]
