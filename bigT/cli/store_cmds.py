"""``bigT convert``, ``bigT export`` and ``bigT info``."""

from __future__ import annotations

import argparse
import json
import os
import sys

from .. import config
from ..atomic import refuse_overwriting_inputs
from ..sizes import format_size
from ._argtypes import image_size, integer, number
from ._options import add_json, add_size, deprecated

# The library's layers are imported inside each command's functions, where the
# command runs: building the parser imports every command module, and a command
# should pay only for the layers it uses (stores: zarr ~0.3 s; compensation ~0.5 s).


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "convert", help="convert a .npz/.mtx/.mat/.npy matrix into a bigT store",
        description="Convert a matrix file (scipy .npz, Matrix Market .mtx, MATLAB .mat, "
                    "dense .npy) into a bigT zarr block-CSR store; or, given a bigT store, "
                    "rewrite it in this bigT's store format (an upgrade: same tiles, "
                    "pixel order and metadata; the layout options do not apply).")
    p.add_argument("input", metavar="IN")
    p.add_argument("-o", "--output", required=True, metavar="OUT.zarr",
                   help="the bigT store to write")
    p.add_argument("--tile-size", type=integer(1), default=None,
                   help="rows/cols of one matrix tile (default "
                        f"{config.DEFAULT_TILE_SIZE})")
    p.add_argument("--var", default=None, help="variable of a .mat file")
    p.add_argument("--dtype", choices=("float32", "float64"), default=None,
                   help="value type of the store (default: the input's, float32 for "
                        "integer values; float32 halves the store of a float64 input)")
    p.add_argument("--image-shape", type=image_size, default=None, metavar="HxW",
                   help="the matrix maps HxW images (numbered row-major in IN)")
    p.add_argument("--pixel-order", choices=("row-major", "tile-major"), default="row-major",
                   help="pixel order of the store (needs --image-shape for tile-major)")
    p.add_argument("--channels", type=int, choices=(1, 3), default=1,
                   help="3 for a colour transport: IN is 3HW x 3HW with index 3(yW+x)+c, "
                        "c = 0, 1, 2 for R, G, B (needs --image-shape; default 1, grey)")
    p.add_argument("--image-tile", type=image_size, default=None, metavar="HxW",
                   help="image tile of the tile-major order (default "
                        f"{config.DEFAULT_IMAGE_TILE[0]}x{config.DEFAULT_IMAGE_TILE[1]})")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bigT store")
    p.set_defaults(func=convert_cmd)

    p = subparsers.add_parser("export", help="write a bigT store to .npz or .mtx",
                              description="Write a bigT store to scipy .npz or Matrix Market .mtx.")
    p.add_argument("store", metavar="STORE")
    p.add_argument("-o", "--output", required=True, metavar="OUT.{npz,mtx}",
                   help="the matrix file to write (.npz or .mtx)")
    p.add_argument("--order", choices=("row-major", "matrix"), default="row-major",
                   help="row-major image order (default; undoes a tile-major pixel order) or "
                        "the stored matrix order")
    add_size(p, "--max-size", dest="max_bytes", default=config.TO_SCIPY_MAX_BYTES,
             help="refuse a matrix whose CSR arrays would exceed this in memory")
    p.add_argument("--max-gb", dest="max_bytes", type=number(0, lo_open=True),
                   help=argparse.SUPPRESS,
                   action=deprecated("--max-size", lambda gb: int(gb * 1e9), format_size))
    p.set_defaults(func=export_cmd)

    p = subparsers.add_parser("info", help="summarise a bigT store",
                              description="Shape, nnz, tile fill, diagonal, size and metadata "
                                          "of a bigT store; checks that every chunk file exists.")
    p.add_argument("store", metavar="STORE")
    add_json(p, "the summary")
    p.set_defaults(func=info_cmd)


def convert_cmd(args) -> int:
    from ..storage import from_scipy
    from ..storage.convert import check_values, load_matrix
    from ..storage.locks import ReplaceLock

    from ..storage import is_url

    refuse_overwriting_inputs([args.output], [args.input])
    if is_url(args.input) or os.path.isdir(args.input):  # a store: rewritten, not loaded
        return _upgrade(args)
    # a second convert (or scene, or invert) of the same store is refused here, at once
    with ReplaceLock(args.output, "bigT convert"):
        A = load_matrix(args.input, var=args.var)
        check_values(A, args.input, args.dtype)  # errors name IN, not the store
        S = from_scipy(A, args.output, tile_size=args.tile_size, dtype=args.dtype,
                       image_shape=args.image_shape, pixel_order=args.pixel_order,
                       image_tile=args.image_tile, channels=args.channels,
                       input_order="row-major", overwrite=args.overwrite,
                       metadata={"source": str(args.input)})
    print(f"wrote {S.path}: {S.shape[0]} x {S.shape[1]} {S.dtype.name}, nnz {S.nnz}, "
          f"{S.n_tiles_stored} of {S.grid[0] * S.grid[1]} tiles stored")
    return 0


