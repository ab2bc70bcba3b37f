"""``bigT compensate``, ``bigT relight`` and ``bigT bounces``.

Images go in and come out in the same form: one file -> one file, a folder of frames ->
a folder with the same names (or a video file), a video -> a video. Folders and videos
are read, processed and written one batch of frames at a time, so the frames never
need to fit in memory; X is held in memory when it fits ``--memory-limit`` and streamed
from disk tile row by tile row otherwise (:mod:`bigT.compensation.realtime`).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from .. import config
from ..errors import ImageError
from ..sizes import format_size
from ._argtypes import clip_range, integer, memory_size, number
from ._options import add_progress, add_scheduler, add_size, deprecated

#: Largest K of ``bigT bounces``. Each bounce costs one streamed pass over X, one
#: (H, W) float64 image held in memory and one file; the remainder T l - sum b_k holds
#: all light beyond K, so a small K loses nothing. 64 is far past any useful K (the
#: paper separates 4-5; bounce k decays like rho^k, and rho^64 < 1e-6 for rho < 0.8)
#: while keeping a mistyped K (100000: 10 GB and 100,000 files) from running away.
MAX_BOUNCES = 64


def register(sub) -> None:
    p = sub.add_parser(
        "compensate", help="projector inputs that make the camera see the desired images",
        description="l_in = clip(X l_desired) (paper eqs. 44-45) for an image, a folder of "
        "frames or a video, batch by batch: X held in memory when it fits --resident-limit, "
        "else streamed from disk one tile row at a time against each batch; or the same "
        "polynomial applied matrix-free with T (--path matrix-free / auto). Reports "
        "frames/s and the latency per frame.")
    p.add_argument("X", help="inverse store (X.zarr); '-' for none (matrix-free path only)")
    p.add_argument("desired", help="desired camera image (png/tif/npy), a folder of frames, "
                   "or a video (mp4/mov/m4v/mkv/avi, read frame by frame)")
    p.add_argument("-o", "--output", required=True,
                   help="projector input: an image file, a folder (for a folder input) or a "
                   "video file (for a video or a folder input; .mkv/.avi: FFV1, .mp4/.mov: "
                   "H.264, both lossless)")
    p.add_argument("--simulate", metavar="T.zarr",
                   help="also compute and write what the camera sees (T l_in), with error, "
                   "fluctuation, a side-by-side PNG and a scan-line plot")
    p.add_argument("--clip", type=clip_range, default="0,1",
                   help="projector range LO,HI ('0,' clips below only, as the paper's f_+; "
                   "'none' for no clipping); default 0,1")
    p.add_argument("--batch", type=integer(1), default=config.DEFAULT_BATCH,
                   help=f"frames per pass over the matrix (default {config.DEFAULT_BATCH})")
    p.add_argument("--path", choices=("explicit", "matrix-free", "auto"), default="auto",
                   help="explicit X, matrix-free series with T, or the cheaper (default auto)")
    p.add_argument("--matrix-free", dest="matrix_free", metavar="T.zarr",
                   help="transport for the matrix-free path (default: the --simulate store)")
    p.add_argument("--terms", type=integer(0), default=None,
                   help="series terms n of the matrix-free path (default: X's, else "
                   f"{config.DEFAULT_COMPENSATION_TERMS})")
    p.add_argument("--bits", type=int, choices=(8, 16), default=None,
                   help="PNG bit depth of the outputs (default: that of each input PNG)")
    add_size(p, "--cache-size", dest="cache_bytes", default=config.COMPENSATE_CACHE_BYTES,
             help="decoded matrix tiles kept between batches", zero="re-read every pass")
    p.add_argument("--cache-mb", dest="cache_bytes", type=integer(0), help=argparse.SUPPRESS,
                   action=deprecated("--cache-size", lambda mib: mib << 20, format_size))
    add_scheduler(p)
    p.add_argument("--resident-limit", dest="memory_limit", type=memory_size, default=None,
                   metavar="SIZE", help="hold X in memory when it needs at most SIZE (e.g. "
                   "2GiB), else stream it from disk tile row by tile row (default "
                   f"{100 * config.COMPENSATE_RESIDENT_FRACTION:.0f}%% of the memory available "
                   "when the command starts)")
    p.add_argument("--memory-limit", dest="memory_limit", type=memory_size,
                   help=argparse.SUPPRESS, action=deprecated("--resident-limit",
                                                             show=format_size))
    p.add_argument("--stream", action="store_true",
                   help="stream X from disk tile row by tile row even when it fits in memory")
    p.add_argument("--precision", choices=("float32", "float16"), default="float32",
                   help="values of X held in memory: float32 (6 bytes per entry with 16-bit "
                   "column indices) or float16 (4 bytes: less memory traffic, relative error "
                   "<= 2^-11 per entry); default float32")
    p.add_argument("--serial", action="store_true",
                   help="read, compensate and write one batch at a time (no reader and "
                   "writer threads beside the products)")
    p.add_argument("--fps", type=number(0, lo_open=True), default=None,
                   help="frames per second of a video written from a folder of frames "
                   "(default 30; a video input keeps its own)")
    add_progress(p)
    p.set_defaults(func=run_compensate)

    p = sub.add_parser("relight", help="what the camera sees for projector images: T l",
                       description="Forward transport T l_in, streamed from disk.")
    p.add_argument("T", help="transport store (T.zarr)")
    p.add_argument("input", help="projector image or folder of frames")
    p.add_argument("-o", "--output", required=True, help="output image file or folder")
    p.add_argument("--batch", type=integer(1), default=config.DEFAULT_BATCH,
                   help=f"frames per pass over T (default {config.DEFAULT_BATCH})")
    p.add_argument("--bits", type=int, choices=(8, 16), default=None,
                   help="PNG bit depth of the outputs (default: that of each input PNG)")
    add_scheduler(p)
    add_progress(p)
    p.set_defaults(func=run_relight)

    p = sub.add_parser("bounces", help="split the camera image T l into light bounces",
                       description="Seitz-style bounce separation: F_ii = 1/X_ii (paper eq. "
                       "33), A = I - F X, b_k = A^k F l for k = 0 (direct light) to K, plus "
                       "the remainder T l - sum b_k: the light of bounces beyond K, less what "
                       "X lacks of the exact inverse (its truncated series and pruned "
                       "entries), so it can be negative when X is inexact. "
                       "Each part's share is its sum over the pixels divided by the sum of T l "
                       "(the share of the total light; the shares add up to 100%%), as "
                       "`bigT scene` reports the bounces of a white image.")
    p.add_argument("T", help="transport store (T.zarr)")
    p.add_argument("X", help="inverse store (X.zarr), as exact as possible")
    p.add_argument("input", help="projector image l (png/tif/npy)")
    p.add_argument("--bounces", type=integer(0, MAX_BOUNCES), default=4,
                   help=f"K, the last bounce kept, 0 to {MAX_BOUNCES} (default 4)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--format", choices=("tif", "npy", "png"), default="tif",
                   help="image format of the parts (tif/npy keep floats; default tif)")
    add_progress(p)
    p.set_defaults(func=run_bounces)


# --- helpers ----------------------------------------------------------------------------

def _sibling(path: Path, tag: str, suffix: str | None = None) -> Path:
    """``out.png`` -> ``out_<tag>.png`` (``suffix`` to change it); ``dir`` -> ``dir_<tag>``."""
    if path.suffix:
        return path.with_name(f"{path.stem}_{tag}{suffix or path.suffix}")
    return path.with_name(f"{path.name}_{tag}{suffix or ''}")


def _image_shape(store):
    order = getattr(store, "pixel_order", None)
    return None if order is None else order.image_shape


def _describe(store, name):
    return (f"{name} {store.path}: {store.shape[0]:,} x {store.shape[1]:,}, nnz {store.nnz:,} "
            f"({store.nnz / max(store.shape[0], 1):.0f}/row), {store.grid[0]} tile rows")


# --- compensate -------------------------------------------------------------------------

def run_compensate(args) -> int:
    from ..compensation import choose_path
    from ..compensation.video import is_video_file
    from ..storage import as_store

    X = None if args.X == "-" else as_store(args.X, "X")
    S = None if args.simulate is None else as_store(args.simulate, "T")
    Tm = as_store(args.matrix_free, "T") if args.matrix_free else S
    choice = choose_path(X, Tm if args.path != "explicit" else None, args.terms, args.path)
    store = X if choice.path == "explicit" else Tm
    shape = _image_shape(store)
    for other, name in ((X, "X"), (Tm, "T"), (S, "T (--simulate)")):
        if other is not None and shape is not None and _image_shape(other) not in (None, shape):
            raise ImageError(f"{name} maps images of shape {_image_shape(other)} but the "
                             f"compensation store maps {shape}", other.path)

    if args.simulate is None:
        return _run_stream(args, X, Tm, choice, shape)
    if is_video_file(args.desired):
        raise ImageError("--simulate takes an image or a folder of frames, not a video",
                         args.desired)
    return _run_simulate(args, X, S, Tm, choice, shape)


def _run_simulate(args, X, S, Tm, choice, shape) -> int:
    """compensate --simulate: :func:`bigT.compensation.simulate_batches` over the frames,
    its report and figures printed."""
    from ..compensation import simulate_batches, simulation_figures
    from ..images import ImageSink, ImageSource
    from ..progress import progress_bar

    source = ImageSource(args.desired, shape)
    out_path = Path(args.output)
    sink = ImageSink(out_path, source, bits=args.bits)
    seen_sink = ImageSink(_sibling(out_path, "seen"), source, bits=args.bits)
    print(f"bigT compensate: {len(source)} frame(s) from {args.desired}"
          + (f", image {shape[0]}x{shape[1]}" if shape else ""))
    shown = []
    for st, name in ((X, "X"), (Tm if choice.path == "matrix-free" else None, "T"), (S, "T")):
        if st is not None and all(st is not o for o in shown):
            print("  " + _describe(st, name))
            shown.append(st)
    _print_path(choice)

    t0 = time.perf_counter()
    with progress_bar(progress=args.progress, total=len(source), desc="compensate",
                      unit="frame", leave=True) as bar:
        def write(files, projector, seen):
            sink.write(files, projector)
            seen_sink.write(files, seen)
            bar.update(len(files))

        report = simulate_batches(
            source.batches(args.batch), X, S, clip=args.clip, path=choice.path,
            matrix_free=Tm, terms=choice.terms, cache_bytes=args.cache_bytes,
            scheduler=args.scheduler, progress=args.progress, on_batch=write)
    elapsed = time.perf_counter() - t0

    print(f"  {report.frames} frame(s) in {report.seconds:.2f} s of products "
          f"({report.frames_per_second:.1f} frames/s, batch {args.batch}); {elapsed:.2f} s "
          "in all (the simulation's passes over T included)")
    print(f"  wrote projector input -> {sink.path}")
    print(f"  simulated camera (T l_in) -> {seen_sink.path}")
    for line in report.describe().splitlines():
        print("  " + line)
    tag = f" (frame {report.first.name})" if source.is_folder else ""
    pic, plot = simulation_figures(report, _sibling(out_path, "compare", ".png"),
                                   _sibling(out_path, "scanline", ".png"), tag=tag)
    print(f"  figures -> {pic}, {plot}")
    return 0


def _print_path(choice) -> None:
    print(f"  path: {choice.path}" + (f" ({choice.terms} terms)" if choice.terms is not None
                                      else "") + f" -- {choice.reason}")


def _run_stream(args, X, Tm, choice, shape) -> int:
    """compensate without --simulate: frames streamed through
    :func:`bigT.compensation.realtime.run_stream`, X in memory when it fits."""
    import sys

    from ..schedule.stream import scheduler_runner
    from ..compensation.realtime import Compensator, image_batches, run_stream, video_batches
    from ..compensation.simulate import clipped_summary
    from ..compensation.video import VideoSource, is_video_file
    from ..images import ImageSource
    from ..progress import progress_bar

    video_in = is_video_file(args.desired)
    source = VideoSource(args.desired, shape) if video_in else ImageSource(args.desired, shape)
    if not video_in and source.is_folder:
        check_frame_shapes(source.files, shape)  # a bad frame is found before writing any
    out_path = Path(args.output)
    video_out = video_in or (source.is_folder and is_video_file(out_path))
    frames_total = len(source) or None
    count = (f"~{frames_total}" if video_in else frames_total) if frames_total else "the"
    print(f"bigT compensate: {count} frame(s) from {args.desired}"
          + (f", image {shape[0]}x{shape[1]}" if shape else "")
          + (f", video {source.info.codec} {source.info.pix_fmt} at {source.info.fps:g} "
             "frames/s" if video_in else ""))
    for st, name in ((X, "X"), (Tm if choice.path == "matrix-free" else None, "T")):
        if st is not None:
            print("  " + _describe(st, name))
    _print_path(choice)
    output = _Output(args, source, out_path, video_in, video_out)  # checked before X is read
    with scheduler_runner(args.scheduler) as runner:
        if runner is not None:
            print(f"  running on {runner.describe()}")
        comp = Compensator(X, Tm, choice, args.clip, memory_limit=args.memory_limit,
                           precision=args.precision,
                           resident=not args.stream and args.scheduler is None,
                           cache_bytes=(config.COMPENSATE_CACHE_BYTES if args.cache_bytes is None
                                        else args.cache_bytes), runner=runner)
        if not args.quiet:
            per_pass = min(args.batch, frames_total or args.batch)
            print(f"bigT compensate: {comp.residency.describe(per_pass)}", file=sys.stderr)
        batches = (video_batches(source, args.batch) if video_in
                   else image_batches(source, args.batch))
        with progress_bar(progress=args.progress, total=frames_total, desc="compensate",
                          unit="frame", leave=True) as bar, \
                output as write:
            stream = run_stream(batches, comp, write, batch=args.batch,
                                overlap=not args.serial, on_batch=bar.update)
    report = comp.report
    print(f"  {stream.frames} frame(s) in {stream.compute_seconds:.2f} s of products "
          f"({stream.frames / max(stream.compute_seconds, 1e-9):.1f} frames/s, batch "
          f"{args.batch}); {stream.seconds:.2f} s in all")
    print("  " + stream.summary(comp.residency))
    if args.clip is not None:
        print("  " + clipped_summary(report.clipped_low, report.clipped_high, report.pixels,
                                     args.clip))
    print(f"  wrote projector input -> {out_path if video_out else _sink_path(out_path, source)}")
    return 0


def _sink_path(out_path: Path, source) -> Path:
    if not source.is_folder and out_path.is_dir():
        return out_path / source.path.name
    return out_path


class _Output:
    """The writer of ``_run_stream``: ``write(names, frames)`` into a video (whole or
    nothing) or images (ImageSink). Checked when made (before X is loaded), opened
    only after every input check passed."""

    def __init__(self, args, source, out_path, video_in, video_out):
        from ..compensation.video import DEFAULT_FPS, VideoSink
        from ..images import is_image_file

        self.args, self.source, self.out_path = args, source, out_path
        self._video = None
        if video_out:
            fps = source.info.fps if video_in else (args.fps or DEFAULT_FPS)
            bits = args.bits or (source.info.bits if video_in else 8)
            shape = source.info.shape if video_in else _frame_shape(source)
            self._video = VideoSink(out_path, shape, fps, bits)
        elif source.is_folder:
            if out_path.exists() and not out_path.is_dir():
                raise ImageError("the input is a folder, so the output must be a folder (or "
                                 "a video) too", out_path)
        elif not out_path.is_dir() and not is_image_file(out_path):
            raise ImageError(f"unknown output format {out_path.suffix!r} (an image: .png, "
                             ".tif, .tiff, .npy)", out_path)

    def __enter__(self):
        from ..images import ImageSink

        if self._video is not None:
            video = self._video.__enter__()
            return lambda names, frames: video.write(frames)
        return ImageSink(self.out_path, self.source, bits=self.args.bits).write

    def __exit__(self, *exc):
        if self._video is not None:
            return self._video.__exit__(*exc)
        return False


def _frame_shape(source):
    """(H, W) of a folder's frames: the store's, else the first frame's."""
    from ..images import read_image

    return source.shape or read_image(source.files[0]).shape


