"""Crash-point injection: run a command in a forked child that dies (``os._exit``, as
under SIGKILL: no ``finally``, no cleanup) just before its k-th file-system mutation,
then rerun it and compare, for every k, as SQLite's crash tests do.

The mutations counted are the calls that change what is on disk: ``os.replace``,
``os.rename``, ``os.unlink``/``os.remove``, ``os.rmdir``, ``os.mkdir``, ``os.link``, ``os.fsync``
(the file written, not yet renamed) and every ``open`` for writing. ``shutil.rmtree``
and ``os.makedirs`` go through them, so a crash half way through a deletion is tried
too.
"""

from __future__ import annotations

import builtins
import contextlib
import io
import json
import os
import re
import traceback

CRASH_STATUS = 137  # what a shell reports for a SIGKILLed process
_WRITE_MODES = set("wax+")
_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND


class _Counter:
    """Counts mutations, each with its kind (:func:`kind_of`); dies before the one
    numbered ``crash_at`` (1-based)."""

    def __init__(self, crash_at: int | None, fail_with: int | None = None):
        self.crash_at = crash_at
        self.fail_with = fail_with
        self.kinds: list[str] = []

    def tick(self, op: str, path) -> None:
        self.kinds.append(kind_of(op, path))
        if len(self.kinds) != self.crash_at:
            return
        if self.fail_with is None:
            os._exit(CRASH_STATUS)
        # the failure a full (ENOSPC) or read-only (EROFS) disk gives at this call
        raise OSError(self.fail_with, os.strerror(self.fail_with), os.fspath(path)
                      if not isinstance(path, int) else None)


def kind_of(op: str, path) -> str:
    """``op`` and the path's last three parts with numbers, PIDs and random hex
    replaced: the crash points of one kind (say, the data chunk of any tile) share it."""
    if isinstance(path, int):
        return f"{op} <fd>"
    parts = os.fspath(path).split(os.sep)
    # the term directory (t0001) keeps its number: the same write in another term is
    # another point, the store holding other things by then
    term = next((p for p in parts if re.fullmatch(r"t\d{4}", p)), "")
    tail = re.sub(r"\d+|[0-9a-f]{8,}", "#", "/".join(parts[-3:]))
    return f"{op} {term}:{tail}"


def _wrap(counter: _Counter, op: str, func, is_mutation=lambda *a, **k: True):
    def wrapper(*args, **kwargs):
        if is_mutation(*args, **kwargs):
            counter.tick(op, args[0] if args else "")
        return func(*args, **kwargs)
    return wrapper


def _opens_for_writing(file, mode="r", *args, **kwargs) -> bool:
    # /dev/null (--quiet's sink) is no file of the disk under test
    return bool(_WRITE_MODES & set(str(mode))) and file != os.devnull


def _os_open_writes(path, flags, *args, **kwargs) -> bool:
    return bool(flags & _WRITE_FLAGS)


def _install(counter: _Counter) -> dict:
    """Patch the module attributes (every caller looks them up at call time); returns
    the originals."""
    originals = {name: getattr(os, name) for name in _OS_MUTATIONS + ("open",)}
    originals["io.open"] = io.open
    for name in _OS_MUTATIONS:
        setattr(os, name, _wrap(counter, name, getattr(os, name)))
    os.open = _wrap(counter, "os.open", os.open, _os_open_writes)
    builtins.open = io.open = _wrap(counter, "open", io.open, _opens_for_writing)
    return originals


def _uninstall(originals: dict) -> None:
    builtins.open = io.open = originals.pop("io.open")
    for name, func in originals.items():
        setattr(os, name, func)


_OS_MUTATIONS = ("replace", "rename", "unlink", "remove", "rmdir", "mkdir", "fsync", "link")


def _fresh_dask_pools() -> None:
    """A forked child has none of the parent's threads: dask must start new pools."""
    import dask.threaded

    dask.threaded.default_pool = None
    dask.threaded.pools.clear()


def run_forked(argv: list[str], crash_at: int | None = None, fail_with: int | None = None,
               stderr_file: str | None = None) -> tuple[int, list[str]]:
    """Run ``bigT.cli.main(argv)`` in a forked child, dying before mutation
    ``crash_at`` (never, when None), or, with ``fail_with`` (an errno), making that
    call fail as a full or read-only disk would. Import bigT.cli and run once in the
    parent first: the children then start warm. The child's standard error goes to
    ``stderr_file`` (default: nowhere).

    Returns
    -------
    status : int
        The child's exit status (:data:`CRASH_STATUS` when it was made to die).
    kinds : list of str
        The kind of each mutation it made, in order (empty when it died).
    """
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child
        status = 1
        try:
            os.close(read_end)
            _fresh_dask_pools()
            from bigT import config

            # one thread mutates, so mutation k is the same one in every run (the
            # background deletion of dropped terms would interleave)
            config.BACKGROUND_REMOVAL = False
            counter = _Counter(crash_at, fail_with)
            from bigT.cli import main

            with open(os.devnull, "w") as sink, open(stderr_file or os.devnull, "w") as err, \
                    contextlib.redirect_stdout(sink), contextlib.redirect_stderr(err):
                originals = _install(counter)
                try:
                    status = main(argv)
                except BaseException:  # what a user would see: the traceback
                    traceback.print_exc()
                    raise
                finally:
                    _uninstall(originals)
            with os.fdopen(write_end, "w") as pipe:
                json.dump(counter.kinds, pipe)
        finally:
            os._exit(status)
    os.close(write_end)
    with os.fdopen(read_end) as f:
        reported = f.read()
    _, wait_status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(wait_status), json.loads(reported or "[]")


def first_of_each_kind(kinds: list[str]) -> list[int]:
    """The 1-based crash points where a kind of mutation occurs for the first time."""
    seen: set[str] = set()
    points = []
    for k, kind in enumerate(kinds, start=1):
        if kind not in seen:
            seen.add(kind)
            points.append(k)
    return points
