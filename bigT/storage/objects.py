"""Stores in object storage: :class:`ObjectPath`, a URL the store code uses like a path.

A store at ``s3://bucket/prefix/T.zarr`` (or ``gs://``, ``az://``, ``memory://``) is
the same tree of keys a local store is of files (docs/FORMAT.md), so the store code
keeps one shape: an :class:`ObjectPath` answers the few :class:`pathlib.Path`
questions it asks (``/``, ``name``, ``parent``, ``exists``, ``is_dir``, ``iterdir``)
with requests to the bucket, and the handful of operations a directory does
differently (an atomic rename, a hard link, an fsync, a lock file) take a branch of
their own where they are used (docs/FORMAT.md, "Object storage").

The I/O layer is obstore (Rust's ``object_store`` crate): one small wheel with no
Python dependencies, the S3, GCS and Azure clients and an in-memory store, the
standard environment variables (``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``,
``AWS_REGION``, ...), and conditional writes (``If-None-Match: *``) that make a
second writer of one object lose cleanly. It is what zarr-python's own
``ObjectStore`` is built on. ``benchmarks/bench_object_io.py`` measured it against s3fs
(fsspec) on moto over loopback, 50 objects: a 64 KiB get 4.7 ms against 46.9 ms, a
1 MiB get 18.6 ms against 46.5 ms, a 64 KiB put 8.7 ms against 28.4 ms, one request at
a time; 8 in flight, 1 MiB gets at 100 MB/s against 35 MB/s. s3fs would also bring
aiobotocore and its pinned botocore.

Keys are never followed anywhere: a key is a name, there are no links in a bucket,
so "no link followed out of a store" holds by construction; a redirect is a key
below the store's prefix (``_format.redirect_target`` checks it).
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from pathlib import PurePosixPath
from typing import Iterator, Mapping

from ..errors import StoreError

#: URL schemes served by the object layer ("file" is a local path, given to pathlib).
SCHEMES = ("s3", "s3a", "gs", "gcs", "az", "azure", "abfs", "abfss", "memory")


def is_url(text) -> bool:
    """Whether ``text`` names a store in object storage (``s3://...`` and the
    other :data:`SCHEMES`); an :class:`ObjectPath` is one too."""
    if isinstance(text, ObjectPath):
        return True
    if not isinstance(text, str) or "://" not in text:
        return False
    return text.split("://", 1)[0].lower() in SCHEMES


def url_scheme(text) -> str | None:
    """The scheme of a ``scheme://...`` string, lower-cased, or None."""
    if isinstance(text, str) and "://" in text:
        scheme = text.split("://", 1)[0]
        if scheme and scheme.replace("+", "").replace("-", "").replace(".", "").isalnum():
            return scheme.lower()
    return None


def _frozen_options(options: Mapping | None) -> tuple:
    """Storage options as a hashable, picklable tuple (nested dicts frozen too)."""
    def freeze(v):
        if isinstance(v, Mapping):
            return tuple(sorted((str(k), freeze(x)) for k, x in v.items()))
        return tuple(freeze(x) for x in v) if isinstance(v, list) else v
    return freeze(dict(options or {}))


def _thawed(options: tuple) -> dict:
    return {k: (_thawed(v) if isinstance(v, tuple) and v and isinstance(v[0], tuple) else v)
            for k, v in options}


@dataclass
class Traffic:
    """Requests and bytes this process exchanged with object storage (a benchmark's
    "bytes moved"); :data:`TRAFFIC` counts them."""

    requests: int = 0
    bytes_read: int = 0
    bytes_written: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add(self, read: int = 0, written: int = 0) -> None:
        with self._lock:
            self.requests += 1
            self.bytes_read += read
            self.bytes_written += written

    def snapshot(self) -> tuple[int, int, int]:
        """(requests, bytes read, bytes written) so far."""
        with self._lock:
            return self.requests, self.bytes_read, self.bytes_written


#: This process's traffic with object storage.
TRAFFIC = Traffic()