def check_frame_shapes(files, shape) -> None:
    """Every frame of a folder has the transport's (H, W): read from the headers, so a
    folder with one bad frame is refused before anything is written."""
    if shape is None:
        return
    import imageio.v3 as iio

    from ..images import read_image

    for f in files:
        try:
            found = (np.load(f, mmap_mode="r", allow_pickle=False).shape
                     if f.suffix.lower() == ".npy" else iio.improps(f).shape)
        except Exception:  # unreadable: read_image says why, naming the file
            found = None
        if (found is None or len(found) not in (2, 3) or tuple(found[:2]) != tuple(shape)
                or found[2:] not in ((), (1,))):
            read_image(f, shape)  # raises the one-line ImageError naming the file


# --- relight ----------------------------------------------------------------------------

def run_relight(args) -> int:
    from ..compensation import relight
    from ..schedule.stream import scheduler_runner
    from ..storage import as_store
    from ..images import ImageSink, ImageSource

    T = as_store(args.T, "T")
    source = ImageSource(args.input, _image_shape(T))
    sink = ImageSink(args.output, source, bits=args.bits)
    print(f"bigT relight: {len(source)} frame(s) from {args.input}")
    print("  " + _describe(T, "T"))
    above = pixels = 0
    t0 = time.perf_counter()
    with scheduler_runner(args.scheduler) as runner:
        if runner is not None:
            print(f"  running on {runner.describe()}")
        for files, frames in source.batches(args.batch):
            seen = relight(T, frames, batch=args.batch, progress=args.progress,
                           scheduler=runner)
            above += int(np.count_nonzero(seen > 1))
            pixels += seen.size
            sink.write(files, seen)
    dt = time.perf_counter() - t0
    print(f"  {len(source)} frame(s) in {dt:.2f} s ({len(source) / dt:.1f} frames/s)")
    print(f"  wrote -> {sink.path}")
    if above and any(sink.target(f).suffix.lower() == ".png" for f in source.files[:1]):
        print(f"  note: {100 * above / pixels:.2f} % of pixels exceed 1 and are clipped in the "
              "PNG output; use .tif or .npy to keep them")
    return 0


