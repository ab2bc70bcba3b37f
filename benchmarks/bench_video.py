"""Real-time compensation of a video (issue #15 item 3), reported, never asserted.

A synthetic video (moving pattern, 8-bit lossless H.264 ``.mp4``) of the scene's size
is compensated through the code path of ``bigT compensate X.zarr in.mp4 -o out.mp4``
(:class:`bigT.compensation.realtime.Compensator`, :func:`run_stream`, the video source
and sink: frames decoded and encoded by ffmpeg, images in and out included) at batch 1
and batch 64, with X held in memory in float32 and float16 and streamed from disk (and
once with FFV1 ``.mkv`` in and out, a slower codec).

For each run: frames/s, latency per frame (read start -> written, queueing included;
mean, p50, p95; and read + compensate + write without the queues, the latency of a
live source paced slower than the pipeline), the
MB of X read per frame (the arrays one pass reads, divided by the batch), the effective
bandwidth (MB per frame x frames/s), the error of the projector frames against the
float32 in-memory run (before 8-bit quantisation), and the load average (the machine
is shared: numbers under load are marked). Kernel-only rows time the products alone,
and a memory copy gives the machine's bandwidth for reference.

A folder of 16-bit PNG frames (issue #30) goes through ``bigT compensate X.zarr in/ -o
out/ --batch 1`` (:class:`bigT.compensation.FileCompensation`, X in memory: the frames
decoded ahead and encoded behind on a pool of threads) and, as it was, one batch at a
time (``--serial``), beside a plain loop a user would write: read each frame (imageio,
and OpenCV's decoder for the quicker loop), multiply with scipy, write it (the same
library). The PNG files are lossless 16-bit in all; bigT writes zlib level 1, imageio
(Pillow) level 6 unless told, so the imageio loop also runs at level 1 (the fair rival),
and OpenCV writes level 1 with its own filter and strategy (:data:`PLAIN_LOOPS`).
Interleaved repeats, best of each; X loaded before the clock starts in all. With
``--folder-trees main=/work/main,branch=.`` the CLI of each checkout runs too, each in
its own process (its report's seconds: X loaded before): before and after in one run.

Issue #32 items 3 and 2 (``--realtime``, ``--uhd-X``): at full HD, ``bigT compensate
X.zarr in.mp4 -o out.mp4`` (a lossless and a CRF 18 H.264 input) at batch 1, 4 and 8
with X in memory in float32 and float16, beside each bound measured alone in the same
run: ffmpeg's decoding, its lossless encoding of the projector frames, the products
(bytes of X per frame, GB/s, against a memory copy) and the pixel passes, each with the
CPU it takes per frame (this process's and ffmpeg's), so the rate the cores allow is
read whatever the load of a shared machine. For a 4K X: one frame with X streamed from
disk, and a video with X in memory within 4 GiB (float16, and float32 if it fits) at
batch 1 and 8.

Run:  .venv/bin/python benchmarks/bench_video.py --T /tmp/bench/dense384.zarr \\
          --X /tmp/bench/X384.zarr            # the dense 384x512 corner's 4-term X
      .venv/bin/python benchmarks/bench_video.py --quick   # builds a 96x128 corner
      .venv/bin/python benchmarks/bench_video.py --realtime --X X_fullhd.zarr
      .venv/bin/python benchmarks/bench_video.py --uhd-X X_4k.zarr
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bigT  # noqa: E402
from bigT import config  # noqa: E402
from bigT.compensation import FileCompensation  # noqa: E402
from bigT.compensation.core import choose_path  # noqa: E402
from bigT.images import write_image  # noqa: E402
from bigT.compensation.realtime import Compensator, run_stream, video_batches  # noqa: E402
from bigT.compensation.video import VideoSink, VideoSource  # noqa: E402

from _results import Results, run_name  # noqa: E402


def _size(text):
    h, w = text.lower().split("x")
    return int(h), int(w)


def build_small(out: Path, size, terms=4, prune=1e-5):
    """A dense corner of ``size`` and its ``terms``-term inverse under ``out``."""
    import bigT.scenes as scenes

    T_path, X_path = out / f"corner_{size[0]}x{size[1]}.zarr", out / f"X_{size[0]}x{size[1]}.zarr"
    if not X_path.exists():
        scenes.corner(size=size, path=str(T_path), density="dense", overwrite=True,
                      preview=False, progress=False)
        bigT.stratified_inverse(str(T_path), str(X_path), terms=terms, prune=prune,
                                progress=False, overwrite=True)
    return T_path, X_path


def make_video(path: Path, shape, frames: int, fps: float = 60.0) -> None:
    """A moving pattern (a drifting sinusoid and a travelling bright bar) in [0.15, 0.6],
    8-bit, streamed to ffmpeg frame by frame (the codec follows the suffix)."""
    H, W = shape
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    with VideoSink(path, shape, fps, 8) as sink:
        for t in range(frames):
            wave = 0.3 + 0.15 * np.sin(2 * np.pi * (x / 64 + y / 96 - t / 60))
            bar = 0.15 * (np.abs(((x - 4 * t) % W) - W / 2) < W / 16)
            sink.write((wave + bar)[None])


@dataclass(frozen=True)
class Row:
    mode: str
    precision: str
    batch: int
    frames: int
    fps: float
    mean: float
    p50: float
    p95: float
    own50: float
    own95: float
    mb_per_frame: float
    gbps: float
    err: str
    load: str


def _load() -> str:
    return "/".join(f"{v:.1f}" for v in os.getloadavg())


def run_video(X, video: Path, out: Path, *, batch: int, precision: str, stream: bool,
              max_frames: int | None, ref: list | None, keep: list | None, serial=False):
    # the output's suffix is the input's: the codec (and its cost) follows it
    """One compensation of ``video`` through the CLI's pipeline; returns a Row."""
    load0 = _load()
    choice = choose_path(X, None, None, "explicit")
    # the tile cache of `bigT compensate` when X is streamed
    comp = Compensator(X, None, choice, (0, 1), precision=precision, resident=not stream,
                       cache_bytes=config.COMPENSATE_CACHE_BYTES)
    source = VideoSource(video, X.pixel_order.image_shape)
    errs = []

    def batches():
        n = 0
        for names, frames in video_batches(source, batch):
            if max_frames is not None and n >= max_frames:
                return
            n += len(frames)
            yield names, frames

    with VideoSink(out, source.info.shape, source.info.fps, 8) as sink:
        def write(names, frames):
            sink.write(frames)
            for i, f in zip(names, frames):
                if keep is not None:
                    keep.append(f.astype(np.float32))
                elif ref is not None and i < len(ref):
                    errs.append(float(np.abs(f - ref[i]).max()))

        rep = run_stream(batches(), comp, write, batch=batch, overlap=not serial)
    lat, own = rep.latency_ms(), rep.latency_ms("service")
    per = comp.residency.bytes_per_pass / min(batch, rep.frames)
    mode = (("in memory" if comp.residency.resident else "streamed")
            + (", serial" if serial else "") + f", {video.suffix[1:]}")
    err = "reference" if keep is not None else (
        f"{max(errs):.2e} ({max(errs) * 255:.2f}/255)" if errs else "n/a")
    return Row(mode, comp.residency.precision, batch, rep.frames, rep.frames_per_second,
               lat["mean"], lat["p50"], lat["p95"], own["p50"], own["p95"], per / 1e6,
               per * rep.frames_per_second / 1e9, err, f"{load0} -> {_load()}")


