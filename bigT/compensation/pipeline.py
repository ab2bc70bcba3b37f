"""Image codecs beside the products: a folder's frames decoded ahead and the projector's
frames encoded behind, on a small pool of threads.

With X in memory, one 384x512 frame's product (the dense corner's 4-term X, 23 M
entries) takes ~23 ms on one core, decoding its 16-bit PNG ~2 ms and encoding the
result ~13 ms (zlib level 1): one reader and one writer thread
(:func:`~bigT.compensation.realtime.run_stream`) would leave the codecs beside the
products on the critical path at batch 1. The decoders and encoders release the GIL
(Pillow's and OpenCV's zlib), so here several frames are decoded and encoded at once:

* :func:`decoded_ahead` reads the frames of an :class:`~bigT.images.ImageSource` on the
  pool, a few ahead of the batch asked for, and yields the batches in order;
* :class:`EncodedBehind` hands each frame written to the pool and returns at once,
  waiting for the oldest frame only when a few are pending
  (:data:`FRAMES_IN_FLIGHT_PER_THREAD` a codec thread).

Both keep at most a few frames in flight, so memory stays bounded whatever the length
of the folder; the products share the cores with the codecs (:data:`CODEC_CORES`). Each
frame keeps its file name, and each file is written whole or not at all
(:func:`bigT.atomic.atomic_output`, fsynced before its rename; the folder fsynced once
when the run closes, :meth:`bigT.images.ImageSink.synced_once`): an interrupted run, or
a power cut, leaves complete files only (not necessarily a prefix of the folder: frames
finish out of order). An error names
its frame's file, as the sequential path's does; the first one (in frame order) is
raised, and the frames not yet started are dropped.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from .. import config
from .realtime import StreamReport

#: Threads that decode and encode frames: the cores, at most 4 (beyond that the
#: products, which take every core, only lose time to them).
CODEC_THREADS = max(2, min(4, os.cpu_count() or 1))
#: Frames decoded ahead of the batch being read, and frames handed to the encoders and
#: not yet written, each at most, per codec thread: enough to keep every one busy.
FRAMES_IN_FLIGHT_PER_THREAD = 2
#: Cores the products leave to the codecs while a pool decodes and encodes beside them
#: (unless ``config.KERNEL_THREADS`` says how many threads the products take). The
#: product with X in memory is bound by memory bandwidth: one 384x512 frame's (23 M
#: entries) takes 23 ms of CPU on one thread but more on two (the cores stall on the
#: same memory), while the codecs are compute-bound (zlib, ~10 ms a frame). On a
#: machine other work loads, one product thread beside the codecs cost the least CPU
#: (44-45 ms a frame against 57-60); on the idle 2-core machine of the benchmarks the
#: products on both cores finish sooner, the CPU spent notwithstanding: the folder of
#: benchmarks/bench_video.py (240 16-bit frames, --batch 1) took 6.19-6.41 s against
#: 6.72-6.99 s (three interleaved pairs, 46 against 43 ms of CPU a frame, the files
#: identical). Wall time is what a user waits for: none left.
CODEC_CORES = 0


class CodecPool:
    """The threads frames are decoded and encoded on; ``with`` closes them, waiting for
    the files being written and dropping the frames not started.

    Parameters
    ----------
    threads : int, optional (default :data:`CODEC_THREADS`)
    """

    def __init__(self, threads: int | None = None):
        self.threads = int(threads or CODEC_THREADS)
        self._executor: ThreadPoolExecutor | None = None

    def __enter__(self) -> "CodecPool":
        self._executor = ThreadPoolExecutor(self.threads, thread_name_prefix="bigT-codec")
        return self

    def __exit__(self, *exc) -> bool:
        # a file half written is finished (or discarded) by atomic_output: never torn
        self._executor.shutdown(wait=True, cancel_futures=True)
        return False

    @property
    def frames_in_flight(self) -> int:
        """Frames decoded ahead, or encoded behind, at most by default."""
        return FRAMES_IN_FLIGHT_PER_THREAD * self.threads

    def product_threads(self, default: int) -> int:
        """The threads the products take beside this pool: ``default`` (one per core,
        or ``config.KERNEL_THREADS``) less :data:`CODEC_CORES` when the products' count
        was not chosen by the user, at least one."""
        if config.KERNEL_THREADS is not None:
            return int(default)
        return max(1, min(int(default), (os.cpu_count() or 1) - CODEC_CORES))

    def submit(self, fn: Callable, *args) -> Future:
        if self._executor is None:
            raise RuntimeError("use CodecPool as a context manager: `with CodecPool() as pool`")
        return self._executor.submit(fn, *args)


def decoded_ahead(pool: CodecPool, source, batch: int, ahead: int | None = None,
                  read: Callable[[Path], np.ndarray] | None = None
                  ) -> Iterator[tuple[list[Path], np.ndarray]]:
    """The (files, frames) batches of ``source`` in order, each frame decoded on
    ``pool`` up to ``ahead`` frames before it is yielded.

    Parameters
    ----------
    pool : CodecPool, entered
    source : ImageSource
    batch : int, frames per batch
    ahead : int, frames decoded and not yet yielded, at most (at least one batch;
        default ``pool.frames_in_flight``)
    read : file -> frame, optional (default the float32 frame,
        ``source.read(file, np.float32)``; ``source.read_codes`` for the codes)

    Yields
    ------
    files : list of Path, k <= batch
    frames : ndarray, shape (k, H, W) or (k, H, W, 3), float32; the values of
        :func:`~bigT.compensation.realtime.image_batches`, bit for bit (or what
        ``read`` gives)
    """
    files = list(source.files)
    batch = max(1, int(batch))
    ahead = max(int(ahead or pool.frames_in_flight), batch)
    pending: collections.deque[Future] = collections.deque()
    following = iter(files)

    if read is None:
        def read(file: Path) -> np.ndarray:
            return source.read(file, np.float32)  # the codes divided in float32: one pass

    def top_up() -> None:
        while len(pending) < ahead:
            file = next(following, None)
            if file is None:
                return
            pending.append(pool.submit(read, file))

    try:
        for start in range(0, len(files), batch):
            top_up()
            count = min(batch, len(files) - start)
            frames = [pending.popleft().result() for _ in range(count)]
            top_up()  # the next frames decode while this batch is compensated
            yield files[start:start + count], np.stack(frames)
    finally:  # closed early (an error elsewhere): frames not started are dropped
        for future in pending:
            future.cancel()


@dataclass(frozen=True)
class EncodedFrame:
    """When one frame handed to :class:`EncodedBehind` was handed over and written.

    Attributes
    ----------
    handed : float, ``time.perf_counter()`` when :meth:`EncodedBehind.write` returned
    started, done : float, when its encoding began and its file was in place
    write_call : float, seconds of the :meth:`EncodedBehind.write` call that handed it
        (waits for the oldest frames included), shared by the frames of one batch
    """

    handed: float
    started: float
    done: float
    write_call: float

    @property
    def seconds(self) -> float:
        """Seconds of encoding and writing its file."""
        return self.done - self.started


class EncodedBehind:
    """``write(names, frames)`` that encodes on ``pool`` and returns at once.

    Parameters
    ----------
    pool : CodecPool, entered
    write : (names, frames) -> None
        Writes frames (k, H, W) or (k, H, W, 3) under names (an
        :meth:`~bigT.images.ImageSink.write`); called with one frame at a time on the
        pool's threads, so it must write each name independently of the others.
    behind : int, frames handed over and not yet written, at most (the oldest is waited
        for beyond; default ``pool.frames_in_flight``)

    Call :meth:`finish` after the last write: it waits for every frame and raises the
    first error, in frame order.
    """

    def __init__(self, pool: CodecPool, write: Callable[[Sequence, np.ndarray], None], *,
                 behind: int | None = None):
        self._pool, self._write = pool, write
        self.behind = max(1, int(behind or pool.frames_in_flight))
        self._pending: collections.deque[tuple[Future, int]] = collections.deque()
        self._times: list[list[float]] = []  # [handed, started, done, write_call] a frame
        self._lock = threading.Lock()  # the times of the frames written by the pool

    def write(self, names: Sequence, frames: np.ndarray) -> None:
        """Hand each frame over (waiting for the oldest while too many are pending)."""
        t = time.perf_counter()
        first = len(self._times)
        for i, (name, frame) in enumerate(zip(names, frames)):
            self._times.append([0.0, 0.0, 0.0, 0.0])
            while len(self._pending) >= self.behind:
                self._wait_oldest()
            self._pending.append((self._pool.submit(self._encode, first + i, name, frame),
                                  first + i))
        handed = time.perf_counter()
        for row in self._times[first:]:
            row[0], row[3] = handed, handed - t

    def finish(self) -> list[EncodedFrame]:
        """Wait for every frame handed over; their times, in frame order."""
        while self._pending:
            self._wait_oldest()
        with self._lock:
            return [EncodedFrame(*row) for row in self._times]

    def _wait_oldest(self) -> None:
        future, _ = self._pending.popleft()
        try:
            future.result()
        except BaseException:
            for later, _ in self._pending:  # frames not started are dropped
                later.cancel()
            self._pending.clear()
            raise

    def _encode(self, index: int, name, frame: np.ndarray) -> None:
        started = time.perf_counter()
        self._write([name], frame[None])
        done = time.perf_counter()
        with self._lock:
            self._times[index][1:3] = [started, done]


def with_encoding_times(stream: StreamReport, frames: list[EncodedFrame],
                        seconds: float) -> StreamReport:
    """``stream`` (of :func:`~bigT.compensation.realtime.run_stream`, whose writes only
    handed the frames over) with each frame's latency running to its file written, its
    service time counting its encoding instead of the hand-over, and ``seconds`` the
    run's wall time up to the last file written."""
    if len(frames) != stream.frames:  # an interrupted run: no times to mend
        return stream
    waited = np.array([f.done - f.handed for f in frames])
    own = np.array([f.seconds - f.write_call for f in frames])
    return dataclasses.replace(stream, seconds=seconds, latencies=stream.latencies + waited,
                               service=stream.service + own)


__all__ = ["CODEC_CORES", "CODEC_THREADS", "FRAMES_IN_FLIGHT_PER_THREAD", "CodecPool", "decoded_ahead", "EncodedBehind",
           "EncodedFrame", "with_encoding_times"]
