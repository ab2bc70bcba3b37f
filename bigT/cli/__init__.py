"""The ``bigT`` command line.

Each group of sub-commands lives in its own module with a ``register(subparsers)``
function that adds its parsers and sets ``func`` to a callable taking the parsed
arguments and returning an exit status.

:func:`main` is the one boundary between the library's exceptions and the user: a bad
option (argparse, checked by the types of :mod:`bigT.cli._argtypes` before anything is
read), an error of the :class:`bigT.BigTError` hierarchy (the option it concerns, a
structured field, spelt as the command's flag: :func:`flag_of`), and an ``OSError`` (full disk,
read-only file system, no permission, a file where a folder is needed, ...) each become
one line on stderr, ``bigT CMD: error: [FILE: ]what happened``, and exit status 2, with
no traceback. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import os
import re
import sys
from typing import Callable

from .. import config
from ..errors import BigTError

#: A hidden sibling that a writer builds in and renames into place (bigT.storage's
#: ``.T.zarr.<pid>.<hex>.partial`` and ``.old``, ``.zarr.json.<pid>.<hex>.tmp``,
#: bigT.atomic's ``.out.<pid>.<hex>.tmp.npz``, a row's ``.3.<hex>.partial``): the user
#: never named it, so errors name the path it stands for.
_TEMPORARY = re.compile(r"(?<![^\s/(])\.(?P<name>[^\s/]+?)(?:\.\d+)?\.[0-9a-f]{6,}"
                        r"\.(?:tmp|partial|old)(?P<suffix>\.\w+)?(?=[\s/:;,)]|$)")


def cli_message(message: str) -> str:
    """``message`` on one line, each hidden temporary sibling replaced by the path it
    stands for."""
    message = _TEMPORARY.sub(lambda m: m["name"] + (m["suffix"] or ""), message)
    return message.replace("\n", " ")


_RERUN = ("completed work is kept: free space and rerun the same command; invert resumes "
          "where it stopped")

#: What the user can do about an OSError, by errno; the strerror says what happened.
OS_ERROR_HINTS = {
    errno.ENOSPC: _RERUN,
    getattr(errno, "EDQUOT", errno.ENOSPC): _RERUN,  # quota: not on every platform
    errno.EROFS: "choose an output on a writable disk",
    errno.EACCES: "check the permissions of the file and its folder",
    errno.EPERM: "check the permissions of the file and its folder",
    errno.EISDIR: "a file is needed here: choose a file name",
    errno.ENOTDIR: "a part of the path is a file where a folder is needed",
    errno.EEXIST: "choose another path, or remove it",
    errno.ENOTEMPTY: "choose another path, or empty the folder",
    errno.EMFILE: "raise the limit with ulimit -n and rerun",
}


def os_error_message(exc: OSError) -> str:
    """``FILE: what happened (what to do)`` for an OSError that reached the command line.

    Parameters
    ----------
    exc : OSError
        With ``filename`` (and ``filename2`` for a rename) when the system call named one.

    Returns
    -------
    str
        One line, the file first as in :class:`~bigT.BigTError` messages; the hint of
        :data:`OS_ERROR_HINTS` in parentheses.
    """
    what = exc.strerror or str(exc) or type(exc).__name__
    hint = OS_ERROR_HINTS.get(exc.errno)
    text = f"{what} ({hint})" if hint else what
    names = [str(os.fspath(n)) for n in (exc.filename, exc.filename2) if n is not None]
    return f"{' -> '.join(names)}: {text}" if names else text


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error: ``bigT CMD: error: argument --opt: what is
    wrong (bigT CMD --help)``, exit status 2 (argparse's own prints the whole usage
    first, which buries the line that says what is wrong). Sub-command parsers are
    made of this class too (``add_subparsers`` uses the parent's class).

    Options only one command needs (``invert``'s, which quote the engine's defaults from
    the light :mod:`bigT.algorithms.defaults`) are added by :meth:`defer`: when this
    parser parses its arguments or prints its help, so that ``bigT info`` or ``bigT
    --help`` does not build ``invert``'s."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._deferred: list[Callable[[argparse.ArgumentParser], None]] = []

    def defer(self, add_options: Callable[[argparse.ArgumentParser], None]) -> None:
        """Call ``add_options(self)`` when this parser is first used, after the
        options deferred before it (so the help lists them in the order given)."""
        self._deferred.append(add_options)

    def complete(self) -> _Parser:
        """Add the deferred options now; returns this parser."""
        while self._deferred:
            self._deferred.pop(0)(self)
        return self

    def parse_known_args(self, args=None, namespace=None):
        return super(_Parser, self.complete()).parse_known_args(args, namespace)

    def format_usage(self) -> str:
        return super(_Parser, self.complete()).format_usage()

    def format_help(self) -> str:
        return super(_Parser, self.complete()).format_help()

    def error(self, message: str):
        if message.endswith("expected one argument"):
            # argparse takes '--memory-limit -5GiB' for two options
            message += " (a value that starts with '-' is written --option=VALUE)"
        self.exit(2, f"{self.prog}: error: {cli_message(message)} (see {self.prog} --help)\n")


# Modules that contribute sub-commands, in the order their help is listed.
COMMAND_MODULES = (
    "bigT.cli.demo_cmd",       # demo
    "bigT.cli.store_cmds",     # convert, export, info
    "bigT.cli.verify_cmd",     # verify
    "bigT.cli.scene_cmd",      # scene
    "bigT.cli.acquire_cmds",   # acquire patterns, build, simulate
    "bigT.cli.invert_cmd",     # invert
    "bigT.cli.compensate_cmds",  # compensate, relight, bounces
)


#: The commands that write stores take --durability (config.DURABILITY for the run).
STORE_WRITERS = ("bigT convert", "bigT scene", "bigT invert", "bigT acquire build")


def build_parser(*, complete: bool = True) -> argparse.ArgumentParser:
    """The ``bigT`` parser, with a sub-parser for every command.

    Parameters
    ----------
    complete : bool
        True (default): every parser holds all its options, for a caller that reads
        them (``_actions``). False, as :func:`main` builds it: the options a command
        module defers (:meth:`_Parser.defer`) are added only to the parser that parses
        or prints its help, so that a command imports only the layers it uses.
    """
    parser = _Parser(
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
    # added after the command's own options, deferred or not, so that they come last
    for command in sub.choices.values():
        command.defer(_add_quiet)
    for command in _leaf_parsers(parser):
        command.defer(_add_storage_options)
    for command in _leaf_parsers(parser):
        command.set_defaults(_parser=command)
        if command.prog in STORE_WRITERS:
            command.defer(_add_durability)
    if complete:
        for command in (*sub.choices.values(), *_leaf_parsers(parser)):
            command.complete()
    return parser


def _add_quiet(command: argparse.ArgumentParser) -> None:
    command.add_argument("-q", "--quiet", action="store_true",
                         help="print nothing but errors and warnings: no progress bars, "
                         "no summary (the outputs are written as usual)")


def _add_storage_options(command: argparse.ArgumentParser) -> None:
    from ._argtypes import json_object

    command.add_argument(
        "--storage-options", metavar="JSON", default=None, type=json_object,
        help="options of the object store for s3://, gs://, az:// paths, a JSON object "
             "(e.g. '{\"endpoint\": \"http://127.0.0.1:9000\", \"region\": "
             "\"eu-west-1\"}'); credentials come from the usual environment variables "
             "(AWS_ACCESS_KEY_ID, AWS_ENDPOINT_URL, ...)")


@contextlib.contextmanager
def _storage_options(args):
    """With ``--storage-options``: every URL of the run (and the worker processes it
    starts) gets them, through ``BIGT_STORAGE_OPTIONS``; checked before the run."""
    text = getattr(args, "storage_options", None)
    if text is None:
        yield
        return
    from ..storage.objects import OPTIONS_ENV, default_storage_options

    saved = os.environ.get(OPTIONS_ENV)
    os.environ[OPTIONS_ENV] = text
    try:
        default_storage_options()  # a StoreError, one line, for what is not an object
        yield
    finally:
        if saved is None:
            os.environ.pop(OPTIONS_ENV, None)
        else:
            os.environ[OPTIONS_ENV] = saved


def _add_durability(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--durability", choices=config.DURABILITY_LEVELS, default=None,
        help="full: every tile row and store is fsynced before it is marked "
             "complete, so a power cut loses no finished work; none: no fsync "
             "(faster; a killed process still loses nothing, a power cut may) "
             f"(default {config.DURABILITY})")


def _leaf_parsers(parser: argparse.ArgumentParser):
    """The parsers that run a command (``acquire build``, not ``acquire``)."""
    groups = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not groups:
        yield parser
    for group in groups:
        for child in dict.fromkeys(group.choices.values()):  # aliases listed once
            yield from _leaf_parsers(child)


def flag_of(parser: argparse.ArgumentParser | None, name: str) -> str | None:
    """The option string of ``parser`` that sets the library argument ``name`` (its
    ``dest``; a deprecated hidden alias is never named), None where it has none."""
    for action in getattr(parser, "_actions", ()):
        if action.dest == name and action.option_strings and action.help != argparse.SUPPRESS:
            return max(action.option_strings, key=len)
    return None


@contextlib.contextmanager
def _durability(args):
    """With ``--durability``: ``config.DURABILITY`` set for the command's run."""
    level = getattr(args, "durability", None)
    saved = config.DURABILITY
    config.DURABILITY = level or saved
    try:
        yield
    finally:
        config.DURABILITY = saved