_STORES: dict = {}
_STORES_LOCK = threading.Lock()


def _bucket_store(base: str, options: tuple):
    """The obstore store of bucket URL ``base`` (``s3://bucket``) with ``options``,
    one per process (its connection pool is reused by every read; a memory store is
    one namespace per process, as a bucket is one per server)."""
    # the environment is part of the key: a client pointed at another endpoint or
    # account (AWS_ENDPOINT_URL changed) gets a store of its own
    env = tuple(sorted((k, v) for k, v in os.environ.items()
                       if k.startswith(("AWS_", "GOOGLE_", "AZURE_"))))
    # the in-process store is one namespace, whatever the options and environment
    key = (base,) if base.startswith("memory") else (base, options, env)
    with _STORES_LOCK:
        store = _STORES.get(key)
        if store is None:
            store = _STORES[key] = _new_store(base, _thawed(options))
        return store


def _new_store(base: str, options: dict):
    from obstore.store import from_url  # obstore: only for a store in object storage

    options = dict(options)
    client = dict(options.pop("client_options", {}) or {})
    endpoint = str(options.get("endpoint") or options.get("aws_endpoint")
                   or os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
                   or "")
    # an S3-compatible server on plain HTTP (MinIO, moto, Ceph on a LAN): what the
    # user's AWS_ENDPOINT_URL says is what they mean, as boto3 takes it
    if endpoint.startswith("http://") and base.startswith(("s3", "s3a")):
        client.setdefault("allow_http", True)
    try:
        if base.startswith("memory"):
            return from_url("memory:///")
        return from_url(base, client_options=client or None, **options)
    except Exception as exc:  # obstore raises its own types for a bad configuration
        raise StoreError(f"cannot open the object store ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0][:160]})", base) from None


class RequestError(StoreError):
    """A request to object storage failed (refused, unreachable, no such bucket): not
    an answer about what the bucket holds."""


def request_error(exc: Exception, url) -> StoreError:
    """obstore's error (a multi-line dump of the HTTP exchange) as one line naming
    ``url``: the server's error code where it sent one (NoSuchBucket, AccessDenied),
    else the first line."""
    import re

    text = str(exc)
    code = re.search(r"<Code>([^<]{1,80})</Code>", text)
    if code:
        what = code.group(1)
    elif "connect" in text.lower() or "dns" in text.lower():
        what = "cannot reach the server (check AWS_ENDPOINT_URL or the endpoint option)"
    else:
        what = text.strip().splitlines()[0][:160] if text.strip() else type(exc).__name__
    return RequestError(f"object storage request failed: {what}", url)


