"""``bigT compensate``, ``bigT relight`` and ``bigT bounces``.

Images go in and come out in the same form: one file -> one file, a folder of frames ->
a folder with the same names (or a video file), a video -> a video. Folders and videos
are read, processed and written one batch of frames at a time, so the frames never
need to fit in memory; X is held in memory when it fits ``--memory-limit`` and streamed
from disk tile row by tile row otherwise (:mod:`bigT.compensation.realtime`).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .. import config
from ..errors import ImageError
from ._argtypes import clip_range, integer, memory_size, number, scheduler_address

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
        "frames or a video, batch by batch: X held in memory when it fits --memory-limit, "
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
    p.add_argument("--cache-mb", dest="cache_mb", type=integer(0), default=None,
                   help="MiB of decoded matrix tiles kept between batches (default "
                   f"{config.COMPENSATE_CACHE_BYTES >> 20}; 0: re-read every pass)")
    p.add_argument("--scheduler", type=scheduler_address, default=None,
                   metavar="ADDRESS|local:N",
                   help="run the passes on a dask cluster: a scheduler address, or local:N "
                   "for N worker processes started for this command (default: local threads)")
    p.add_argument("--memory-limit", dest="memory_limit", type=memory_size, default=None,
                   metavar="SIZE", help="hold X in memory when it needs at most SIZE (e.g. "
                   "2GiB; default "
                   f"{100 * config.COMPENSATE_RESIDENT_FRACTION:.0f}%% of the available memory), "
                   "else "
                   "stream it from disk tile row by tile row")
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
    p.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress bars")
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
    p.add_argument("--scheduler", type=scheduler_address, default=None,
                   metavar="ADDRESS|local:N",
                   help="run the passes on a dask cluster: a scheduler address, or local:N "
                   "for N worker processes started for this command (default: local threads)")
    p.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress bars")
    p.set_defaults(func=run_relight)

    p = sub.add_parser("bounces", help="split the camera image T l into light bounces",
                       description="Seitz-style bounce separation: F_ii = 1/X_ii (paper eq. "
                       "33), A = I - F X, b_k = A^k F l, plus the remainder T l - sum b_k. "
                       "Each part's share is its sum over the pixels divided by the sum of T l "
                       "(the share of the total light; the shares add up to 100%), as "
                       "`bigT scene` reports the bounces of a white image.")
    p.add_argument("T", help="transport store (T.zarr)")
    p.add_argument("X", help="inverse store (X.zarr), as exact as possible")
    p.add_argument("input", help="projector image l (png/tif/npy)")
    p.add_argument("--bounces", type=integer(0, MAX_BOUNCES), default=4,
                   help=f"K, the last bounce kept, 0 to {MAX_BOUNCES} (default 4)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--format", choices=("tif", "npy", "png"), default="tif",
                   help="image format of the parts (tif/npy keep floats; default tif)")
    p.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress bars")
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
    from ..compensation.core import (CompensationReport, choose_path, compensate_frames,
                                     fluctuation, relative_error, scan_line)
    from ..schedule.stream import cache_budget, compute_dtype, scheduler_runner, stream_matmul
    from ..storage import as_store
    from ..storage.frames import pixel_order_of, to_frames, to_vectors
    from ..compensation.video import is_video_file
    from ..images import ImageSink, ImageSource

    clip = args.clip
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
    source = ImageSource(args.desired, shape)
    out_path = Path(args.output)
    sink = ImageSink(out_path, source, bits=args.bits)
    seen_sink = ImageSink(_sibling(out_path, "seen"), source, bits=args.bits) if S else None

    print(f"bigT compensate: {len(source)} frame(s) from {args.desired}"
          + (f", image {shape[0]}x{shape[1]}" if shape else ""))
    shown = []
    for st, name in ((X, "X"), (Tm if choice.path == "matrix-free" else None, "T"), (S, "T")):
        if st is not None and all(st is not o for o in shown):
            print("  " + _describe(st, name))
            shown.append(st)
    print(f"  path: {choice.path}" + (f" ({choice.terms} terms)" if choice.terms is not None
                                      else "") + f" -- {choice.reason}")

    report = CompensationReport(choice)
    cache_bytes = cache_budget(None if args.cache_mb is None else args.cache_mb << 20)
    sums = dict(err=0.0, err0=0.0, ref=0.0)
    flat = []  # (image fl. without, with, scan line without, with) for constant targets
    first = None
    from ..progress import progress_bar

    t_comp = 0.0
    t0 = time.perf_counter()
    with progress_bar(progress=args.progress, total=len(source), desc="compensate",
                      unit="frame", leave=True) as bar, \
            scheduler_runner(args.scheduler) as runner:
        if runner is not None:
            print(f"  running on {runner.describe()}")
        for files, frames in source.batches(args.batch):
            t1 = time.perf_counter()
            l_in = compensate_frames(frames, X=X, T=Tm, choice=choice, clip=clip,
                                        report=report, progress=args.progress,
                                        cache_bytes=cache_bytes, runner=runner)
            t_comp += time.perf_counter() - t1
            report.frames += len(frames)
            sink.write(files, l_in)
            if S is not None:
                order = pixel_order_of(S, frames.shape[1:])
                both = np.concatenate([l_in, frames])  # one pass over T for both
                seen_all = to_frames(stream_matmul(S, to_vectors(both, order, compute_dtype(S)),
                                                   progress=args.progress, desc="T pass",
                                                   cache_bytes=cache_bytes, runner=runner),
                                     order)
                seen, seen0 = seen_all[:len(frames)], seen_all[len(frames):]
                seen_sink.write(files, seen)
                sums["err"] += float(np.sum((seen - frames) ** 2))
                sums["err0"] += float(np.sum((seen0 - frames) ** 2))
                sums["ref"] += float(np.sum(frames ** 2))
                for d, a, b in zip(frames, seen0, seen):
                    if np.ptp(d) == 0 and d.flat[0] > 0:
                        flat.append((fluctuation(a), fluctuation(b), fluctuation(scan_line(a)),
                                     fluctuation(scan_line(b))))
                if first is None:
                    first = (files[0], frames[0], seen0[0], l_in[0], seen[0])
            bar.update(len(frames))
    elapsed = time.perf_counter() - t0
    report.seconds = t_comp

    print(f"  {report.frames} frame(s) in {t_comp:.2f} s of products "
          f"({report.frames_per_second:.1f} frames/s, batch {args.batch}); {elapsed:.2f} s in all")
    if clip is not None:
        _print_clipped(report, clip)
    print(f"  wrote projector input -> {sink.path}")
    if S is not None:
        ref = np.sqrt(sums["ref"])
        print(f"  simulated camera (T l_in) -> {seen_sink.path}")
        print(f"  relative error ||T l_in - l_desired|| / ||l_desired||: "
              f"{np.sqrt(sums['err']) / ref:.4f} compensated, {np.sqrt(sums['err0']) / ref:.4f} "
              "uncompensated (T l_desired)")
        if flat:
            f = np.mean(np.array(flat), axis=0)
            print(f"  constant target ({len(flat)} frame(s)), fluctuation (max-min)/mean: "
                  f"image {f[0]:.3f} -> {f[1]:.3f}, centre scan line {f[2]:.3f} -> {f[3]:.3f} "
                  "(uncompensated -> compensated)")
        else:
            print("  fluctuation: n/a (no constant target frame)")
        name, desired, seen0, l_in, seen = first
        from ..figures import scan_lines, side_by_side

        tag = "" if not source.is_folder else f" (frame {name.name})"
        pic = side_by_side(
            _sibling(out_path, "compare", ".png"), [desired, seen0, l_in, seen],
            ["desired", "seen without compensation", "projector input", "seen with compensation"],
            suptitle=f"compensation, {choice.path} path{tag}; error "
            f"{relative_error(seen, desired):.3f} vs {relative_error(seen0, desired):.3f}")
        lines = {"without compensation": scan_line(seen0), "with compensation": scan_line(seen),
                 "projector input": scan_line(l_in)}
        const = float(desired.flat[0]) if np.ptp(desired) == 0 else None
        if const is None:
            lines["desired"] = scan_line(desired)
        plot = scan_lines(_sibling(out_path, "scanline", ".png"), lines,
                          title=f"centre scan line (row {desired.shape[0] // 2}){tag}",
                          target=const)
        print(f"  figures -> {pic}, {plot}")
    return 0


def _run_stream(args, X, Tm, choice, shape) -> int:
    """compensate without --simulate: frames streamed through
    :func:`bigT.compensation.realtime.run_stream`, X in memory when it fits."""
    import sys

    from ..schedule.stream import cache_budget, scheduler_runner
    from ..compensation.realtime import Compensator, image_batches, run_stream, video_batches
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
    print(f"  path: {choice.path}" + (f" ({choice.terms} terms)" if choice.terms is not None
                                      else "") + f" -- {choice.reason}")
    output = _Output(args, source, out_path, video_in, video_out)  # checked before X is read
    cache_bytes = cache_budget(None if args.cache_mb is None else args.cache_mb << 20)
    with scheduler_runner(args.scheduler) as runner:
        if runner is not None:
            print(f"  running on {runner.describe()}")
        comp = Compensator(X, Tm, choice, args.clip, memory_limit=args.memory_limit,
                           precision=args.precision,
                           resident=not args.stream and args.scheduler is None,
                           cache_bytes=cache_bytes, runner=runner)
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
        _print_clipped(report, args.clip)
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
    from ..schedule.stream import scheduler_runner
    from ..storage import as_store
    from ..compensation.core import relight
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
    from ..storage import as_store
    from ..compensation.core import bounce_shares, separate_bounces
    from ..figures import bounce_strip
    from ..images import read_image, write_image

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
    print(f"  {args.bounces + 1} bounce(s) + remainder in {dt:.2f} s; share of the total T l "
          f"(sum {parts.sum():.4g}):")
    for name, part, share in zip(names, parts, shares):
        write_image(out / f"{name}.{args.format}", part, bits=16)
        label = "direct" if name == "bounce_0" else name.replace("_", " ")
        print(f"    {label:>10}: {100 * share:7.3f} %")
    write_image(out / f"total.{args.format}", parts.sum(axis=0), bits=16)
    strip = bounce_strip(out / "bounces.png", parts, shares)
    if args.format == "png":
        print("  note: PNG clips to [0, 1] (a negative remainder is lost); use tif/npy for exact parts")
    print(f"  wrote {len(names) + 1} images and {strip.name} -> {out}")
    return 0


def _print_clipped(report, clip) -> None:
    """The share of projector pixels clipped, below and above (both paths' summary)."""
    print(f"  clipped projector pixels: {100 * report.clipped_fraction:.2f} % "
          f"(below {clip[0]}: {100 * report.clipped_low / max(report.pixels, 1):.2f} %, "
          f"above {clip[1]}: {100 * report.clipped_high / max(report.pixels, 1):.2f} %)")