@contextlib.contextmanager
def _quieted(args):
    """With ``--quiet``: progress off and standard output discarded while the command
    runs (errors and warnings go to standard error as always; ``info -q`` answers by
    its exit status alone, as ``grep -q`` does)."""
    if not getattr(args, "quiet", False):
        yield
        return
    if hasattr(args, "progress"):
        args.progress = False
    with open(os.devnull, "w") as sink, contextlib.redirect_stdout(sink):
        yield


def _error(args, message: str) -> int:
    print(cli_message(f"bigT {args.command}: error: {message}"), file=sys.stderr)
    return 2


def _advise_no_huge_pages() -> None:
    """Ask numpy not to advise transparent huge pages for its large arrays
    (``NUMPY_MADVISE_HUGEPAGE=0``, numpy's own switch, read when numpy is imported:
    a command imports it after this), unless the environment says otherwise.

    Why: where the kernel's ``transparent_hugepage/defrag`` is ``madvise`` (the
    default of many distributions, and this project's machines), a fault in an
    advised region may compact memory synchronously before it zeroes a 2 MiB page
    (numpy issue #31590). On this project's 2-core virtual machines the first touch
    of 1 GiB of fresh memory took 3.3-3.8 s advised against 0.7-1.0 s not; the dense
    384x512 corner's 4-term inverse (1.7 GiB peak) ran 13.9 s against 11.3-11.8 s
    (kernel time 8-9 s against 3.7-3.9 s), its products at the same speed.
    Set ``NUMPY_MADVISE_HUGEPAGE=1`` to keep numpy's default. A process that
    imported numpy before (a caller of :func:`main` in Python) keeps its own, and its
    environment is left as it was."""
    if "numpy" not in sys.modules:
        os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


def main(argv: list[str] | None = None) -> int:
    """Run ``bigT`` with ``argv`` (default ``sys.argv[1:]``).

    Returns
    -------
    int
        0 on success; 2 for a bad input of any kind (one line on stderr); 130 when
        interrupted; 141 when the reader of stdout went away. ``--help`` and
        ``--version`` exit through ``SystemExit(0)`` as argparse has them.
    """
    _advise_no_huge_pages()
    parser = build_parser(complete=False)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        if exc.code == 2:  # a bad option, already reported on one line by _Parser
            return 2
        raise
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        with _quieted(args), _durability(args), _storage_options(args):
            return int(args.func(args) or 0)
    except BigTError as exc:
        parser_of_command = getattr(args, "_parser", None)
        return _error(args, exc.render(lambda name: flag_of(parser_of_command, name)))
    except BrokenPipeError:
        # the reader went away (`bigT info X.zarr | head`): not an error of ours; point
        # stdout at /dev/null so the interpreter's final flush does not complain
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a writer cut off
    except OSError as exc:  # after BrokenPipeError, an OSError too
        return _error(args, os_error_message(exc))
    except KeyboardInterrupt:
        print(f"bigT {args.command}: interrupted; finished work on disk is kept",
              file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
