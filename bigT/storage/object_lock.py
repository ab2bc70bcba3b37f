"""One writer per store in object storage: a lock object that is also a lease.

A bucket has no ``flock`` that the kernel drops with a dead process, so the lock is an
object created only where none is (``If-None-Match: *``): of two writers one creates
it, the other is refused with the first one's name. The holder renews it (a
conditional overwrite of its own version, ``If-Match``) every quarter of
``config.OBJECT_LOCK_SECONDS`` from a daemon thread, and releases it by overwriting it,
again conditionally, with a *released* record (never by a deletion, which could remove
a lock another writer took over meanwhile). A lock that is released, not renewed for
``OBJECT_LOCK_SECONDS``, or held by a process of this machine (same host, boot and PID
namespace) that is gone, is free: the next writer takes it over by the same conditional
overwrite of the version it read, which exactly one taker wins.

A holder that loses its lock (its renewal refused: another writer took it over after
the holder was frozen past the lease) knows it: :meth:`ObjectLock.check_held` raises,
and the inverse store checks before it publishes a term.

What is not guaranteed: a writer frozen for longer than the lease may finish the row
it was writing when it wakes; a clock more than the lease away from the server's makes
a live lock look abandoned. docs/FORMAT.md says so.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from datetime import datetime, timezone

from .. import config
from ..atomic import pid_alive
from ..errors import StoreError
from .objects import ObjectPath, request_error

#: The most of a lock object read (its record is ~200 bytes).
LOCK_MAX_BYTES = 4096


def _machine() -> dict:
    """What makes a PID meaningful: the host, its boot, the PID namespace (two
    containers of one host share its name, not their PIDs)."""
    def read(path):
        try:
            with open(path) as f:
                return f.read().strip()
        except OSError:
            return None

    try:
        pidns = os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        pidns = None
    return {"host": socket.gethostname(), "boot": read("/proc/sys/kernel/random/boot_id"),
            "pidns": pidns}


class ObjectLock:
    """An exclusive, non-blocking lock held by this process on the object ``obj``.

    Parameters
    ----------
    obj : ObjectPath, the lock object's key.
    command : what holds it, for the message a second writer gets.
    store : the store it guards, named in that message.
    """

    def __init__(self, obj: ObjectPath, command: str, store):
        self.obj, self.command, self.store = obj, command, store
        self._etag: str | None = None
        self.lost = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def held(self) -> bool:
        return self._etag is not None

    def _body(self, released: bool = False) -> bytes:
        return json.dumps({"command": self.command, "pid": os.getpid(), **_machine(),
                           "since": time.strftime("%Y-%m-%d %H:%M:%S"),
                           "released": released}).encode()

    def _put(self, body: bytes, mode) -> str:
        """The ETag of a conditional PUT of the lock object; a refused condition raises
        obstore's error, anything else a one-line StoreError."""
        import obstore

        try:
            return obstore.put(self.obj.store, self.obj.key, body, mode=mode,
                               use_multipart=False)["e_tag"]
        except Exception as exc:
            if _lost_race(exc):
                raise
            raise request_error(exc, self.obj) from None

    def acquire(self) -> "ObjectLock":
        if self.held:
            return self
        try:
            self._etag = self._put(self._body(), "create")
        except StoreError:
            raise
        except Exception:  # there already: free (released, abandoned) or held
            self._take_over_if_free()
        self.lost = False
        self._stop.clear()
        self._thread = threading.Thread(target=self._renew, daemon=True,
                                        name="bigT-object-lock")
        self._thread.start()
        return self

    def _take_over_if_free(self) -> None:
        import obstore

        try:
            got = obstore.get(self.obj.store, self.obj.key)
            meta = got.meta
            raw = bytes(got.bytes()) if meta["size"] <= LOCK_MAX_BYTES else b""
        except FileNotFoundError:  # deleted meanwhile (an older bigT): create it
            meta = None
        except Exception as exc:
            raise request_error(exc, self.obj) from None
        if meta is not None:
            holder = _holder(raw)
            age = (datetime.now(timezone.utc) - meta["last_modified"]).total_seconds()
            if not (holder.get("released") is True or _gone(holder)
                    or age >= config.OBJECT_LOCK_SECONDS):
                raise StoreError(f"is being written by {_describe(holder)}, its lock renewed "
                                 f"{age:.0f} s ago; wait for it to finish or stop it (a "
                                 "second writer would corrupt it)", self.store)
        try:
            self._etag = self._put(self._body(), "create" if meta is None
                                   else {"e_tag": meta["e_tag"]})
        except StoreError:
            raise
        except Exception:
            raise StoreError("another writer took its lock at the same moment; it is "
                             "being written", self.store) from None

    def _renew(self) -> None:
        period = max(0.05, config.OBJECT_LOCK_SECONDS / 4)
        while not self._stop.wait(period):
            with self._lock:
                if self._etag is None:
                    return
                try:
                    self._etag = self._put(self._body(), {"e_tag": self._etag})
                except StoreError:
                    continue  # the server unreachable for now: the next period retries
                except Exception:  # refused: another writer holds it now
                    self.lost = True
                    self._etag = None
                    return

    def check_held(self) -> None:
        """StoreError when this process lost the lock it held (taken over by another
        writer once its renewals stopped for longer than the lease)."""
        if self.lost:
            raise StoreError("lost its writer lock to another writer (this process was "
                             f"stopped for over {config.OBJECT_LOCK_SECONDS:.0f} s); "
                             "nothing more is published by it", self.store)

    def release(self) -> None:
        self._stop.set()
        with self._lock:
            etag, self._etag = self._etag, None
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None
        if etag is not None:
            try:  # released only if still ours: never another writer's lock
                self._put(self._body(released=True), {"e_tag": etag})
            except Exception:  # taken over, or unreachable: it expires by itself
                pass


def _gone(holder: dict) -> bool:
    """Whether the lock's holder was a process of this machine (host, boot, PID
    namespace all equal) that no longer runs."""
    here = _machine()
    same = all(holder.get(k) == here[k] for k in ("host", "boot", "pidns"))
    return same and isinstance(holder.get("pid"), int) and not pid_alive(holder["pid"])


def _lost_race(exc: Exception) -> bool:
    """Whether obstore's ``exc`` is a conditional write refused (the object is there,
    or changed since it was read, or gone)."""
    name = type(exc).__name__.lower()
    return (isinstance(exc, (FileExistsError, FileNotFoundError)) or "exist" in name
            or "precondition" in name or "notfound" in name)


def _holder(raw: bytes) -> dict:
    try:
        holder = json.loads(raw)
    except ValueError:
        return {}
    return holder if isinstance(holder, dict) else {}


def _describe(holder: dict) -> str:
    return (f"{holder.get('command', 'another process')!s:.80} (PID {holder.get('pid')!s:.12} "
            f"on {holder.get('host')!s:.80}, since {holder.get('since')!s:.30})")
