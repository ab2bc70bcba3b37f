"""``bigT acquire``: patterns to project, T built from their captures, and a simulated
camera to try it without a rig (bigT.acquisition)."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import warnings

from .. import config
from ..atomic import refuse_overwriting_inputs
from ..errors import MemoryLimitWarning
from ._argtypes import image_size, integer, number
from ._options import add_json, add_memory_limit, add_progress

# plain numbers, kept here so that building the parser imports no library layer
# (bigT.acquisition.manifest's MIN_RAMP_LEVELS, MAX_RAMP_LEVELS, DEFAULT_RAMP_LEVELS;
# tests/acquisition check they agree)
MIN_RAMP_LEVELS, MAX_RAMP_LEVELS, DEFAULT_RAMP_LEVELS = 17, 256, 17

# The library's layers are imported inside each command's functions, where the
# command runs: building the parser imports every command module, and a command
# should pay only for the layers it uses (stores: zarr ~0.3 s; compensation ~0.5 s).


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "acquire", help="measure T with a projector and a camera (patterns, build, simulate)",
        description="Acquire a light-transport matrix from a projector-camera rig: write the "
                    "patterns to project, build T from their captures (correspondence, noise "
                    "floor, tile row by tile row), or simulate the captures from a synthetic "
                    "scene.")
    sub = p.add_subparsers(dest="acquire_command", metavar="STEP", required=True)
    _register_patterns(sub)
    _register_build(sub)
    _register_simulate(sub)


def _common(p) -> None:
    add_progress(p)
    p.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing but errors and warnings")


def _register_patterns(sub) -> None:
    p = sub.add_parser(
        "patterns", help="write the pattern images and their manifest",
        description="Write the images the projector shows (8-bit PNG at its resolution) and "
                    "DIR/manifest.json listing them in order with what each lights. Every set "
                    "has an all-black and an all-white pattern.")
    # the methods are bigT.acquisition's: the options are added when this step runs or
    # prints its help, so that no other command imports that layer to list them
    p.defer(_patterns_options)
    p.set_defaults(func=patterns_cmd, command="acquire patterns")


def _patterns_options(p) -> None:
    from ..acquisition import METHODS

    p.add_argument("--method", choices=METHODS, required=True,
                   help="brute-force: one super-pixel per image; stripes: row and column "
                        "bands (Ding et al. 2009); graycode: the correspondence only")
    p.add_argument("--projector", type=image_size, required=True, metavar="HxW",
                   help="the projector's resolution in pixels")
    p.add_argument("--superpixel", type=integer(1), default=1, metavar="S",
                   help="super-pixel side in projector pixels (default %(default)s)")
    p.add_argument("--graycode", action="store_true",
                   help="add Gray-code patterns: the correspondence by decoding rather than "
                        "by each camera pixel's maximum response")
    p.add_argument("--channels", type=int, choices=(1, 3), default=1,
                   help="3 for a colour T: every super-pixel or stripe pattern once per "
                        "projector primary (R, G, B; RGB PNGs), black, white and the Gray "
                        "code in white (default %(default)s: grey)")
    p.add_argument("--ramp-levels", type=ramp_levels, default=DEFAULT_RAMP_LEVELS,
                   metavar="N",
                   help="uniform frames from 0 to 1 (each an 8-bit code) that the build fits "
                        "the projector's response from, once per primary for colour: 0 (no "
                        f"ramp) or {MIN_RAMP_LEVELS} to {MAX_RAMP_LEVELS} (default "
                        "%(default)s)")
    p.add_argument("-o", "--output", required=True, metavar="DIR",
                   help="folder of the pattern images and manifest.json")
    _common(p)


def _register_build(sub) -> None:
    p = sub.add_parser(
        "build", help="build T from the captures of a pattern set",
        description="Subtract the black capture, find each projector super-pixel's camera "
                    "super-pixel (paper §6.1), drop values under the noise floor and write T "
                    "tile row by tile row into a bigT store, then compare T 1 with the "
                    "captured white image (paper Fig. 8). An interrupted build resumes.")
    p.add_argument("patterns", metavar="PATTERNS_DIR")
    p.add_argument("captures", metavar="CAPTURES_DIR")
    p.add_argument("-o", "--output", required=True, metavar="T.zarr",
                   help="the transport store to write (an interrupted build resumes)")
    p.add_argument("--black", default=None, metavar="FILE",
                   help="a black-level image to subtract (default: the black pattern's capture)")
    p.add_argument("--floor", type=number(0), default=None, metavar="T",
                   help="drop entries of T below this (default 3 x the noise of a camera "
                        "super-pixel, estimated from the black capture)")
    p.add_argument("--gamma", type=number(0, lo_open=True), default=1.0,
                   help="undo a camera gamma: linear = stored ** gamma (default 1: linear; "
                        "the same as --camera-response gamma:G)")
    p.add_argument("--camera-response", default=None, metavar="SPEC",
                   help="the camera's response, undone before anything else (each exposure "
                        "of a bracket before the merge): linear (default), srgb, gamma:G, a "
                        ".npy/.json table, or recover[:debevec|:robertson] (from the "
                        "brackets of the white and ramp patterns); RAW files are linear")
    p.add_argument("--tile-size", type=integer(1), default=None,
                   help=f"rows/cols of one matrix tile of T (default {config.DEFAULT_TILE_SIZE}; "
                        f"of a colour T a multiple of 3, default "
                        f"{config.DEFAULT_COLOUR_TILE_SIZE})")
    p.add_argument("--mixing", default=None, metavar="FILE",
                   help='colour: the rig\'s global colour mixing, a JSON file {"camera": 3x3, '
                        '"projector": 3x3}, recorded in T\'s metadata ("mixing") for the '
                        "engine's global path")
    add_memory_limit(p, default=config.ACQUIRE_MEMORY_BYTES,
                     bounds="memory the build may hold of T's entries gathered in one pass "
                     "over the captures; more passes when they do not fit")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bigT store")
    p.add_argument("--no-figures", action="store_true",
                   help="do not write the correspondence and validation PNGs")
    add_json(p)
    _common(p)
    p.set_defaults(func=build_cmd, command="acquire build")


def _register_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate", help="render the captures of a pattern set from a synthetic scene",
        description="Stand in for a rig: the camera image each pattern would produce on a "
                    "scene made by bigT scene (or any T store with an image shape; a colour "
                    "T with colour patterns gives RGB captures), at another resolution, each "
                    "projector super-pixel seen by an uneven patch of camera pixels, with "
                    "noise, a black level and a gamma. The camera model goes to "
                    "CAPTURES_DIR/simulation.json.")
    # added when this step runs or prints its help: no other command's parser needs them
    p.defer(_simulate_options)
    p.set_defaults(func=simulate_cmd, command="acquire simulate")


def _simulate_options(p) -> None:
    from ..acquisition.formats import FORMATS  # light: not the simulator's imports

    p.add_argument("scene", metavar="SCENE.zarr")
    p.add_argument("patterns", metavar="PATTERNS_DIR")
    p.add_argument("-o", "--output", required=True, metavar="CAPTURES_DIR",
                   help="folder of the captures to write")
    p.add_argument("--camera", type=image_size, required=True, metavar="HxW",
                   help="the camera's resolution (any: it need not match the projector's)")
    p.add_argument("--noise", type=noise_levels, default=0.0, metavar="STD[,STD,STD]",
                   help="noise std, or one for each of R, G, B of a colour T (default 0)")
    p.add_argument("--black", type=number(0, 1), default=0.0, help="black level (default 0)")
    p.add_argument("--gamma", type=number(0, lo_open=True), default=1.0,
                   help="camera gamma: stored = linear ** (1 / gamma) (default 1)")
    p.add_argument("--format", choices=tuple(FORMATS), default=None,
                   help="capture files (default png16; with the nonlinear rig, png of its "
                        "--bits)")
    p.add_argument("--seed", type=integer(0), default=0,
                   help="seed of the noise (default %(default)s)")
    rig = p.add_argument_group(
        "nonlinear rig", "any of these simulates a real rig (docs/CALIBRATION.md): the "
        "patterns through a projector response r(v) = b + (1 - b) s(v^G), s(u) = u + S u "
        "(1 - u), captured by a camera with shot and read noise, clipped at its full well, "
        "through its response and quantised; the defaults are those given")
    rig.add_argument("--projector-gamma", type=per_channel(number(0, lo_open=True)),
                     default=None, metavar="G[,G,G]",
                     help="the projector's gamma, or one per primary (default 2.2)")
    rig.add_argument("--projector-black", type=per_channel(number(0, 1, hi_open=True)),
                     default=None, metavar="B[,B,B]",
                     help="light at value 0, of full scale (default 0.02)")
    rig.add_argument("--projector-shoulder", type=per_channel(number(0, 1, hi_open=True)),
                     default=None, metavar="S[,S,S]",
                     help="roll-off at the top: slope 1 - S at full scale (default 0.3)")
    rig.add_argument("--camera-response", default=None, metavar="SPEC",
                     help="the camera's curve: linear, srgb, gamma:G or a table file "
                          "(default gamma:2.2); build with the same --camera-response")
    rig.add_argument("--bits", type=int, choices=(8, 16), default=None,
                     help="the camera's bit depth (default 8)")
    rig.add_argument("--full-well", type=number(0, lo_open=True), default=None,
                     metavar="E", help="electrons at full well: the shot noise (default 20000)")
    rig.add_argument("--read-noise", type=number(0), default=None, metavar="R",
                     help="read noise std, of full well (default 0.001)")
    rig.add_argument("--exposures", type=exposure_list, default=None, metavar="T1,T2,...",
                     help="exposure times in seconds, rising (default 1): several write "
                          "brackets, CAPTURES_DIR/<pattern>@<seconds>.png; the white "
                          "pattern's brightest pixel fills 0.9 of the full well in the first")
    _common(p)


def ramp_levels(text: str) -> int:
    """An argparse type: 0 (no ramp) or MIN_RAMP_LEVELS to MAX_RAMP_LEVELS."""
    value = integer(0)(text)
    if value and not MIN_RAMP_LEVELS <= value <= MAX_RAMP_LEVELS:
        raise argparse.ArgumentTypeError(
            f"must be 0 (no ramp) or {MIN_RAMP_LEVELS} to {MAX_RAMP_LEVELS}, got {text!r}")
    return value


def per_channel(parse):
    """An argparse type: one value of ``parse``, or three (R, G, B) separated by commas."""
    def values(text: str) -> float | tuple[float, ...]:
        parts = text.split(",")
        if len(parts) not in (1, 3):
            raise argparse.ArgumentTypeError(f"must be one value or three (R,G,B), got {text!r}")
        parsed = tuple(parse(part) for part in parts)
        return parsed[0] if len(parsed) == 1 else parsed
    return values


def exposure_list(text: str) -> tuple[float, ...]:
    """An argparse type: exposure times in seconds, rising strictly: ``1,8,64``."""
    times = tuple(number(0, lo_open=True)(part) for part in text.split(","))
    if any(b <= a for a, b in zip(times, times[1:])):
        raise argparse.ArgumentTypeError(f"must rise strictly, got {text!r}")
    return times


def noise_levels(text: str) -> float | tuple[float, ...]:
    """An argparse type: one noise std >= 0, or three (R, G, B) separated by commas."""
    parts = text.split(",")
    parse = number(0)
    if len(parts) not in (1, 3):
        raise argparse.ArgumentTypeError(f"must be one std >= 0 or three (R,G,B), got {text!r}")
    values = tuple(parse(part) for part in parts)
    return values[0] if len(values) == 1 else values


def _progress(args):
    return None if args.progress else False


def patterns_cmd(args) -> int:
    from ..acquisition import make_manifest, write_patterns

    manifest = make_manifest(args.method, args.projector, args.superpixel, graycode=args.graycode,
                             channels=args.channels, ramp_levels=args.ramp_levels)
    path = write_patterns(args.output, manifest, progress=_progress(args))
    ramp = (f", a ramp of {manifest.ramp_levels} levels"
            f"{' per primary' if manifest.channels == 3 else ''}" if manifest.ramp_levels else "")
    print(f"{len(manifest.patterns)} patterns ({args.method}"
          f"{', Gray code' if manifest.graycode else ''}"
          f"{', colour: R, G, B each' if manifest.channels == 3 else ''}{ramp}) for a "
          f"{manifest.projector[0]}x{manifest.projector[1]} projector, "
          f"{manifest.grid[0]}x{manifest.grid[1]} super-pixels")
    print(f"-> {path}")
    return 0


def build_cmd(args) -> int:
    from ..acquisition import build_transport, load_correspondence
    from ..acquisition.ramp import response_figure_path
    from ..acquisition.validate import (
        check_white,
        figure_paths,
        plot_correspondence,
        plot_white_check,
    )

    planned = () if args.no_figures else (*figure_paths(args.output),
                                          response_figure_path(args.output))
    response_file = args.camera_response if _is_file_spec(args.camera_response) else None
    refuse_overwriting_inputs(planned, [args.patterns, args.captures, args.black, args.mixing,
                                        response_file])

    with _own_warnings("bigT acquire build"):
        report = build_transport(args.patterns, args.captures, args.output, black=args.black,
                                 floor=args.floor, gamma=args.gamma, tile_size=args.tile_size,
                                 memory_bytes=args.memory_limit, overwrite=args.overwrite,
                                 progress=_progress(args), mixing=args.mixing,
                                 camera_response=args.camera_response)
    check = check_white(report.path)
    figures = []
    if not args.no_figures:
        corr_png, val_png = figure_paths(report.path)
        figures = [plot_correspondence(load_correspondence(report.path), _grid(report),
                                       corr_png),
                   plot_white_check(check, val_png)]
        if report.projector_response is not None:
            figures.append(report.projector_response.draw(
                response_figure_path(report.path),
                title=f"projector response of {report.path.name} (light above black)"))
    if args.json:
        print(json.dumps({**report.settings.to_dict(), "n": report.n, "seen": report.seen,
                          "nnz": report.nnz, "passes": report.passes,
                          "black_level": report.black_level,
                          "saturated_pixels": report.saturated_pixels,
                          "seconds": report.seconds,
                          "white_relative_error": check.relative_error,
                          "interreflected_share": check.kept.interreflected_share,
                          "dropped_interreflection": check.dropped_interreflection,
                          "dropped_light": check.dropped_light,
                          "mixing": None if report.mixing is None else report.mixing.to_metadata(),
                          "projector_response": None if report.projector_response is None
                          else report.projector_response.to_document(),
                          "figures": [str(f) for f in figures]}, indent=1))
        return 0
    print(report.describe())
    print(check.describe())
    for f in figures:
        print(f"-> {f}")
    print(f"-> {report.path}")
    return 0


@contextlib.contextmanager
def _own_warnings(command: str):
    """Print bigT's own warnings (saturated pixels, a tile row over the memory limit) as
    ``COMMAND: warning: ...`` lines on stderr once the block has run (a failure's one
    line stays the only one); any other warning (a library's) is handed on to Python's
    own handling, as it would be without bigT."""
    from ..acquisition.build import AcquisitionWarning

    own = (AcquisitionWarning, MemoryLimitWarning)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", own)
        yield
    for w in caught:
        if issubclass(w.category, own):
            print(f"{command}: warning: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno,
                                   source=w.source)


def _is_file_spec(spec) -> bool:
    """A ``--camera-response`` naming a table file (an input the figures must not
    overwrite)."""
    return spec is not None and str(spec).lower().endswith((".npy", ".json"))


def _noise_text(noise) -> str:
    """``0.002``, or ``R 0.001 G 0.002 B 0.003``."""
    if isinstance(noise, tuple):
        return " ".join(f"{c} {v:g}" for c, v in zip("RGB", noise))
    return f"{noise:g}"


def _grid(report) -> tuple[int, int]:
    s = report.settings
    return (s.projector[0] // s.superpixel, s.projector[1] // s.superpixel)


def simulate_cmd(args) -> int:
    from ..acquisition import read_manifest, simulate_captures

    # the pattern folder as the output is refused by simulate_captures, in its own words
    refuse_overwriting_inputs((), [args.scene], folders=[args.output])
    rig = _rig(args)
    exposures = args.exposures or (1.0,)
    fmt = args.format or ("png16" if rig is None else f"png{rig.bits}")
    model = simulate_captures(args.scene, args.patterns, args.output, camera=args.camera,
                              noise=args.noise, black=args.black, gamma=args.gamma,
                              fmt=fmt, seed=args.seed, progress=_progress(args), rig=rig,
                              exposures=exposures)
    count = len(read_manifest(args.patterns).patterns)
    if rig is None:
        print(f"{count} captures of {args.scene} by a {model.camera[0]}x{model.camera[1]} "
              f"camera (exposure {model.exposure:.3g}, noise {_noise_text(model.noise)}, "
              f"black {model.black:g}, gamma {model.gamma:g})")
    else:
        from ..acquisition.brackets import seconds_text

        r = rig
        shots = (f"{count} captures" if len(exposures) == 1 else
                 f"{count} brackets of {len(exposures)} exposures "
                 f"({', '.join(seconds_text(t) for t in exposures)})")
        print(f"{shots} of {args.scene} on a nonlinear rig: projector gamma "
              f"{_noise_text(r.projector_gamma)}, black {_noise_text(r.projector_black)}, "
              f"shoulder {_noise_text(r.projector_shoulder)}; a {model.camera[0]}x"
              f"{model.camera[1]} {r.bits}-bit camera, response {r.camera.describe()}, "
              f"full well {r.full_well_electrons:g} e-, read noise {r.read_noise:g}")
    print(f"-> {args.output}")
    return 0


def _rig(args):
    """The nonlinear rig the options describe, None when none is given."""
    names = ("projector_gamma", "projector_black", "projector_shoulder", "camera_response",
             "bits", "full_well", "read_noise", "exposures")
    if all(getattr(args, name) is None for name in names):
        return None
    from ..calibration import NonlinearRig, parse_camera_response

    given = {key: getattr(args, name) for key, name in (
        ("projector_gamma", "projector_gamma"), ("projector_black", "projector_black"),
        ("projector_shoulder", "projector_shoulder"), ("bits", "bits"),
        ("full_well_electrons", "full_well"), ("read_noise", "read_noise"))
        if getattr(args, name) is not None}
    if args.camera_response is not None:  # a bad spelling: one CalibrationError line
        given["camera"] = parse_camera_response(args.camera_response)
    return NonlinearRig(**given, seed=args.seed)
