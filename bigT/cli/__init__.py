"""The ``bigT`` command line.

Each group of sub-commands lives in its own module with a ``register(subparsers)``
function that adds its parsers and sets ``func`` to a callable taking the parsed
arguments and returning an exit status. Errors from the :class:`bigT.BigTError`
hierarchy are printed on one line to stderr with exit status 2, no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import BigTError

# Modules that contribute sub-commands, in the order their help is listed.
COMMAND_MODULES = (
    "bigT.cli.demo_cmd",       # demo
    "bigT.cli.store_cmds",     # convert, export, info
    "bigT.cli.scene_cmd",      # scene
    "bigT.cli.invert_cmd",     # invert
    "bigT.cli.compensate_cmds",  # compensate, relight, bounces
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bigT",
        description="Out-of-core stratified inversion of light-transport matrices "
        "stored as zarr v3 block-CSR.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:  # a real import error inside the module
                raise
            continue
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except BigTError as exc:
        print(f"bigT {args.command}: error: {exc}".replace("\n", " "), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bigT {args.command}: interrupted; finished work on disk is kept",
              file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
