"""``bigT compensate``, ``bigT relight`` and ``bigT bounces``.

Images go in and come out in the same form: one file -> one file, a folder of frames ->
a folder with the same names (or a video file), a video -> a video. Folders and videos
are read, processed and written one batch of frames at a time, so the frames never
need to fit in memory; X is held in memory when it fits ``--memory-limit`` and streamed
from disk tile row by tile row otherwise (:mod:`bigT.compensation.realtime`).

A colour store takes RGB images and colour video (a grey one, grey: the other kind is
refused in one line naming the file); ``--encoding`` says how the values relate to
light (an 8-bit colour input is sRGB unless told ``linear``), and the outputs are
written in the input's encoding.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from .. import config
from ..atomic import refuse_overwriting_inputs
from ..errors import ImageError
from ..progress import progress_bar
from ..sizes import format_size
from ._argtypes import clip_range, integer, memory_size, number
from ._options import add_json, add_progress, add_scheduler, add_size, deprecated

# The library's layers are imported inside each command's functions, where the
# command runs: building the parser imports every command module, and a command
# should pay only for the layers it uses (stores: zarr ~0.3 s; compensation ~0.5 s).

#: Largest K of ``bigT bounces``. Each bounce costs one streamed pass over X, one
#: (H, W) float64 image held in memory and one file; the remainder T l - sum b_k holds
#: all light beyond K, so a small K loses nothing. 64 is far past any useful K (the
#: paper separates 4-5; bounce k decays like rho^k, and rho^64 < 1e-6 for rho < 0.8)
#: while keeping a mistyped K (100000: 10 GB and 100,000 files) from running away.
MAX_BOUNCES = 64
#: What --encoding takes: bigT.colour's ENCODINGS, or "auto" (its policy); written out
#: here because bigT.colour imports numpy (~0.1 s), which ``bigT --help`` does not need
#: (tests/test_startup_imports.py checks they agree)
ENCODING_CHOICES = ("auto", "srgb", "linear")


def add_encoding(p: argparse.ArgumentParser, what: str) -> None:
    """``--encoding {auto,srgb,linear}``: how the input's values relate to light."""
    p.add_argument("--encoding", choices=ENCODING_CHOICES, default="auto",
                   help="how the input's values relate to light: srgb (decoded to linear "
                   "light before the product) or linear; the outputs are written in the "
                   f"same encoding. auto (default): srgb for an 8-bit colour {what}, "
                   "linear for 16-bit, floating-point and grey ones")


def add_projector(p: argparse.ArgumentParser) -> None:
    """The projector's response, depth and dither, and the rig's smoothing."""
    p.add_argument("--projector-response", dest="projector_response", metavar="FILE",
                   default="auto",
                   help="the projector's response (JSON, docs/CALIBRATION.md): the output "
                   "is the projector's integer values, the linear light encoded through its "
                   "inverse. Default: the one stored with T (acquire build's, found through "
                   "X's record or the T given); 'none' for linear light, as without one")
    p.add_argument("--projector-bits", dest="projector_bits", type=int, choices=(8, 16),
                   default=None, help="the projector's input depth (default 8; with a "
                   "projector response only)")
    p.add_argument("--dither", choices=("none", "ordered", "random"), default="none",
                   help="dither of the projector's values: ordered (8x8 Bayer, the same "
                   "every frame) or random; the expected light is the one asked (default "
                   "none: the nearest value)")
    p.add_argument("--smooth", action="store_true",
                   help="with an acquired T (a rig's correspondence): the projector's image "
                   "interpolated bilinearly between super-pixel centres, not in blocks")


def _projector_options(args) -> dict:
    """The projector options of a compensation, from the command line."""
    response = None if args.projector_response == "none" else args.projector_response
    return dict(projector_response=response, projector_bits=args.projector_bits,
                dither=args.dither, smooth=args.smooth)


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
    add_encoding(p, "image or video")
    add_projector(p)
    add_json(p, "the report (with --simulate: PSNR, SSIM, ΔE2000 too)")
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
    add_encoding(p, "image")
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