# --- bounces ----------------------------------------------------------------------------

def run_bounces(args) -> int:
    from ..compensation import bounce_shares, separate_bounces
    from ..figures import bounce_strip
    from ..images import read_image, write_image
    from ..storage import as_store

    T = as_store(args.T, "T")
    X = as_store(args.X, "X")
    if Path(args.input).is_dir():
        raise ImageError("bounces takes one image, not a folder", args.input)
    out = Path(args.output)
    if out.exists() and not out.is_dir():  # refused now, not after the passes
        raise ImageError("is a file; bounces writes a folder of images: choose a folder",
                         out)
    image = read_image(args.input, _image_shape(T))
    print(f"bigT bounces: {args.input}, K = {args.bounces}")
    print("  " + _describe(T, "T"))
    print("  " + _describe(X, "X"))
    t0 = time.perf_counter()
    parts = separate_bounces(T, X, image, args.bounces, progress=args.progress)
    dt = time.perf_counter() - t0
    shares = bounce_shares(parts)
    out.mkdir(parents=True, exist_ok=True)
    names = [f"bounce_{k}" for k in range(args.bounces + 1)] + ["remainder"]
    K = args.bounces
    print(f"  {K + 2} parts in {dt:.2f} s: bounces 0 (direct light) to {K}, and the "
          f"remainder T l - (b_0 + ... + b_{K}) (the light of bounces after {K}, less what "
          f"X lacks of the exact inverse); share of the total T l (sum {parts.sum():.4g}):")
    for name, part, share in zip(names, parts, shares):
        write_image(out / f"{name}.{args.format}", part, bits=16)
        label = "direct" if name == "bounce_0" else name.replace("_", " ")
        print(f"    {label:>10}: {100 * share:7.3f} %")
    if shares[-1] < 0:
        print("  note: the remainder is negative: X is not the exact inverse (its series is "
              "truncated after its terms and its small entries pruned), so the separated "
              "bounces add up to more than T l; an X with more terms or a lower prune "
              "(bigT invert --terms, --prune) brings it towards the light beyond bounce "
              f"{K}")
    write_image(out / f"total.{args.format}", parts.sum(axis=0), bits=16)
    strip = bounce_strip(out / "bounces.png", parts, shares)
    if args.format == "png":
        print("  note: PNG clips to [0, 1] (a negative remainder is lost); use tif/npy for exact parts")
    print(f"  wrote {len(names) + 1} images and {strip.name} -> {out}")
    return 0
