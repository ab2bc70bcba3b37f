"""Outputs written whole or not at all.

Every file bigT writes for a user (an exported matrix, an image, a figure, a report)
goes through :func:`atomic_output`: it is written to a hidden sibling, flushed to disk,
checked, and renamed over the destination in one step. A full disk, a crash or an
error half way leaves the destination as it was (absent, or its old contents), never
a truncated file; the hidden sibling is deleted. Stores (directories) have their own
protocol (:mod:`bigT.storage.replace`); their small JSON files are replaced whole by
:func:`atomic_write_json`. No output may destroy an input of the same command
(:func:`refuse_overwriting_inputs`).
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import re
import socket
import uuid
from concurrent.futures import wait
from glob import escape as glob_escape
from pathlib import Path, PurePosixPath
from typing import Iterable, Iterator

from .errors import DiskFullError, OutputError
from .pools import named_pool


def _host_tag() -> str:
    """This machine's name as it goes into a hidden name: letters, digits and ``-``
    only (a dot would split the name's fields)."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:63] or "host"


def hidden_sibling(path: Path, kind: str, name: str | None = None) -> Path:
    """A fresh hidden name beside ``path``: ``.NAME.PID@HOST.HEX.KIND``, NAME default
    ``path``'s. The writer's PID and host in it tell a later run whether the writer is
    alive (:func:`dead_writers_siblings`); every temporary name bigT makes has this
    form. The host matters on a shared file system: a PID is only meaningful on the
    machine that issued it."""
    name = path.name if name is None else name
    return path.with_name(f".{name}.{os.getpid()}@{_host_tag()}.{uuid.uuid4().hex[:8]}.{kind}")


def dead_writers_siblings(parent: Path, kind: str, name: str | None = None) -> list[Path]:
    """The :func:`hidden_sibling` names of ``kind`` in ``parent`` (of ``name`` only,
    when given) whose writer process is gone, newest first.

    A name made on another host is never reported (its writer may be alive there: no
    PID says otherwise here); a name made before names carried the host
    (``.NAME.PID.HEX.KIND``) is taken as this host's, as it was then.
    """
    pattern = re.compile(r"\.(?P<name>.+)\.(?P<pid>\d+)(?:@(?P<host>[A-Za-z0-9-]+))?"
                         r"\.[0-9a-f]+\." + re.escape(kind))
    here = _host_tag()
    found = []
    for entry in Path(parent).glob(f".{glob_escape(name) if name else '*'}.*.{glob_escape(kind)}"):
        match = pattern.fullmatch(entry.name)
        if (match and (name is None or match["name"] == name)
                and match["host"] in (None, here)
                and not pid_alive(int(match["pid"]))):
            found.append(entry)
    return sorted(found, key=lambda p: p.lstat().st_mtime, reverse=True)


def temporary_file_sibling(path: Path) -> Path:
    """A fresh hidden name beside ``path`` that keeps its suffix (writers such as
    imageio and matplotlib choose the format from it)."""
    return hidden_sibling(path, f"tmp{path.suffix}", name=path.stem)


def _remove_dead_writers_files(path: Path) -> None:
    """Delete the temporary siblings of ``path`` that writers killed before their
    rename left."""
    remove_dead_writers_files(path.parent, path.suffix, name=path.stem)


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (always True on Windows, where
    ``os.kill(pid, 0)`` would terminate it: litter is then left, never deleted under a
    live writer)."""
    if os.name == "nt":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def _fsync_path(path: Path, directory: bool = False) -> None:
    # a file read-write (Windows flushes only handles open for writing); a directory
    # read-only, where the platform has O_DIRECTORY
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) if directory else os.O_RDWR
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# --- durability: what a power cut may not undo --------------------------------------
#
# The store protocol publishes by rename (a tile row's directory, a store, a marker,
# the redirect). A rename is atomic against a crash of the process, but after a power
# cut the kernel may have written the rename and not the data it publishes: a row
# marked complete over chunks that are zeros. So, as SQLite and LMDB order theirs:
# every file is fsynced before the rename that publishes it, and the directory after
# the rename (the rename itself is durable only then). The store writers call these
# when config.DURABILITY asks (bigT.storage.replace.durable decides).


def fsync_file(path: str | os.PathLike) -> None:
    """Flush the file ``path``'s data to disk."""
    # read-only is enough on POSIX (and is no write for the crash harness to count);
    # Windows flushes only handles open for writing
    fd = os.open(path, os.O_RDWR if os.name == "nt" else os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(path: str | os.PathLike) -> None:
    """Make the entries of directory ``path`` (names created, renamed or deleted in
    it) durable. A no-op where directories cannot be opened (Windows) or the file
    system refuses (EINVAL, EBADF: some network file systems)."""
    if os.name != "nt":
        with contextlib.suppress(OSError):
            _fsync_path(Path(os.fspath(path)), directory=True)


#: Threads that issue the fsyncs of :func:`fsync_trees` together. Why: fsyncs waiting
#: at once are made durable by one journal commit (ext4's jbd2 commits for all of them),
#: where one after the other each waits for a commit of its own, and, while other
#: processes write, for the journal's batching delay too: a tile row's 12 fsyncs took
#: 30-50 ms one after the other and 1-1.6 ms together on this project's machine under
#: load (issue #30: most of the write of an n = 1000 term); 2, 4 and 8 threads alike
#: took 1-1.5 ms. All started when the pool is made (:func:`bigT.pools.named_pool`).
FSYNC_THREADS = 4


def _fsync_together(func, paths: list[str]) -> None:
    """``func(path)`` for every path at once on the fsync threads (in this thread when
    there is one); returns when all are done, raising the first error in order."""
    if len(paths) <= 1:
        for path in paths:
            func(path)
        return
    pool = named_pool("fsync", FSYNC_THREADS, started=True)
    futures = [pool.submit(func, path) for path in paths]
    wait(futures)
    for future in futures:
        future.result()


def fsync_tree(root: str | os.PathLike, include_root: bool = True) -> None:
    """fsync every file below ``root``, then every directory, ``root`` included
    (left to the caller with ``include_root=False``, when a file it writes next fsyncs
    it): one pass over what was just written (a tile row's chunks), before the marker
    that says it is complete (:func:`fsync_trees`)."""
    fsync_trees([root], include_root)


def fsync_trees(roots: Iterable[str | os.PathLike], include_root: bool = True) -> None:
    """:func:`fsync_tree` of each of ``roots`` in one pass: the files below them all
    fsynced at once, then, once every file is, the directories at once (each
    directory after every file in it). When it returns everything is durable; the
    order among the files (among the directories) does not matter, as nothing reads
    the tree as complete before its caller's marker, written after."""
    files, folders = [], []
    for root in map(os.fspath, roots):
        for dirpath, _, filenames in os.walk(root, topdown=False):
            files += [os.path.join(dirpath, name) for name in filenames]
            if include_root or dirpath != root:
                folders.append(dirpath)
    _fsync_together(fsync_file, files)
    _fsync_together(fsync_dir, folders)


def _as_output_error(exc: OSError, path: Path, what: str) -> Exception:
    if exc.errno == errno.ENOSPC:
        return DiskFullError(f"disk full while writing {what}; nothing was replaced", path)
    reason = exc.strerror or str(exc)
    return OutputError(f"cannot write {what}: {reason}; nothing was replaced", path)


def remove_dead_writers_files(folder: str | os.PathLike, suffix: str,
                              name: str | None = None) -> None:
    """Delete the temporary files with ``suffix`` (of ``name`` only, when given) that
    writers killed before their rename left in ``folder``: what :func:`atomic_output`
    does for its own file, and once for a folder of many (``clean=False`` then)."""
    for entry in dead_writers_siblings(Path(os.fspath(folder)), f"tmp{suffix}", name=name):
        with contextlib.suppress(OSError):
            entry.unlink()


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, what: str = "the output", *, clean: bool = True,
                  sync_folder: bool = True) -> Iterator[Path]:
    """Write a file through a temporary sibling, then rename it into place.

    Parameters
    ----------
    path : the destination file; its folder is created when missing.
    what : words for the error messages ("the exported matrix").
    clean : delete the temporary siblings of ``path`` that killed writers left. False
        where the caller cleans the folder once for many files
        (:func:`remove_dead_writers_files`): each scan reads the whole folder.
    sync_folder : fsync the folder after the rename, which makes the rename itself
        durable. False where the caller fsyncs the folder once after many files
        (:func:`fsync_dir`): the file is still fsynced before its rename, so after a
        power cut it is whole or absent, never torn; only its presence waits for the
        caller's fsync.

    Yields
    ------
    Path
        Where to write (same folder and suffix as ``path``).

    Raises
    ------
    OutputError, DiskFullError
        The file could not be written; ``path`` is untouched and the sibling deleted.
    """
    path = Path(os.fspath(path))
    if path.is_dir():
        raise OutputError(f"is a folder; {what} is a file: choose a file name", path)
    tmp = temporary_file_sibling(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if clean:
            _remove_dead_writers_files(path)
        yield tmp
        if not tmp.is_file() or tmp.stat().st_size == 0:
            raise OutputError(f"writing {what} produced no data; nothing was replaced", path)
        _fsync_path(tmp)
        os.replace(tmp, path)
        if sync_folder:
            with contextlib.suppress(OSError):  # the rename's durability; not on every FS
                _fsync_path(path.parent, directory=True)
    except OSError as exc:
        _discard(tmp)
        raise _as_output_error(exc, path, what) from exc
    except BaseException:
        _discard(tmp)
        raise


def _discard(tmp: Path) -> None:
    with contextlib.suppress(OSError):
        tmp.unlink()


def atomic_write_json(path: Path, obj: dict, durable: bool = True) -> None:
    """Write ``obj`` as JSON to ``path`` via a temporary file and ``os.replace``.

    A reader sees the old file or the new one, never a torn one; this is what makes
    the tile-row completion markers and metadata updates atomic. With ``durable``
    the file is fsynced before the rename and its directory after, so a power cut
    too leaves the old file or the new one.
    """
    text = json.dumps(obj, indent=2, allow_nan=False)
    tmp = hidden_sibling(path, "tmp")
    try:
        with io.open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
        if durable:
            fsync_dir(path.parent)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def remove_stale_temp_files(directory: Path) -> int:
    """Delete the temporary files of :func:`atomic_write_json` (``.NAME.PID.ID.tmp``)
    in ``directory`` whose writer process is gone (killed between writing and
    renaming). Returns how many were deleted."""
    gone = 0
    for entry in dead_writers_siblings(Path(directory), "tmp"):
        with contextlib.suppress(OSError):
            entry.unlink()
            gone += 1
    return gone


def refuse_overwriting_inputs(outputs: Iterable, inputs: Iterable, *,
                              folders: Iterable = ()) -> None:
    """Refuse, before anything is written, an output that would destroy an input of
    the same call.

    Paths are compared after resolving symbolic links and ``..`` (and by device and
    inode where both exist, so a hard link or a case-insensitive spelling is caught).
    Every command and library entry point that writes calls this with all of its
    outputs and inputs, so ``bigT compensate X in.png -o in.png`` is one line, never
    a lost input.

    Parameters
    ----------
    outputs : paths replaced whole when written (a file, a store): refused when one
        is an input, lies inside an input (a folder of frames, a store), or holds one.
    inputs : paths read (files, folders of frames, stores); None entries are skipped.
    folders : folders written into (files added beside what they hold): refused when
        one is an input or lies inside one. An input inside such a folder is safe
        unless a file written there is that input: list those files in ``outputs``.

    Raises
    ------
    OutputError
        Naming the output (as the path) and the input, and how they meet.
    """
    sources = [(inp, _resolved(inp)) for inp in inputs if inp is not None]
    # folders first: a folder that is an input is named as such, not its first file
    for out, replaced_whole in [(f, False) for f in folders if f is not None] + [
            (o, True) for o in outputs if o is not None]:
        real = _resolved(out)
        for inp, real_inp in sources:
            if type(real) is not type(real_inp):  # a URL and a local path never meet
                continue
            if _same_file(real, real_inp):
                raise OutputError(f"is the input {_text(inp)}: writing it would destroy "
                                  "the input; choose another output", _text(out))
            if _lies_within(real, real_inp):
                raise OutputError(f"lies inside the input {_text(inp)}: writing it would "
                                  "change the input; choose an output outside it", _text(out))
            if replaced_whole and _lies_within(real_inp, real):
                raise OutputError(f"holds the input {_text(inp)}, which writing it would "
                                  "replace; choose another output", _text(out))


def _text(path) -> str:
    return os.fspath(path) if isinstance(path, (str, os.PathLike)) else str(path)


def _resolved(path) -> "Path | PurePosixPath":
    """A local path resolved (links, ``..``); a URL of object storage (a string with
    ``://``, or a store location that is not os.PathLike) as its key path, which has
    no links to resolve."""
    text = os.fspath(path) if isinstance(path, (str, os.PathLike)) else str(path)
    if "://" not in text:
        return Path(os.path.realpath(text))
    scheme, rest = text.split("://", 1)
    scheme = scheme.lower()
    if scheme == "file":
        return Path(os.path.realpath(rest))
    # one bucket under any of its spellings (S3:// and s3a:// are s3://)
    scheme = _SCHEME_ALIASES.get(scheme, scheme)
    return PurePosixPath("/" + scheme, *[p for p in rest.split("/") if p not in ("", ".")])


#: URL schemes that name the same object storage as another (what bigT.storage maps).
_SCHEME_ALIASES = {"s3a": "s3", "gcs": "gs", "azure": "az"}


def _same_file(a: Path, b: Path) -> bool:
    """``a`` and ``b`` (resolved) name one file: equal, or one inode where both exist."""
    if a == b:
        return True
    if not isinstance(a, Path):  # keys of object storage: their names are all they are
        return False
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet): only the names could tell
        return False


def _lies_within(inner: Path, outer: Path) -> bool:
    """``inner`` (resolved) is strictly below the folder ``outer`` (resolved)."""
    return any(_same_file(parent, outer) for parent in inner.parents)