def print_json(data: dict) -> None:
    """``data`` as one JSON object on stdout; NaN and infinities (a PSNR of identical
    images) as null, which JSON has."""
    def finite(value):
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, dict):
            return {k: finite(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [finite(v) for v in value]
        return value

    print(json.dumps(finite(data)))


def say(args, text: str) -> None:
    """Print the text report's lines (not with --json, whose object is the output)."""
    if not getattr(args, "json", False):
        print(text)

# --- compensate -------------------------------------------------------------------------

def run_compensate(args) -> int:
    # the compensation layer's imports (~0.5 s) are paid by these commands only, not by
    # every command whose parser this module adds
    from ..storage import as_store

    X = None if args.X == "-" else as_store(args.X, "X")
    if args.simulate is None:
        Tm = as_store(args.matrix_free, "T") if args.matrix_free else None
        return _run_stream(args, X, Tm)
    return _run_simulate(args, X)


def _run_simulate(args, X) -> int:
    """compensate --simulate: :class:`bigT.compensation.FileSimulation` made (inputs
    checked), described, run, its report printed."""
    from ..compensation import FileSimulation

    job = FileSimulation(X, args.desired, args.output, args.simulate, path=args.path,
                         matrix_free=args.matrix_free, terms=args.terms, clip=args.clip,
                         batch=args.batch, bits=args.bits, cache_bytes=args.cache_bytes,
                         scheduler=args.scheduler, encoding=args.encoding,
                         **_projector_options(args))
    head, *rest = job.describe().splitlines()
    say(args, f"bigT compensate: {head}")
    for line in rest:
        say(args, "  " + line)
    with progress_bar(progress=args.progress, total=len(job.source), desc="compensate",
                      unit="frame", leave=True) as bar:
        report = job.run(progress=args.progress, on_batch=bar.update)
    if args.json:
        print_json(report.to_dict())
        return 0
    for line in report.describe().splitlines():
        print("  " + line)
    return 0


def _run_stream(args, X, Tm) -> int:
    """compensate without --simulate: :class:`bigT.compensation.FileCompensation` set up
    (inputs checked, X loaded), described, run, its report printed."""

    from ..compensation import FileCompensation

    job = FileCompensation(
        X, args.desired, args.output, T=Tm, path=args.path, terms=args.terms, clip=args.clip,
        batch=args.batch, bits=args.bits, fps=args.fps, resident=not args.stream,
        memory_limit=args.memory_limit, precision=args.precision,
        cache_bytes=args.cache_bytes, scheduler=args.scheduler, encoding=args.encoding,
        **_projector_options(args))
    head, *rest = job.describe().splitlines()
    say(args, f"bigT compensate: {head}")
    for line in rest:
        say(args, "  " + line)
    with job:  # X read (into memory when it fits), the scheduler's runner opened
        if job.runner is not None:
            say(args, f"  running on {job.runner.describe()}")
        if not args.quiet:
            print(f"bigT compensate: {job.describe_residency()}", file=sys.stderr)
        with progress_bar(progress=args.progress, total=job.frames, desc="compensate",
                          unit="frame", leave=True) as bar:
            report = job.run(overlap=not args.serial, on_batch=bar.update)
    if args.json:
        print_json(report.to_dict())
        return 0
    for line in report.describe().splitlines():
        print("  " + line)
    return 0


# --- relight ----------------------------------------------------------------------------

def run_relight(args) -> int:
    from ..compensation.files import describe_store, relight_files
    from ..storage import as_store

    T = as_store(args.T, "T")
    print(f"bigT relight: {args.input}")
    print("  " + describe_store(T, "T"))
    report = relight_files(T, args.input, args.output, batch=args.batch, bits=args.bits,
                           scheduler=args.scheduler, progress=args.progress,
                           on_start=lambda runner: print(f"  running on {runner}"),
                           encoding=args.encoding)
    for line in report.describe().splitlines():
        print("  " + line)
    return 0


# --- bounces ----------------------------------------------------------------------------

def run_bounces(args) -> int:
    from ..compensation import bounce_shares, separate_bounces
    from ..compensation.files import describe_store, image_shape_of, store_paths
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
    names = [f"bounce_{k}" for k in range(args.bounces + 1)] + ["remainder"]
    files = [out / f"{name}.{args.format}" for name in names + ["total"]]
    refuse_overwriting_inputs(files + [out / "bounces.png"], [args.input, *store_paths(T, X)],
                              folders=[out])
    image = read_image(args.input, image_shape_of(T), channels=T.channels)
    print(f"bigT bounces: {args.input}, K = {args.bounces}")
    print("  " + describe_store(T, "T"))
    print("  " + describe_store(X, "X"))
    t0 = time.perf_counter()
    parts = separate_bounces(T, X, image, args.bounces, progress=args.progress)
    dt = time.perf_counter() - t0
    shares = bounce_shares(parts)
    out.mkdir(parents=True, exist_ok=True)
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