def kernel_rows(X, precisions, repeats=20):
    """Products alone (no I/O, no pixel reordering): ms per frame at batch 1 and 64."""
    from bigT.compensation.resident import load_resident

    rows = []
    n = X.shape[1]
    rng = np.random.default_rng(0)
    for prec in precisions:
        R = load_resident(X, prec)
        for k in (1, 64):
            V = rng.uniform(0, 1, (n, k)).astype(np.float32)
            R.matmul(V)  # compiled / warm
            ts = []
            for _ in range(repeats if k == 1 else max(3, repeats // 5)):
                t = time.perf_counter()
                R.matmul(V)
                ts.append(time.perf_counter() - t)
            med = float(np.median(ts))
            rows.append((prec, k, 1e3 * med / k, k / med, R.nbytes / k / 1e6,
                         R.nbytes / med / 1e9, _load()))
    return rows


def copy_bandwidth(mb=512, repeats=5) -> float:
    """GB/s of a large numpy copy (read + write counted): the machine's memory speed."""
    a = np.ones(mb * (1 << 20) // 8)
    b = np.empty_like(a)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        np.copyto(b, a)
        ts.append(time.perf_counter() - t)
    return 2 * a.nbytes / min(ts) / 1e9


def make_png_folder(folder: Path, shape, frames: int) -> None:
    """``frames`` 16-bit grey PNG frames of :func:`make_video`'s moving pattern."""
    H, W = shape
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    folder.mkdir(parents=True, exist_ok=True)
    for t in range(frames):
        wave = 0.3 + 0.15 * np.sin(2 * np.pi * (x / 64 + y / 96 - t / 60))
        bar = 0.15 * (np.abs(((x - 4 * t) % W) - W / 2) < W / 16)
        write_image(folder / f"frame{t:04d}.png", wave + bar, bits=16)


@dataclass(frozen=True)
class FolderRow:
    """One mode of the folder rows: its best wall time, its ratios to the plain loops
    and the mean size of the files it wrote."""

    mode: str
    frames: int
    seconds: float
    fps: float
    ratio: float  # the imageio loop's seconds over this mode's (Pillow's zlib level 6)
    ratio_level1: float  # ... over the imageio loop at zlib level 1, bigT's level
    ratio_opencv: float  # ... over the OpenCV loop (level 1, another filter and strategy)
    cpu_seconds: float
    kb_per_frame: float
    load: str


#: The plain loops: (library, its writer's options) and the zlib level each PNG is
#: written at. bigT writes level 1 (``bigT.images.PNG_COMPRESSION``, every row filtered
#: "up"); Pillow (imageio's writer) level 6 unless told, with its adaptive filters;
#: OpenCV level 1 with the "sub" filter and zlib's RLE strategy (quicker on noisy
#: frames, ~19x larger files of smooth ones). The level-1 imageio loop is the fair rival:
#: the same zlib level as bigT's; all are lossless 16-bit.
PLAIN_LOOPS = {"plain loop (imageio + scipy)": ("imageio", {}),
               "plain loop (imageio level 1 + scipy)": ("imageio", {"compress_level": 1}),
               "plain loop (OpenCV + scipy)": ("opencv", {})}
IMAGEIO_LOOP, LEVEL1_LOOP, OPENCV_LOOP = PLAIN_LOOPS


def _plain_codecs(library: str, options: dict):
    """(read, write) of 16-bit grey PNG files in ``library``: what a plain loop calls."""
    if library == "imageio":
        import imageio.v3 as iio

        return iio.imread, lambda f, a: iio.imwrite(f, a, **options)
    import cv2

    return (lambda f: cv2.imread(str(f), cv2.IMREAD_UNCHANGED),
            lambda f, a: cv2.imwrite(str(f), a))


def plain_loop(Xs, files, out: Path, library: str, options: dict | None = None) -> float:
    """Seconds of a loop that decodes, multiplies with scipy and encodes each frame
    (``Xs`` the row-major CSR X: ``Xs @ image.ravel()``)."""
    read, write = _plain_codecs(library, options or {})
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    for f in files:
        image = read(f).astype(np.float32) / np.float32(65535)
        y = np.clip(Xs @ image.ravel(), 0, 1).reshape(image.shape)
        write(out / f.name, np.rint(y * 65535).astype(np.uint16))
    return time.perf_counter() - t


def cli_compensate(tree: Path, X, folder: Path, out: Path) -> float:
    """The run's seconds (its report's: X loaded and imports done before) of ``bigT
    compensate X folder -o out --batch 1`` in its own process, with the bigT of
    ``tree`` (a checkout: the same run's before and after)."""
    import json
    import subprocess

    env = dict(os.environ, PYTHONPATH=str(tree))
    done = subprocess.run([sys.executable, "-m", "bigT.cli", "compensate", str(X.path),
                           str(folder), "-o", str(out), "--batch", "1", "--json"],
                          env=env, cwd=tree, capture_output=True, text=True, check=True)
    return float(json.loads(done.stdout.strip().splitlines()[-1])["seconds"])


def folder_rows(X, folder: Path, out: Path, repeats: int,
                trees: dict[str, Path] | None = None) -> list[FolderRow]:
    """The plain loops against `bigT compensate --batch 1` (pooled codecs, and one
    batch at a time), interleaved ``repeats`` times, best of each; with ``trees``
    (label: checkout), the CLI of each in its own process too."""
    files = sorted(folder.glob("*.png"))
    Xs = X.to_scipy().astype(np.float32)
    jobs = {"compensate --batch 1": FileCompensation(X, folder, out / "c", batch=1),
            "compensate --batch 1 --serial": FileCompensation(X, folder, out / "s", batch=1)}
    for job in jobs.values():
        job.__enter__()  # X loaded into memory once, before any clock starts
    modes = {mode: (lambda o, lib=lib, opt=opt: plain_loop(Xs, files, o, lib, opt))
             for mode, (lib, opt) in PLAIN_LOOPS.items()}
    modes["compensate --batch 1"] = (
        lambda o: jobs["compensate --batch 1"].run().stream.seconds)
    modes["compensate --batch 1 --serial"] = (
        lambda o: jobs["compensate --batch 1 --serial"].run(overlap=False).stream.seconds)
    for label, tree in (trees or {}).items():
        modes[f"CLI compensate --batch 1 ({label})"] = (
            lambda o, tree=tree: cli_compensate(tree, X, folder, o))
    best = dict.fromkeys(modes, float("inf"))
    cpu = dict.fromkeys(modes, float("inf"))
    loads, sizes = {}, {}
    try:
        for _ in range(repeats):
            for mode, run in modes.items():
                target = out / "c" if mode == "compensate --batch 1" else (
                    out / "s" if mode.endswith("--serial") else out / "other")
                shutil.rmtree(target, ignore_errors=True)
                load0, cpu0 = _load(), time.process_time() + _children_cpu()
                best[mode] = min(best[mode], run(target))
                # every thread's CPU time (a CLI's: its process's, start-up and X's
                # loading included): what the run costs a machine, whatever the load
                cpu[mode] = min(cpu[mode], time.process_time() + _children_cpu() - cpu0)
                loads[mode] = f"{load0} -> {_load()}"
                sizes[mode] = np.mean([(target / f.name).stat().st_size for f in files]) / 1e3
                print(f"  folder: {mode}: {best[mode]:.2f} s", file=sys.stderr, flush=True)
    finally:
        for job in jobs.values():
            job.__exit__(None, None, None)
    loops = [best[m] for m in PLAIN_LOOPS]
    return [FolderRow(m, len(files), s, len(files) / s, *(loop / s for loop in loops),
                      cpu[m], sizes[m], loads[m])
            for m, s in best.items()]


def _children_cpu() -> float:
    """CPU seconds of the child processes waited for (the CLI runs)."""
    usage = os.times()
    return usage.children_user + usage.children_system


def record(rows: list[Row], products: list[tuple], X, frames: int,
           folder: list[FolderRow] = ()) -> None:
    """The printed tables, handed to RESULTS.md (``_results.Results``)."""
    H, W = X.pixel_order.image_shape
    res = Results(run_name("video"), "Real-time compensation of a video",
                  "python benchmarks/bench_video.py " + " ".join(sys.argv[1:]))
    if rows:
        _record_video(res, rows, products, X, frames)
    if folder:
        res.table("folder", f"{folder[0].frames} 16-bit PNG frames of {H}x{W} in a folder: "
                  "`bigT compensate X.zarr in/ -o out/ --batch 1` (X in memory) against a "
                  "plain loop that decodes, multiplies with scipy and encodes each frame",
                  FOLDER_COLUMNS, [folder_cells(r) for r in folder],
                  note="interleaved repeats, best of each; X in memory in all, loaded "
                       "before the clock starts; zlib levels: imageio (Pillow) 6 by "
                       "default, the level-1 loop and bigT 1, OpenCV 1 (sub filter, RLE); "
                       "CPU seconds: the process's, every thread's (a loaded machine "
                       "stretches the wall time, less so these; a CLI row's include its "
                       "start-up and X's loading). On two free cores a single-threaded loop "
                       "runs at best at 1000 / its CPU ms per frame, the pooled bigT at "
                       "2000 / its own")
        pooled = next(r for r in folder if r.mode == "compensate --batch 1")
        res.value("folder:speedup", pooled.ratio, "compensate --batch 1 of a folder of 16-bit "
                  "PNG frames over the plain imageio + scipy loop")
        res.value("folder:speedup-level1", pooled.ratio_level1, "compensate --batch 1 of a "
                  "folder of 16-bit PNG frames over the plain imageio + scipy loop writing "
                  "at bigT's zlib level (1)")
    res.save()


FOLDER_COLUMNS = ["mode", "frames", "seconds (best)", "frames/s", "x the imageio loop",
                  "x the level-1 imageio loop", "x the OpenCV loop",
                  "CPU seconds (all threads)", "CPU ms per frame", "kB per frame written",
                  "load 1/5/15 min"]


def folder_cells(r: FolderRow) -> list:
    return [r.mode, r.frames, round(r.seconds, 2), round(r.fps, 1), round(r.ratio, 2),
            round(r.ratio_level1, 2), round(r.ratio_opencv, 2), round(r.cpu_seconds, 2),
            round(1e3 * r.cpu_seconds / r.frames, 1), round(r.kb_per_frame), r.load]


def print_folder(rows: list[FolderRow]) -> None:
    print()
    print(f"Folder of {rows[0].frames} 16-bit PNG frames, batch 1, X in memory:")
    print()
    print("| " + " | ".join(FOLDER_COLUMNS) + " |")
    print("|" + "---|" * len(FOLDER_COLUMNS))
    for r in rows:
        print("| " + " | ".join(str(c) for c in folder_cells(r)) + " |")
    print(flush=True)


def _record_video(res, rows, products, X, frames) -> None:
    """The video and products tables of :func:`record`."""
    H, W = X.pixel_order.image_shape
    res.table("video", f"{frames} frames of {H}x{W} through `bigT compensate X.zarr in.mp4 "
              f"-o out.mp4`'s pipeline, X {X.nnz:,} nonzeros ({X.nnz / X.shape[0]:.0f} a row)",
              ["mode", "precision", "batch", "frames", "frames/s", "latency mean ms",
               "latency p50 ms", "latency p95 ms", "without queueing p50 ms",
               "without queueing p95 ms", "MB of X per frame", "effective GB/s",
               "max error vs float32", "load 1/5/15 min"],
              [[r.mode, r.precision, r.batch, r.frames, r.fps, r.mean, r.p50, r.p95, r.own50,
                r.own95, r.mb_per_frame, r.gbps, r.err, r.load] for r in rows],
              note="latency: read start to written, queueing included; without queueing: "
                   "read + compensate + write")
    res.table("products", "the products alone (X in memory, no I/O)",
              ["precision", "batch", "ms per frame", "frames/s", "MB of X per frame", "GB/s",
               "load"], [list(p) for p in products])


# --- real time at full HD, and the 4K measurement (issue #32 items 2 and 3) -------------

#: The memory a 4K X may hold in memory (issue #32: every process under 4 GiB).
UHD_MEMORY_LIMIT = 4 << 30


def _cpu() -> tuple[float, float]:
    """(this process's CPU seconds, its waited children's: the ffmpeg decoders and
    encoders, counted once each has ended)."""
    import resource

    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, kids.ru_utime + kids.ru_stime


@dataclass(frozen=True)
class Measured:
    """One timed run: what it did, its rate and the CPU it took per frame."""

    what: str
    frames: int
    seconds: float
    cpu_ms: float
    ffmpeg_cpu_ms: float
    p50: float = float("nan")
    p95: float = float("nan")
    own50: float = float("nan")
    mb_per_frame: float = float("nan")
    gbps: float = float("nan")
    load: str = ""

    @property
    def fps(self) -> float:
        return self.frames / self.seconds

    @property
    def cores_fps(self) -> float:
        """Frames/s the machine's cores give at this CPU cost per frame (the rate of an
        unloaded machine, where CPU is what binds)."""
        total = self.cpu_ms + self.ffmpeg_cpu_ms
        return (os.cpu_count() or 1) * 1e3 / total if total > 0 else float("inf")

    def cells(self) -> list:
        return [self.what, self.frames, self.fps, self.cpu_ms, self.ffmpeg_cpu_ms,
                self.cores_fps, self.p50, self.p95, self.own50, self.mb_per_frame, self.gbps,
                self.load]


MEASURED_COLUMNS = ["run", "frames", "frames/s", "CPU ms/frame (bigT)",
                    "CPU ms/frame (ffmpeg)", "frames/s the cores allow", "latency p50 ms",
                    "latency p95 ms", "without queueing p50 ms", "MB of X per frame", "GB/s of X", "load 1/5/15 min"]


def _timed(what: str, run, frames: int, **extra) -> Measured:
    load0, c0, t0 = _load(), _cpu(), time.perf_counter()
    run()
    seconds, c1 = time.perf_counter() - t0, _cpu()
    return Measured(what, frames, seconds, 1e3 * (c1[0] - c0[0]) / frames,
                    1e3 * (c1[1] - c0[1]) / frames, load=f"{load0} -> {_load()}", **extra)


def video_for(out: Path, shape, frames: int, lossy: bool = False) -> Path:
    """The moving pattern of :func:`make_video` at ``shape`` (cached under ``out``):
    lossless H.264, or (``lossy``) re-encoded as a camera or an editor would give it
    (H.264 at CRF 18, yuv420p)."""
    path = out / f"pattern_{shape[0]}x{shape[1]}_{frames}{'_crf18' if lossy else ''}.mp4"
    if path.exists():
        return path
    tmp = path.with_suffix(".part.mp4")
    if lossy:
        import subprocess

        import imageio_ffmpeg

        subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-i",
                        str(video_for(out, shape, frames)), "-c:v", "libx264", "-crf", "18",
                        "-pix_fmt", "yuv420p", str(tmp)], check=True)
    else:
        make_video(tmp, shape, frames, fps=30.0)
    tmp.rename(path)
    return path


def codec_bounds(videos: dict, output: Path, shape, frames: int) -> list[Measured]:
    """ffmpeg alone: decoding each of ``videos`` ({label: path}) to codes, and encoding
    the frames of ``output`` (a compensation's projector frames, decoded first) to
    lossless H.264 (.mp4, as ``compensate`` writes it), with no product between."""
    rows = []
    for label, video in videos.items():
        source = VideoSource(video, shape)
        rows.append(_timed(f"decode alone ({label} H.264 -> codes)",
                           lambda: sum(1 for _ in source.codes()), frames))
    codes = [np.array(c) for c in VideoSource(output, shape).codes()]
    with tempfile.TemporaryDirectory() as tmp:
        def encode():
            with VideoSink(Path(tmp) / "enc.mp4", shape, 30.0, 8) as sink:
                for c in codes:
                    sink.write_codes(c)

        rows.append(_timed("encode alone (projector codes -> lossless H.264)", encode,
                           len(codes)))
    return rows


def product_bounds(X, precisions, batches, repeats: int = 5) -> list[Measured]:
    """The products alone (X in memory, no pixels reordered, no I/O): best of
    ``repeats``; the bytes of X read per frame and the GB/s they make."""
    from bigT.compensation.resident import load_resident

    rows = []
    rng = np.random.default_rng(0)
    for prec in precisions:
        R = load_resident(X, prec, memory_limit=UHD_MEMORY_LIMIT * 2)
        for k in batches:
            V = rng.uniform(0, 1, (X.shape[1], k)).astype(np.float32)
            R.matmul(V)  # compiled (or loaded from numba's cache)
            best = min((_timed("", lambda: R.matmul(V), k) for _ in range(repeats)),
                       key=lambda m: m.seconds)
            per = R.nbytes / k
            rows.append(Measured(f"product alone, X {prec} ({R.nbytes / 1e6:.0f} MB), batch {k}",
                                 k, best.seconds, best.cpu_ms, 0.0, mb_per_frame=per / 1e6,
                                 gbps=per * k / best.seconds / 1e9, load=best.load))
        R = None  # the next precision loads into the memory this one held
    return rows


def pixel_bounds(X, batch: int, repeats: int = 5) -> list[Measured]:
    """The codes in and out of a batch alone (gather + scatter, no product)."""
    from bigT.compensation.codes import gather_codes, scatter_codes

    order = X.pixel_order
    perm = order.permutation.astype(np.int32)
    codes = np.random.default_rng(1).integers(0, 256, (batch, *order.frame_shape), np.uint8)
    B = gather_codes(codes, perm, 2)

    def both():
        gather_codes(codes, perm, 2)
        scatter_codes(B, perm, (0, 1), order.frame_shape, np.uint8, 2)

    both()
    best = min((_timed("", both, batch) for _ in range(repeats)), key=lambda m: m.seconds)
    return [Measured(f"codes -> batch -> codes alone (gather + scatter), batch {batch}", batch,
                     best.seconds, best.cpu_ms, 0.0, load=best.load)]


def compensate_runs(X_path, video: Path, out: Path, batches, precisions, *, repeats: int,
                    memory_limit=None, label: str = "") -> list[Measured]:
    """``bigT compensate X in.mp4 -o out.mp4 --batch b --precision p`` as the CLI runs
    it (FileCompensation), X loaded before the clock starts; interleaved repeats, best
    of each. The output is ``out/out.mp4``."""
    from bigT.compensation.files import FileCompensation

    best: dict = {}
    for _ in range(repeats):
        for prec in precisions:
            for b in batches:
                job = FileCompensation(X_path, video, out / "out.mp4", batch=b, precision=prec,
                                       memory_limit=memory_limit)
                with job:
                    codes = job.takes_codes
                    res = job.compensator.residency
                    rep: list = []
                    m = _timed("", lambda: rep.append(job.run()), 1)
                stream = rep[0].stream
                n = stream.frames
                lat = stream.latency_ms()
                per = res.bytes_per_pass / b
                row = Measured(f"compensate {label}in.mp4 -o out.mp4, X {prec} "
                               f"{'in memory' if res.resident else 'streamed'}, batch {b}"
                               + ("" if codes else " (float frames)"), n, m.seconds,
                               m.cpu_ms / n, m.ffmpeg_cpu_ms / n, lat["p50"], lat["p95"],
                               stream.latency_ms("service")["p50"], per / 1e6, per * n / m.seconds / 1e9, m.load)
                key = (prec, b)
                if key not in best or row.fps > best[key].fps:
                    best[key] = row
                print(f"  {row.what}: {row.fps:.1f} frames/s", file=sys.stderr, flush=True)
    return list(best.values())


def uhd_runs(X_path, out: Path, frames: int, *, repeats: int = 1) -> list[Measured]:
    """Issue #32 item 2 on the X at ``X_path`` (4K: 3840x2160): one frame with X
    streamed from disk (the first read, then again with the tiles in the page cache),
    and a video with X held in memory (float16, and float32 when it fits
    :data:`UHD_MEMORY_LIMIT`) at batch 1 and 8."""
    from bigT.compensation.resident import load_bytes_needed

    X = bigT.open(X_path)
    shape = X.pixel_order.image_shape
    choice = choose_path(X, None, None, "explicit")
    y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
    frame = (0.3 + 0.15 * np.sin(2 * np.pi * (x / 64 + y / 96)))[None]
    rows = []
    for label in ("first call: kernels loaded, page cache as found", "again: page cache warm"):
        comp = Compensator(X, None, choice, (0, 1), resident=False, cache_bytes=0)
        row = _timed(f"one frame, X streamed from disk ({label})", lambda: comp(frame), 1)
        rows.append(dataclasses.replace(row, mb_per_frame=comp.residency.bytes_per_pass / 1e6,
                                        gbps=comp.residency.bytes_per_pass / row.seconds / 1e9))
    video = video_for(out, shape, frames)
    precisions = [p for p in ("float16", "float32")
                  if load_bytes_needed(X, p) <= UHD_MEMORY_LIMIT]
    print(f"# {X_path}: {shape[0]}x{shape[1]}, nnz {X.nnz:,}; held in memory within "
          f"{UHD_MEMORY_LIMIT >> 30} GiB: {precisions or 'neither precision'}", flush=True)
    if precisions:
        rows += compensate_runs(X_path, video, out, (1, 8), precisions, repeats=repeats,
                                memory_limit=UHD_MEMORY_LIMIT)
    return rows


def print_measured(title: str, rows: list[Measured]) -> None:
    print()
    print(title)
    print()
    print("| " + " | ".join(MEASURED_COLUMNS) + " |")
    print("|" + "---|" * len(MEASURED_COLUMNS))
    for r in rows:
        cells = [c if isinstance(c, str) else f"{c:.1f}" if isinstance(c, float) else str(c)
                 for c in r.cells()]
        print("| " + " | ".join(cells) + " |")
    print(flush=True)


def realtime_main(args) -> None:
    """``--realtime`` and ``--uhd-X``: the tables of issue #32 items 3 and 2."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = Results(run_name("video_realtime"), "Real-time compensation: full HD and 4K",
                  "python benchmarks/bench_video.py " + " ".join(sys.argv[1:]))
    if args.realtime:
        X = bigT.open(args.X)
        shape = X.pixel_order.image_shape
        frames = args.frames or 240
        video, lossy = video_for(out, shape, frames), video_for(out, shape, frames, lossy=True)
        head = (f"{shape[0]}x{shape[1]} X {args.X}: nnz {X.nnz:,} ({X.nnz / X.shape[0]:.1f} a "
                f"row), {bigT.storage.disk_bytes(X.path) / 1e6:.0f} MB on disk; {frames} "
                f"frames; {os.cpu_count()} cores; memory copy {copy_bandwidth():.1f} GB/s "
                "(read + write)")
        print("# " + head, flush=True)
        runs = compensate_runs(args.X, lossy, out, (8,), ("float32", "float16"),
                               repeats=args.repeats, label="(H.264 CRF 18) ")
        batches = tuple(int(b) for b in args.batches.split(","))
        runs += compensate_runs(args.X, video, out, batches, ("float32", "float16"),
                                repeats=args.repeats, label="(lossless H.264) ")
        print_measured("compensate (decode, products and encode together):", runs)
        bounds = codec_bounds({"lossless": video, "CRF 18": lossy}, out / "out.mp4", shape,
                              frames)
        bounds += product_bounds(X, ("float32", "float16"), (1, 8))
        bounds += pixel_bounds(X, 8)
        print_measured("Bounds (each alone):", bounds)
        res.table("bounds", "each stage alone: " + head, MEASURED_COLUMNS,
                  [r.cells() for r in bounds],
                  note="CPU ms/frame: this process's CPU seconds (all threads) and ffmpeg's "
                       "(the decoder's or encoder's process) per frame; frames/s the cores "
                       "allow: cores x 1000 / the two together, the rate where CPU binds")
        res.table("compensate", "`bigT compensate X.zarr in.mp4 -o out.mp4`: " + head,
                  MEASURED_COLUMNS, [r.cells() for r in runs],
                  note="interleaved repeats, best of each; X loaded before the clock starts")
    if args.uhd_X:
        import resource

        rows = uhd_runs(args.uhd_X, out, args.uhd_frames, repeats=args.repeats)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB
        h, w = bigT.open(args.uhd_X).pixel_order.image_shape
        print_measured(f"{h}x{w}: one frame streamed, a video with X in memory (peak RSS "
                       f"of this process {peak:.2f} GiB):", rows)
        res.table("uhd", f"compensation with X {args.uhd_X} (peak RSS of the process "
                  f"{peak:.2f} GiB)", MEASURED_COLUMNS, [r.cells() for r in rows])
    res.save()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--T", help="X's transport store (named in the header, its shape checked; "
                    "default: the one built with X)")
    ap.add_argument("--X", help="inverse store (default: build a 4-term one)")
    ap.add_argument("--quick", action="store_true", help="96x128 scene, 120 frames")
    ap.add_argument("--size", default="384x512", help="scene built when no --X (HxW)")
    ap.add_argument("--frames", type=int, default=None, help="frames of the video (240)")
    ap.add_argument("--streamed-frames", type=int, default=64,
                    help="frames compensated with X streamed (it is slow)")
    ap.add_argument("--out", default="bench-out/video", help="where built stores go")
    ap.add_argument("--folder-frames", type=int, default=None,
                    help="16-bit PNG frames of the folder rows (240; 60 with --quick; 0: none)")
    ap.add_argument("--folder-repeats", type=int, default=3,
                    help="interleaved repeats of the folder rows (best of)")
    ap.add_argument("--folder-only", action="store_true",
                    help="only the folder rows (no video, no products)")
    ap.add_argument("--folder-trees", default="",
                    help="LABEL=CHECKOUT,... : the folder rows also run `bigT compensate` "
                         "of each checkout in its own process (before and after in one run)")
    ap.add_argument("--realtime", action="store_true",
                    help="with --X: `compensate in.mp4 -o out.mp4` at batch 1, 4, 8 in float32 "
                         "and float16, and each bound alone (decode, encode, the products, "
                         "the pixel passes, a memory copy): issue #32 item 3")
    ap.add_argument("--uhd-X", help="an X store (4K) to measure one frame streamed from disk "
                    "and a video with X in memory at batch 1 and 8: issue #32 item 2")
    ap.add_argument("--batches", default="1,4,8",
                    help="batch sizes of the --realtime runs of the lossless video")
    ap.add_argument("--uhd-frames", type=int, default=32, help="frames of the --uhd-X video")
    ap.add_argument("--repeats", type=int, default=2,
                    help="interleaved repeats of the --realtime and --uhd-X runs (best of)")
    args = ap.parse_args()
    if args.realtime or args.uhd_X:
        if args.realtime and not args.X:
            sys.exit("bench_video: --realtime needs --X")
        realtime_main(args)
        return

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.X is None:
        size = (96, 128) if args.quick else _size(args.size)
        t_path, x_path = build_small(out, size)
        args.T = args.T or str(t_path)
    else:
        x_path = Path(args.X)
    X = bigT.open(x_path)
    shape = X.pixel_order.image_shape
    if args.T is not None:
        T = bigT.open(args.T)
        if tuple(T.shape) != tuple(X.shape):
            sys.exit(f"bench_video: T {args.T} is {T.shape} but X {x_path} is {X.shape}")
        print(f"# T {args.T}: nnz {T.nnz:,} ({T.nnz / T.shape[0]:.0f}/row)")
    frames = args.frames or (120 if args.quick else 240)
    tmp = Path(tempfile.mkdtemp(prefix="bench_video_"))
    try:
        folder_frames = (args.folder_frames if args.folder_frames is not None
                         else 60 if args.quick else 240)
        folder = []
        if folder_frames:
            make_png_folder(tmp / "frames", shape, folder_frames)
            trees = dict(item.split("=", 1) for item in args.folder_trees.split(",") if item)
            folder = folder_rows(X, tmp / "frames", tmp / "folder-out", args.folder_repeats,
                                 {label: Path(tree).resolve() for label, tree in trees.items()})
            print_folder(folder)
        if args.folder_only:
            record([], [], X, frames, folder)
            return
        t = time.perf_counter()
        make_video(tmp / "in.mp4", shape, frames)
        make_video(tmp / "in.mkv", shape, frames)
        print(f"# video: {frames} frames {shape[0]}x{shape[1]}, 8-bit, .mp4 (H.264 qp 0) and "
              f".mkv (FFV1), written in "
              f"{time.perf_counter() - t:.1f} s; X {x_path}: nnz {X.nnz:,} "
              f"({X.nnz / X.shape[0]:.0f}/row); {os.cpu_count()} cores; memory copy "
              f"{copy_bandwidth():.1f} GB/s", flush=True)
        # warm-up: compile (or load) the kernels and fill the page cache
        run_video(X, tmp / "in.mp4", tmp / "w.mp4", batch=1, precision="float32",
                  stream=False, max_frames=4, ref=None, keep=None)
        run_video(X, tmp / "in.mp4", tmp / "w.mp4", batch=4, precision="float16",
                  stream=False, max_frames=8, ref=None, keep=None)
        ref: list = []
        rows = [run_video(X, tmp / "in.mp4", tmp / "o.mp4", batch=1, precision="float32",
                          stream=False, max_frames=None, ref=None, keep=ref)]
        plan = [(1, "float32", False, None, True, "mp4"), (1, "float16", False, None, False, "mp4"),
                (64, "float32", False, None, False, "mp4"),
                (64, "float16", False, None, False, "mp4"),
                (1, "float32", False, None, False, "mkv"),
                (64, "float32", False, None, False, "mkv"),
                (1, "float32", True, args.streamed_frames, False, "mp4"),
                (64, "float32", True, max(args.streamed_frames, 64), False, "mp4")]
        for batch, prec, stream, limit, serial, ext in plan:
            rows.append(run_video(X, tmp / f"in.{ext}", tmp / f"o.{ext}", batch=batch,
                                  precision=prec, stream=stream, max_frames=limit, ref=ref,
                                  keep=None, serial=serial))
            print(f"  done: {rows[-1]}", file=sys.stderr, flush=True)
        print()
        print("| mode | precision | batch | frames | frames/s | latency mean / p50 / p95 ms "
              "| without queueing p50 / p95 ms | MB of X per frame | effective GB/s "
              "| max error vs float32 | load 1/5/15 min |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r.mode} | {r.precision} | {r.batch} | {r.frames} | {r.fps:.1f} | "
                  f"{r.mean:.1f} / {r.p50:.1f} / {r.p95:.1f} | {r.own50:.1f} / {r.own95:.1f} | "
                  f"{r.mb_per_frame:.1f} | "
                  f"{r.gbps:.2f} | {r.err} | {r.load} |")
        print()
        print("Products alone (X in memory, no I/O):")
        print()
        print("| precision | batch | ms per frame | frames/s | MB of X per frame | GB/s | load |")
        print("|---|---|---|---|---|---|---|")
        products = kernel_rows(X, ("float32", "float16"))
        for prec, k, ms, fps, mb, gbps, load in products:
            print(f"| {prec} | {k} | {ms:.2f} | {fps:.0f} | {mb:.1f} | {gbps:.2f} | {load} |")
        record(rows, products, X, frames, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
