"""One writer per store in object storage: a lock object that is also a lease.

A bucket has no ``flock`` that the kernel drops with a dead process, so the lock is an
object created only where none is (``If-None-Match: *``): of two writers one creates
it, the other is refused with the first one's name. The holder renews it (a
conditional overwrite of its own version, ``If-Match``) every quarter of
``config.OBJECT_LOCK_SECONDS`` from a daemon thread; one not renewed for that long, or
held by a process of this machine that is gone, is abandoned, and the next writer
takes it over by the same conditional overwrite, which exactly one taker wins.

What is not guaranteed: a writer frozen (suspended, partitioned from the bucket) for
longer than the lease still writes when it wakes; a clock more than the lease away
from the server's makes a live lock look abandoned. docs/FORMAT.md says so.
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
from .objects import ObjectPath


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
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def held(self) -> bool:
        return self._etag is not None

    def _body(self) -> bytes:
        return json.dumps({"command": self.command, "pid": os.getpid(),
                           "host": socket.gethostname(),
                           "since": time.strftime("%Y-%m-%d %H:%M:%S")}).encode()

    def acquire(self) -> "ObjectLock":
        import obstore

        if self.held:
            return self
        store, key = self.obj.store, self.obj.key
        try:
            self._etag = obstore.put(store, key, self._body(), mode="create")["e_tag"]
        except Exception as exc:
            if not _lost_race(exc):
                raise
            self._take_over_abandoned()
        self._stop.clear()
        self._thread = threading.Thread(target=self._renew, daemon=True,
                                        name="bigT-object-lock")
        self._thread.start()
        return self

    def _take_over_abandoned(self) -> None:
        import obstore

        store, key = self.obj.store, self.obj.key
        try:
            got = obstore.get(store, key)
            meta, raw = got.meta, bytes(got.bytes())
        except FileNotFoundError:  # released meanwhile: try once more from the start
            meta, raw = None, b""
        if meta is not None:
            holder = _holder(raw)
            age = (datetime.now(timezone.utc) - meta["last_modified"]).total_seconds()
            gone = (holder.get("host") == socket.gethostname()
                    and isinstance(holder.get("pid"), int) and not pid_alive(holder["pid"]))
            if not gone and age < config.OBJECT_LOCK_SECONDS:
                raise StoreError(f"is being written by {_describe(holder)}, its lock renewed "
                                 f"{age:.0f} s ago; wait for it to finish or stop it (a "
                                 "second writer would corrupt it)", self.store)
            mode = {"e_tag": meta["e_tag"]}
        else:
            mode = "create"
        try:
            self._etag = obstore.put(store, key, self._body(), mode=mode)["e_tag"]
        except Exception as exc:
            if not _lost_race(exc):
                raise
            raise StoreError("another writer took over its abandoned lock at the same "
                             "moment; it is being written", self.store) from None

    def _renew(self) -> None:
        import obstore

        period = max(0.05, config.OBJECT_LOCK_SECONDS / 4)
        while not self._stop.wait(period):
            with self._lock:
                if self._etag is None:
                    return
                try:
                    self._etag = obstore.put(self.obj.store, self.obj.key, self._body(),
                                             mode={"e_tag": self._etag})["e_tag"]
                except Exception:  # lost it (taken over after a freeze) or a network
                    return         # error: the next writer's takeover decides

    def release(self) -> None:
        self._stop.set()
        with self._lock:
            etag, self._etag = self._etag, None
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None
        if etag is not None:
            try:
                import obstore

                obstore.delete(self.obj.store, self.obj.key)
            except Exception:  # an abandoned lock is taken over by the next writer
                pass


def _lost_race(exc: Exception) -> bool:
    """Whether obstore's ``exc`` is a conditional write refused (the object is there,
    or changed since it was read)."""
    name = type(exc).__name__.lower()
    return isinstance(exc, FileExistsError) or "exist" in name or "precondition" in name


def _holder(raw: bytes) -> dict:
    try:
        holder = json.loads(raw)
    except ValueError:
        return {}
    return holder if isinstance(holder, dict) else {}


def _describe(holder: dict) -> str:
    return (f"{holder.get('command', 'another process')!s:.80} (PID {holder.get('pid')!s:.12} "
            f"on {holder.get('host')!s:.80}, since {holder.get('since')!s:.30})")