def _requests(method):
    """Run an :class:`ObjectPath` method with obstore's errors as one-line StoreErrors
    (a missing object stays FileNotFoundError, a refused conditional write stays
    what :meth:`ObjectPath.create` expects)."""
    import functools

    @functools.wraps(method)
    def wrapped(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except (FileNotFoundError, StoreError, ValueError):
            raise
        except Exception as exc:
            if _conditional_refusal(exc):
                raise
            raise request_error(exc, self) from None
    return wrapped


def _conditional_refusal(exc: Exception) -> bool:
    name = type(exc).__name__.lower()
    return isinstance(exc, FileExistsError) or "exist" in name or "precondition" in name


@dataclass(frozen=True)
class ObjectPath:
    """A key prefix in an object store, used by the store code like a directory path.

    Parameters
    ----------
    base : str
        Scheme and bucket, ``s3://bucket`` (``memory://`` for the in-process store).
    key : str
        The key prefix below the bucket, without leading or trailing ``/``.
    options : tuple
        Storage options (:func:`as_location` freezes a dict), passed to obstore's
        ``from_url``: ``endpoint``, ``region``, ``skip_signature``, ``client_options``...

    Notes
    -----
    Pickled as its URL and options, so a dask worker opens the bucket with its own
    credentials (its environment), never the client's.
    """

    base: str
    key: str
    options: tuple = field(default=(), repr=False)

    # --- what a path is ------------------------------------------------------------

    def __str__(self) -> str:
        return f"{self.base}/{self.key}" if self.key else self.base

    def __truediv__(self, other) -> "ObjectPath":
        parts = [p for p in str(other).split("/") if p not in ("", ".")]
        if ".." in parts:
            raise ValueError(f"'..' in a key: {other!r}")
        return ObjectPath(self.base, "/".join([self.key, *parts]) if self.key else "/".join(parts),
                          self.options)

    def joinpath(self, *parts) -> "ObjectPath":
        out = self
        for part in parts:
            out = out / part
        return out

    @property
    def name(self) -> str:
        return self.key.rsplit("/", 1)[-1]

    @property
    def suffix(self) -> str:
        return PurePosixPath(self.name).suffix

    @property
    def parent(self) -> "ObjectPath":
        return ObjectPath(self.base, self.key.rsplit("/", 1)[0] if "/" in self.key else "",
                          self.options)

    @property
    def parents(self) -> list["ObjectPath"]:
        out, p = [], self
        while p.key:
            p = p.parent
            out.append(p)
        return out

    def with_name(self, name: str) -> "ObjectPath":
        return self.parent / name

    def relative_to(self, other: "ObjectPath") -> PurePosixPath:
        if not isinstance(other, ObjectPath) or other.base != self.base:
            raise ValueError(f"{self} is not below {other}")
        if other.key and self.key != other.key and not self.key.startswith(other.key + "/"):
            raise ValueError(f"{self} is not below {other}")
        return PurePosixPath(self.key[len(other.key):].lstrip("/") or ".")

    def as_posix(self) -> str:
        return str(self)

    # --- what is there -------------------------------------------------------------

    @property
    def store(self):
        return _bucket_store(self.base, self.options)

    @_requests
    def read_bytes(self, max_bytes: int | None = None) -> bytes:
        """The object's bytes; FileNotFoundError when absent, ValueError past
        ``max_bytes`` (checked from its size before a byte is read)."""
        import obstore

        try:
            result = obstore.get(self.store, self.key)
        except FileNotFoundError:
            raise FileNotFoundError(str(self)) from None
        if max_bytes is not None and result.meta["size"] > max_bytes:
            TRAFFIC.add()
            raise ValueError(f"{self.key} is larger than {max_bytes} bytes")
        data = bytes(result.bytes())
        TRAFFIC.add(read=len(data))
        return data

    @_requests
    def write_bytes(self, data: bytes) -> None:
        """Put the object whole (an object store replaces it in one step)."""
        import obstore

        # one PUT, never a multipart upload: the largest object bigT writes is a chunk
        # of 2^27 values (1 GiB), under S3's 5 GiB for one PUT, and a writer killed
        # mid-PUT leaves no invisible, billed, half-finished upload behind
        obstore.put(self.store, self.key, data, use_multipart=False)
        TRAFFIC.add(written=len(data))

    @_requests
    def create(self, data: bytes) -> bool:
        """Put the object only where none is (``If-None-Match: *``); False when one
        was there already (another writer's)."""
        import obstore

        try:
            obstore.put(self.store, self.key, data, mode="create", use_multipart=False)
        except Exception as exc:  # obstore's AlreadyExistsError / PreconditionError
            if _conditional_refusal(exc):
                TRAFFIC.add()
                return False
            raise
        TRAFFIC.add(written=len(data))
        return True

    @_requests
    def size(self) -> int:
        import obstore

        TRAFFIC.add()
        try:
            return int(obstore.head(self.store, self.key)["size"])
        except FileNotFoundError:
            raise FileNotFoundError(str(self)) from None

    def is_file(self) -> bool:
        try:
            self.size()
        except FileNotFoundError:
            return False
        return True

    @_requests
    def _listing(self) -> dict:
        import obstore

        TRAFFIC.add()
        return obstore.list_with_delimiter(self.store, self.key + "/" if self.key else None)

    def child_names(self) -> list[str]:
        """Names directly below this prefix (objects and sub-prefixes), sorted."""
        listing = self._listing()
        cut = len(self.key) + 1 if self.key else 0
        names = {p.rstrip("/")[cut:] for p in listing["common_prefixes"]}
        names |= {o["path"][cut:] for o in listing["objects"]}
        return sorted(n for n in names if n)

    def iterdir(self) -> Iterator["ObjectPath"]:
        return iter([self / n for n in self.child_names()])

    def is_dir(self) -> bool:
        listing = self._listing()
        return bool(listing["common_prefixes"] or listing["objects"])

    def exists(self) -> bool:
        return self.is_file() or self.is_dir()

    def is_symlink(self) -> bool:
        return False

    def mkdir(self, parents: bool = False, exist_ok: bool = False) -> None:
        """Nothing to do: a prefix exists as soon as a key below it does."""

    @_requests
    def unlink(self, missing_ok: bool = False) -> None:
        import obstore

        obstore.delete(self.store, self.key)  # deleting a missing key is no error in S3

    def touch(self) -> None:
        if not self.is_file():
            self.write_bytes(b"")

    @_requests
    def walk_objects(self) -> list[tuple[str, int]]:
        """(key, size) of every object below this prefix."""
        import obstore

        return [(meta["path"], int(meta["size"]))
                for batch in obstore.list(self.store, self.key + "/" if self.key else None,
                                          chunk_size=1000)
                for meta in batch]

    @_requests
    def remove_tree(self) -> None:
        """Delete every object below this prefix (and the object at it)."""
        import obstore

        # the store's root zarr.json first: a deletion cut short leaves no store that
        # still says it is complete over missing rows
        root = f"{self.key}/zarr.json" if self.key else "zarr.json"
        keys = [k for k, _ in self.walk_objects()]
        if root in keys:
            obstore.delete(self.store, root)
            keys.remove(root)
        for start in range(0, len(keys), 1000):  # S3's DeleteObjects takes 1000 a call
            obstore.delete(self.store, keys[start:start + 1000])
        if self.key:
            obstore.delete(self.store, self.key)

    @_requests
    def copy_tree_to(self, dest: "ObjectPath") -> None:
        """Copy every object below this prefix to the same keys below ``dest``, in the
        server (no byte travels to this process)."""
        import obstore

        for key, _ in self.walk_objects():
            obstore.copy(self.store, key, dest.key + key[len(self.key):])


#: Environment variable holding the storage options (a JSON object) every URL gets
#: when none are given: how the command line's ``--storage-options`` reaches the
#: stores it opens, and the worker processes it starts.
OPTIONS_ENV = "BIGT_STORAGE_OPTIONS"


def default_storage_options() -> dict:
    """The storage options of :data:`OPTIONS_ENV` (empty when unset); StoreError for
    a value that is not a JSON object."""
    import json

    text = os.environ.get(OPTIONS_ENV, "").strip()
    if not text:
        return {}
    try:
        options = json.loads(text)
    except ValueError as exc:
        raise StoreError(f"storage options are not JSON ({exc})") from None
    if not isinstance(options, dict):
        raise StoreError("storage options must be a JSON object, such as "
                         '{"endpoint": "http://127.0.0.1:9000", "region": "us-east-1"}')
    return options


_POOL = None


def concurrently(func, items: list) -> list:
    """``[func(x) for x in items]`` with the requests in flight together (a row's three
    arrays: one round trip's latency instead of three); the first exception raised
    propagates. Threads, since obstore releases the GIL while it waits."""
    global _POOL
    if len(items) < 2:
        return [func(x) for x in items]
    with _STORES_LOCK:
        if _POOL is None:
            from concurrent.futures import ThreadPoolExecutor

            _POOL = ThreadPoolExecutor(max_workers=16, thread_name_prefix="bigT-objects")
    return [f.result() for f in [_POOL.submit(func, x) for x in items]]


def as_location(path, storage_options: Mapping | None = None):
    """A store's location: an :class:`ObjectPath` for a URL of object storage, a
    :class:`pathlib.Path` for anything else (a ``file://`` URL included).

    Parameters
    ----------
    path : str, os.PathLike or ObjectPath
    storage_options : mapping, optional
        For a URL: obstore's ``from_url`` options (``endpoint``, ``region``,
        ``client_options``...); default those of the environment variable
        ``BIGT_STORAGE_OPTIONS`` (JSON). The AWS, Google and Azure environment
        variables hold the rest.

    Raises
    ------
    StoreError
        A URL of a scheme bigT does not serve (``http://``), or one without a bucket.
    """
    from pathlib import Path

    if isinstance(path, ObjectPath):  # its own options stand unless others are given
        return path if storage_options is None else ObjectPath(
            path.base, path.key, _frozen_options(storage_options))
    if storage_options is None:
        storage_options = default_storage_options()
    if isinstance(path, str):
        scheme = url_scheme(path)
        if scheme == "file":
            return Path(path.split("://", 1)[1])
        if scheme is not None:
            if scheme not in SCHEMES:
                raise StoreError(f"URL scheme {scheme!r} is not served (use a path, or "
                                 f"{', '.join(s + '://' for s in SCHEMES[::2])})", path)
            rest = path.split("://", 1)[1]
            bucket, _, key = rest.partition("/")
            if scheme == "memory":
                bucket, key = "", rest
            elif not bucket:
                raise StoreError("URL without a bucket (s3://BUCKET/KEY)", path)
            parts = [p for p in key.split("/") if p not in ("", ".")]
            if ".." in parts:
                raise StoreError("'..' in a URL's key", path)
            # one spelling per bucket: S3:// and s3a:// are s3://, gcs:// is gs://
            scheme = {"s3a": "s3", "gcs": "gs", "azure": "az"}.get(scheme, scheme)
            return ObjectPath(f"{scheme}://{bucket}", "/".join(parts),
                              _frozen_options(storage_options))
    return Path(os.fspath(path))


def upload_tree(local, dest: ObjectPath) -> int:
    """Put every file below the local directory ``local`` at the same keys below
    ``dest`` (their requests in flight together), the root ``zarr.json`` last, so a
    reader of ``dest`` sees a store only once all of it is there. Symbolic links are
    refused (a store holds none). Returns the bytes put."""
    from pathlib import Path

    local = Path(local)
    files = []
    for dirpath, dirnames, filenames in os.walk(local):
        for name in dirnames + filenames:
            if os.path.islink(os.path.join(dirpath, name)):
                raise StoreError(f"{name} is a symbolic link: a store holds none",
                                 os.path.join(dirpath, name))
        # bigT's hidden files (a reader lease, a build record) stay here
        dirnames[:] = [d for d in dirnames if not d.startswith(".")]
        files += [Path(dirpath, name) for name in filenames if not name.startswith(".")]
    root_meta = local / "zarr.json"
    body = [f for f in files if f != root_meta]

    def put(f) -> int:
        data = f.read_bytes()
        (dest / f.relative_to(local).as_posix()).write_bytes(data)
        return len(data)

    total = sum(concurrently(put, body))
    if root_meta.is_file():
        total += put(root_meta)
    return total


def store_identity(path) -> tuple:
    """What changes when the store at ``path`` has its root ``zarr.json`` rewritten:
    (inode, mtime) of the file, (ETag, time) of the object. Caches key on it."""
    path = as_location(path)
    if isinstance(path, ObjectPath):
        import obstore

        try:
            meta = obstore.head(path.store, (path / "zarr.json").key)
        except FileNotFoundError:
            raise FileNotFoundError(str(path / "zarr.json")) from None
        except Exception as exc:
            raise request_error(exc, path) from None
        return meta["e_tag"], str(meta["last_modified"])
    st = os.stat(os.path.join(path, "zarr.json"))
    return st.st_ino, st.st_mtime_ns
