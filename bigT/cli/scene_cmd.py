"""``bigT scene``: build a synthetic scene (bigT.scenes) with its ground truth."""

from __future__ import annotations

import json

from .. import config
from ._argtypes import density, image_size, integer, number
from ._options import add_json, add_memory_limit, add_progress

# The library's layers are imported inside each command's functions, where the
# command runs: building the parser imports every command module, and a command
# should pay only for the layers it uses (stores: zarr ~0.3 s; compensation ~0.5 s).


def register(subparsers) -> None:
    from ..scenes import DENSITIES, SCENE_NAMES

    p = subparsers.add_parser(
        "scene", help="build a synthetic projector-camera scene with known ground truth",
        description="Build a synthetic scene's light transport T = (I - A)^-1 F (radiosity, "
                    "Lambertian form factors, paper eq. 6) tile row by tile row into a bigT "
                    "store, with its ground truth (A, F, spectral radius, bounce shares) in "
                    "the store's ground_truth/ group and a preview PNG of T 1 beside it. "
                    "An interrupted build resumes when run again with the same parameters. "
                    "dihedral4 is the paper's 4x4 example (eq. 34).")
    p.add_argument("name", choices=SCENE_NAMES)
    p.add_argument("--size", type=image_size, default=None, metavar="HxW",
                   help="image size (default: 96x128; cornell 64x80 = 5120 patches)")
    p.add_argument("-o", "--output", required=True, metavar="T.zarr",
                   help="the transport store to write (with its ground truth)")
    p.add_argument("--albedo", type=number(0, 1, lo_open=True, hi_open=True), default=0.6,
                   help="Lambertian albedo in (0, 1) (default %(default)s)")
    p.add_argument("--density", type=density(DENSITIES), default=None,
                   metavar="|".join(DENSITIES) + "|CUT",
                   help="preset of (form-factor cut, threshold), or a form-factor cut; "
                        "default exact up to 1024 pixels, sparse beyond")
    p.add_argument("--ff-cut", type=number(0), default=None,
                   help="drop patch pairs whose form factor is below this (sparsity of A)")
    p.add_argument("--threshold", type=number(0), default=None,
                   help="truncate T: entries and bounces below this are dropped (0: exact)")
    p.add_argument("--noise", type=number(0), default=0.0, help="std of additive camera noise")
    p.add_argument("--noise-floor", type=number(0), default=None,
                   help="entries below this are dropped after the noise (default 3 x noise)")
    p.add_argument("--blur", type=number(0), default=0.0,
                   help="projector defocus: Gaussian std in pixels (0: none)")
    p.add_argument("--seed", type=integer(0), default=0,
                   help="seed of the noise (default %(default)s)")
    p.add_argument("--tile-size", type=integer(1), default=None,
                   help=f"rows/cols of one matrix tile (default {config.DEFAULT_TILE_SIZE}; "
                        f"colour {config.DEFAULT_COLOUR_TILE_SIZE}, a multiple of 3)")
    p.add_argument("--pixel-order", choices=("tile-major", "row-major"), default="tile-major",
                   help="pixel order of the store (default %(default)s)")
    p.add_argument("--colour", "--color", action="store_true",
                   help="an RGB scene: per-surface RGB albedo (cornell: red left and green "
                        "right walls; corner: orange and blue walls), a colour store "
                        "(3 H W values, index 3 p + c), mixed by a projector-camera rig "
                        "with realistic cross-talk")
    p.add_argument("--mixing", choices=("global", "per-pixel"), default=None,
                   help="with --colour: one camera and projector 3x3 mixing for the whole "
                        "rig (the default; recorded in T's metadata), or one varying by a "
                        "few percent per pixel (so that T has no global factorisation)")
    p.add_argument("--dtype", choices=("float32", "float64"), default=None,
                   help="dtype of T's values (default float32; dihedral4 float64)")
    add_memory_limit(p, default=config.SCENE_IN_MEMORY_BYTES,
                     bounds="memory the build may hold of A and T, e.g. 4GiB: a matrix "
                     "within it is read whole once, a larger one tile row by tile row")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bigT store")
    p.add_argument("--no-preview", action="store_true", help="do not write the preview PNG")
    add_progress(p)
    add_json(p)
    p.set_defaults(func=scene_cmd)


def scene_cmd(args) -> int:
    from ..errors import BigTError
    from ..scenes import make
    from ..storage.locks import ReplaceLock

    kwargs = dict(overwrite=args.overwrite, preview=not args.no_preview)
    if args.dtype:
        kwargs["dtype"] = args.dtype
    if args.name != "dihedral4":
        kwargs.update(albedo=args.albedo, density=args.density, ff_cut=args.ff_cut,
                      threshold=args.threshold, noise=args.noise, noise_floor=args.noise_floor,
                      blur=args.blur, seed=args.seed, tile_size=args.tile_size,
                      pixel_order=args.pixel_order, memory_limit=args.memory_limit,
                      progress=None if args.progress else False,
                      colour=args.colour, mixing=args.mixing or "global")
    elif args.colour:
        raise BigTError("dihedral4 is the paper's grey 4x4 example: it has no --colour")
    if args.mixing and not args.colour:
        raise BigTError("--mixing is the colour rig's: give it with --colour")
    # a second scene (or convert, or invert) of the same store is refused here, at once
    with ReplaceLock(args.output, "bigT scene"):
        scene = make(args.name, args.size, args.output, **kwargs)
    if args.json:
        print(json.dumps(scene.summary, indent=1))
    else:
        print(scene.describe())
        print(f"-> {scene.path}")
    return 0
