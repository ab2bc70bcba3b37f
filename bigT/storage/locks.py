"""Who writes a store, and which term directories readers still hold.

Both use ``flock`` on small files inside the store, so a process that dies (killed,
crashed, its machine rebooted) holds nothing: the kernel drops its locks with it,
and no stale lock needs cleaning.

* The **writer lock** (:class:`WriterLock`, file :data:`WRITER_LOCK` in the inverse
  store's root) is held exclusively by the one ``invert`` that extends the store; a
  second writer is refused at once with the first one's PID.
* The **replace lock** (:class:`ReplaceLock`, a hidden file beside a store) is held
  exclusively by the one ``convert`` or ``scene`` that writes the store whole and
  renames it into place, with the writer lock inside it where it has one: two
  commands never replace one store at once, nor one replace an inverse being extended.
* A **reader lease** (:class:`ReaderLease`, file :data:`READER_LEASE` in a published
  term's X store) is held shared by every reader that opened that term; the writer
  deletes an old term only when it can take the lease exclusively, else it leaves
  the term for a later clean-up (:func:`remove_unless_read`).

Where ``fcntl`` is missing (Windows), both are no-ops: one writer per store is then
the user's to ensure.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import socket
import threading
import time
import warnings
from pathlib import Path

from .. import config
from ..atomic import dead_writers_siblings, hidden_sibling
from ..errors import StoreError
from .object_lock import ObjectLock
from .objects import ObjectPath, as_location

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

#: errno values of a file system without flock (Lustre's noflock, NFS without lockd):
#: locking is then skipped, with a warning, rather than failing every open.
_NO_LOCKING = {errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP, errno.EINVAL}


def _flock(fd: int, operation: int) -> bool:
    """``flock(fd, operation)``; False (and a warning) where the file system has no
    locks. BlockingIOError (held by another) propagates."""
    try:
        fcntl.flock(fd, operation)
        return True
    except BlockingIOError:
        raise
    except OSError as exc:
        if exc.errno not in _NO_LOCKING:
            raise
        warnings.warn("this file system has no flock: bigT cannot stop a second writer "
                      "or keep a reader's term from deletion here", stacklevel=3)
        return False


#: The writer lock's file, in the root of an inverse store.
WRITER_LOCK = ".bigT-writer.lock"
#: The reader lease's file, in a published term's X store.
READER_LEASE = ".bigT-readers"


class _HeldFile:
    """A file descriptor whose ``flock`` lasts as long as it is open: closed by
    :meth:`release`, or when the object is collected."""

    _fd: int | None = None

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self):
        self.release()


def _lock_exclusively(file: Path, command: str, store: Path) -> int:
    """Open (creating) ``file`` and take its flock exclusively, without waiting; write
    who holds it (``command``, PID, host, time) into it for the next one's message.
    Returns the descriptor; StoreError naming ``store`` when another process holds it."""
    fd = os.open(file, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        _flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 200).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise StoreError(f"is being written by {holder}; wait for it to finish or stop "
                         "it (a second writer would corrupt it)", store) from None
    except BaseException:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.write(fd, f"{command} (PID {os.getpid()} on {socket.gethostname()}, since "
                 f"{time.strftime('%Y-%m-%d %H:%M:%S')})".encode())
    return fd


class WriterLock(_HeldFile):
    """An exclusive, non-blocking lock on ``root/WRITER_LOCK``.

    Parameters
    ----------
    root : the store directory (must exist).
    command : what holds it, for the message a second writer gets.
    """

    def __init__(self, root: str | os.PathLike, command: str = "bigT invert"):
        root = as_location(root)
        self.file = root / WRITER_LOCK
        self.command = command
        self._fd: int | None = None
        # in object storage, a lease object (no flock dies with a process there)
        self._object = ObjectLock(self.file, command, root) if isinstance(
            root, ObjectPath) else None

    def acquire(self) -> "WriterLock":
        if self._object is not None:
            self._object.acquire()
            return self
        if fcntl is None or self._fd is not None:
            return self
        self._fd = _lock_exclusively(self.file, self.command, self.file.parent)
        return self

    # release() drops the lock; the file stays (unlinking it would race a waiting writer)

    def release(self) -> None:
        if self._object is not None:
            self._object.release()
        super().release()

    def check_held(self) -> None:
        """StoreError when a lock in object storage was lost to another writer (a
        file's flock cannot be lost while its descriptor is open)."""
        if self._object is not None:
            self._object.check_held()

    def __enter__(self) -> "WriterLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


class ReplaceLock(_HeldFile):
    """An exclusive, non-blocking lock on replacing the store at ``path`` whole, taken
    by ``bigT convert`` and ``bigT scene`` for as long as they write.

    Its file is the hidden sibling ``.NAME.bigT-writer.lock`` beside ``path``, not a
    file inside it: the store may not exist yet, and the replace renames it away. The
    file is deleted on release (a run killed leaves it to the next, which takes it
    over). Where ``path`` holds a :class:`WriterLock` file (an inverse store), that
    lock is taken too, so a replace never runs under an ``invert``.

    Parameters
    ----------
    path : the store to replace (its parent must exist).
    command : what holds it, for the message a second writer gets.
    """

    def __init__(self, path: str | os.PathLike, command: str):
        self.path = as_location(path)
        self.file = self.path.with_name(f".{self.path.name}.bigT-writer.lock")
        self.command = command
        self._fd: int | None = None
        self._inner = WriterLock(self.path, command)
        self._object = ObjectLock(self.file, command, self.path) if isinstance(
            self.path, ObjectPath) else None

    def acquire(self) -> "ReplaceLock":
        if self._object is not None:
            self._object.acquire()
            return self._with_writer_lock()
        if fcntl is None or self._fd is not None:
            return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = _lock_exclusively(self.file, self.command, self.path)
            # the holder before us deletes the file as it releases: a lock taken on
            # the deleted file would lock nothing, so lock the file now at the name
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.file))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        self._fd = fd
        return self._with_writer_lock()

    def _with_writer_lock(self) -> "ReplaceLock":
        """The inverse's writer lock too, where the store has one: an inverse being
        extended is not replaced under its writer."""
        try:
            if (self.path / WRITER_LOCK).is_file():
                self._inner.acquire()
        except BaseException:
            self.release()
            raise
        return self

    def release(self) -> None:
        self._inner.release()
        if self._object is not None:
            self._object.release()
        if self._fd is not None:
            with contextlib.suppress(OSError):  # deleted before the lock is dropped
                os.unlink(self.file)
        super().release()

    def __enter__(self) -> "ReplaceLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


