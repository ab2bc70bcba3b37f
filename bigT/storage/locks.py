"""Who writes a store, and which term directories readers still hold.

Both use ``flock`` on small files inside the store, so a process that dies (killed,
crashed, its machine rebooted) holds nothing: the kernel drops its locks with it,
and no stale lock needs cleaning.

* The **writer lock** (:class:`WriterLock`, file :data:`WRITER_LOCK` in the inverse
  store's root) is held exclusively by the one ``invert`` that extends the store; a
  second writer is refused at once with the first one's PID.
* A **reader lease** (:class:`ReaderLease`, file :data:`READER_LEASE` in a published
  term's X store) is held shared by every reader that opened that term; the writer
  deletes an old term only when it can take the lease exclusively, else it leaves
  the term for a later clean-up (:func:`remove_unless_read`).

Where ``fcntl`` is missing (Windows), both are no-ops: one writer per store is then
the user's to ensure.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from pathlib import Path

from ..errors import StoreError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

#: The writer lock's file, in the root of an inverse store.
WRITER_LOCK = ".bigT-writer.lock"
#: The reader lease's file, in a published term's X store.
READER_LEASE = ".bigT-readers"


class WriterLock:
    """An exclusive, non-blocking lock on ``root/WRITER_LOCK``.

    Parameters
    ----------
    root : the store directory (must exist).
    command : what holds it, for the message a second writer gets.
    """

    def __init__(self, root: str | os.PathLike, command: str = "bigT invert"):
        self.file = Path(os.fspath(root)) / WRITER_LOCK
        self.command = command
        self._fd: int | None = None

    def acquire(self) -> "WriterLock":
        if fcntl is None or self._fd is not None:
            return self
        fd = os.open(self.file, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 200).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise StoreError(f"is being written by {holder}; wait for it to finish or stop "
                             "it (a second writer would corrupt it)", self.file.parent) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{self.command} (PID {os.getpid()}, since "
                     f"{time.strftime('%Y-%m-%d %H:%M:%S')})".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        """Drop the lock (the file stays: unlinking it would race a waiting writer)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self):
        self.release()

    def __enter__(self) -> "WriterLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


class ReaderLease:
    """A shared lock on ``store/READER_LEASE`` while a reader holds the store open;
    a no-op for stores without the file (every store but a published term's X).

    ``valid`` is False when the writer deleted the store before the lease was taken
    (the reader then opens the redirect again).
    """

    def __init__(self, store: str | os.PathLike):
        self._fd: int | None = None
        self.valid = True
        file = Path(os.fspath(store)) / READER_LEASE
        if fcntl is None:
            return
        try:
            fd = os.open(file, os.O_RDONLY)
        except OSError:
            return
        fcntl.flock(fd, fcntl.LOCK_SH)  # the writer holds it exclusively only to delete
        self._fd = fd
        self.valid = (Path(os.fspath(store)) / "zarr.json").exists()

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self):
        self.release()


def create_reader_lease(store: str | os.PathLike) -> None:
    """Give a store a lease file, before it is published to readers."""
    Path(os.fspath(store), READER_LEASE).touch()


def remove_unless_read(directory: str | os.PathLike) -> bool:
    """Delete ``directory`` unless a reader holds a lease on a store inside it.

    Returns
    -------
    bool
        True when it is gone; False when a reader holds it (left for a later call).
    """
    directory = Path(os.fspath(directory))
    held: list[int] = []
    try:
        try:
            for file in directory.rglob(READER_LEASE):
                held.append(os.open(file, os.O_RDONLY))
                if fcntl is not None:
                    fcntl.flock(held[-1], fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        except OSError:
            pass  # a lease file deleted meanwhile: nobody can hold it
        # deleted with the leases held, so no reader opens it half deleted
        shutil.rmtree(directory, ignore_errors=True)
    finally:
        for fd in held:
            os.close(fd)
    return not directory.exists()
