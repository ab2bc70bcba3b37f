"""The ``bigT`` command line.

Each group of sub-commands lives in its own module with a ``register(subparsers)``
function that adds its parsers and sets ``func`` to a callable taking the parsed
arguments and returning an exit status. Errors from the :class:`bigT.BigTError`
hierarchy are printed on one line to stderr with exit status 2, no traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys

from ..errors import BigTError

#: Library wording in error messages -> the command line's (errors are raised by the
#: library, which names its Python arguments; the CLI user knows the flags).
CLI_WORDING = (
    ("pass overwrite=True (--overwrite)", "pass --overwrite"),
    ("overwrite=True", "--overwrite"),
    ("force=True (bigT invert --force)", "--force"),
    ("force=True", "--force"),
    ("first_bounce='diag'", "--first-bounce diag"),
    ("first_bounce='identity'", "--first-bounce identity"),
    ("first_bounce=", "--first-bounce "),
    ("resume writing with resume=True and finalize()", "rerun the command that wrote it"),
    ("resume writing with resume=True", "rerun the command that wrote it"),
    ("resume with resume=True", "rerun the same command to resume"),
    ("memory_limit", "--memory-limit"),
)


def cli_message(message: str) -> str:
    """``message`` on one line, in the command line's words (:data:`CLI_WORDING`)."""
    for python, flag in CLI_WORDING:
        message = message.replace(python, flag)
    return message.replace("\n", " ")

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
    from .. import __version__

    parser.add_argument("--version", action="version", version=f"bigT {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:  # a real import error inside the module
                raise
            continue
        module.register(sub)
    for command in sub.choices.values():
        command.add_argument("-q", "--quiet", action="store_true",
                             help="print nothing but errors and warnings: no progress "
                             "bars, no summary (the outputs are written as usual)")
    return parser


@contextlib.contextmanager
def _quieted(args):
    """With ``--quiet``: progress off and standard output discarded while the command
    runs (errors and warnings go to standard error as always; ``info -q`` answers by
    its exit status alone, as ``grep -q`` does)."""
    if not getattr(args, "quiet", False):
        yield
        return
    if hasattr(args, "no_progress"):
        args.no_progress = True
    if hasattr(args, "progress"):
        args.progress = False
    with open(os.devnull, "w") as sink, contextlib.redirect_stdout(sink):
        yield


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        with _quieted(args):
            return int(args.func(args) or 0)
    except BigTError as exc:
        print(cli_message(f"bigT {args.command}: error: {exc}"), file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader went away (`bigT info X.zarr | head`): not an error of ours; point
        # stdout at /dev/null so the interpreter's final flush does not complain
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a writer cut off
    except KeyboardInterrupt:
        print(f"bigT {args.command}: interrupted; finished work on disk is kept",
              file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