class ReaderLease(_HeldFile):
    """A shared lock on ``store/READER_LEASE`` while a reader holds the store open;
    a no-op for stores without the file (every store but a published term's X).

    ``valid`` is False when the writer deleted the store before the lease was taken
    (the reader then opens the redirect again).
    """

    def __init__(self, store: str | os.PathLike):
        self._fd: int | None = None
        self.valid = True
        store = as_location(store)
        if isinstance(store, ObjectPath):
            # no shared lock in a bucket: a dropped term is deleted at once, and a
            # reader of it then fails naming the missing row (docs/FORMAT.md)
            self.valid = (store / "zarr.json").is_file()
            return
        if fcntl is not None:
            try:
                self._fd = os.open(store / READER_LEASE, os.O_RDONLY)
            except FileNotFoundError:
                pass  # a store without readers' leases, or one being deleted: see below
            else:
                # blocks only while the writer holds it exclusively, to delete the term
                _flock(self._fd, fcntl.LOCK_SH)
        # the writer deletes a term after renaming it away: gone means deleted, and the
        # reader opens the redirect again
        self.valid = (store / "zarr.json").exists()
        if not self.valid:
            self.release()


def create_reader_lease(store: str | os.PathLike) -> None:
    """Give a store a lease file, before it is published to readers (none in object
    storage, where a lease cannot be held)."""
    store = as_location(store)
    if not isinstance(store, ObjectPath):
        Path(store, READER_LEASE).touch()


def _remove_tree(trash: Path, removals: list | None) -> None:
    """``rmtree(trash)``; in a thread of its own, appended to ``removals`` for the
    caller to join, when a list is given and ``config.BACKGROUND_REMOVAL`` is on. A
    process killed meanwhile leaves the trash to :func:`remove_trash`."""
    if removals is None or not config.BACKGROUND_REMOVAL:
        shutil.rmtree(trash, ignore_errors=True)
        return
    thread = threading.Thread(target=shutil.rmtree, args=(trash,), kwargs={"ignore_errors": True},
                              name=f"bigT-remove-{trash.name}")
    thread.start()
    removals.append(thread)


def _lease_files(directory: Path) -> list[Path]:
    """The lease files of the stores directly inside ``directory``, never through a
    symbolic link (a link, or ``directory`` itself a link, has none)."""
    if directory.is_symlink():
        return []
    try:
        with os.scandir(directory) as entries:
            return [Path(e.path, READER_LEASE) for e in entries
                    if e.is_dir(follow_symlinks=False)]
    except (FileNotFoundError, NotADirectoryError):
        return []


def remove_unless_read(directory: str | os.PathLike, removals: list | None = None) -> bool:
    """Delete ``directory`` unless a reader holds a lease on a store inside it (the
    deletion itself in a background thread, appended to ``removals``, when given).

    With every lease held exclusively, the directory is first renamed to a hidden
    ``.NAME.PID.HEX.trash`` sibling (one atomic step: a reader that then takes a lease
    finds the store gone and opens the redirect again, never a half-deleted store),
    then deleted. Trash of writers killed meanwhile goes with :func:`remove_trash`.

    Returns
    -------
    bool
        True when it is gone; False when a reader holds it (left for a later call).
    """
    directory = as_location(directory)
    if isinstance(directory, ObjectPath):
        directory.remove_tree()  # no leases there (ReaderLease): deleted at once
        return True
    held: list[int] = []
    try:
        # the leases of the stores directly inside, never through a link out of it
        for file in _lease_files(directory):
            try:
                # read-write: NFS emulates flock with byte-range locks, whose exclusive
                # form needs a descriptor open for writing
                held.append(os.open(file, os.O_RDWR | os.O_NOFOLLOW))
            except (FileNotFoundError, NotADirectoryError):
                continue
            except OSError as exc:
                if exc.errno != errno.ELOOP:  # a link is no lease: nothing to wait for
                    raise
                continue
            if fcntl is not None:
                _flock(held[-1], fcntl.LOCK_EX | fcntl.LOCK_NB)
        trash = hidden_sibling(directory, "trash")
        try:
            os.rename(directory, trash)
        except FileNotFoundError:
            return True
    except BlockingIOError:
        return False
    finally:
        for fd in held:
            os.close(fd)
    _remove_tree(trash, removals)
    return True


def remove_trash(parent: str | os.PathLike) -> None:
    """Delete the ``.trash`` directories in ``parent`` whose writer is gone (object
    storage has none: nothing is renamed there)."""
    if isinstance(parent, ObjectPath):
        return
    for entry in dead_writers_siblings(Path(os.fspath(parent)), "trash"):
        shutil.rmtree(entry, ignore_errors=True)