def _upgrade(args) -> int:
    """``bigT convert OLD.zarr -o NEW.zarr``: a store rewritten in this bigT's format."""
    from ..storage.locks import ReplaceLock
    from ..storage.upgrade import upgrade_store

    with ReplaceLock(args.output, "bigT convert"):
        S = upgrade_store(args.input, args.output, overwrite=args.overwrite, progress=None)
    print(f"wrote {S.path}: {S.shape[0]} x {S.shape[1]} {S.dtype.name}, nnz {S.nnz}, "
          f"store format {S.attrs.version}")
    return 0


def export_cmd(args) -> int:
    from ..storage import open as open_store
    from ..storage.convert import save_matrix

    S = open_store(args.store)
    refuse_overwriting_inputs([args.output], [args.store, S.path])
    A = S.to_scipy(max_bytes=args.max_bytes, output_order=args.order)
    out = save_matrix(A, args.output)
    print(f"wrote {out}: {A.shape[0]} x {A.shape[1]}, nnz {A.nnz}")
    return 0


def _fmt_bytes(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def info_cmd(args) -> int:
    from ..storage import open as open_store

    S = open_store(args.store)
    S.check_chunks_exist()
    info = S.info()
    if args.json:
        json.dump(info, sys.stdout, indent=2)
        print()
        return 0
    lines = [f"store        {info['path']}"
             + (f" (via redirect at {info['redirected_from']})" if info["redirected_from"] else "")]
    lines.append(f"shape        {info['shape'][0]} x {info['shape'][1]}  {info['dtype']}")
    lines.append(f"nnz          {info['nnz']}  (density {info['density']:.3g}, "
                 f"{info['nnz_per_row']:.1f} per row)")
    lines.append(f"tiles        {info['n_tiles_stored']} of {info['n_tiles_total']} stored "
                 f"({100 * info['tile_fill']:.1f} %), tile size {info['tile_size']}, "
                 f"grid {info['grid'][0]} x {info['grid'][1]}, inner format {info['inner_format']}")
    if info["diagonal_min"] is not None:
        lines.append(f"diagonal     min {info['diagonal_min']:.6g}  max {info['diagonal_max']:.6g}  "
                     f"zero entries {info['zero_diagonal']}")
    lines.append(f"on disk      {_fmt_bytes(info['bytes_on_disk'])}  "
                 f"(CSR in memory {_fmt_bytes(info['csr_bytes'])})")
    po = info["pixel_order"]
    if po:
        lines.append(f"pixel order  {po['pixel_order']}, image {po['image_shape'][0]} x "
                     f"{po['image_shape'][1]}" + (f", image tile {po['image_tile'][0]} x "
                                                   f"{po['image_tile'][1]}"
                                                   if po["pixel_order"] == "tile-major" else "")
                     + (", colour (3 channels, index 3p+c)" if po.get("channels", 1) == 3
                        else ""))
    else:
        lines.append("pixel order  none (the matrix maps no image)")
    if not info["complete"]:
        lines.append(f"INCOMPLETE   tile rows missing: {info['missing_tile_rows']}")
    lines += _metadata_lines(info["metadata"])
    print("\n".join(lines))
    return 0


def _short(value, width: int = 76) -> str:
    """A metadata value on one line: floats to 4 significant digits, long JSON cut."""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, str):
        return value if len(value) <= width else value[:width - 3] + "..."
    if isinstance(value, list) and all(isinstance(v, float) for v in value):
        text = "[" + ", ".join(f"{v:.3g}" for v in value) + "]"
    else:
        text = json.dumps(value)
    return text if len(text) <= width else text[:width - 3] + "..."


def _metadata_lines(metadata: dict) -> list[str]:
    """``metadata`` as the text of ``bigT info``: one line per key, the entries of a
    dictionary (the inverse engine's record, a scene's summary) one per line below it."""
    lines = []
    for key in sorted(metadata):
        value = metadata[key]
        if isinstance(value, dict):
            lines.append(f"metadata     {key}:")
            lines += [f"  {k:<22} {_short(v)}" for k, v in value.items()]
        else:
            lines.append(f"metadata     {key} = {_short(value)}")
    return lines
