"""The versioned inverse store: a root group whose record says which term it holds,
one subgroup per term (``tKKKK/X``, ``tKKKK/P``, ...), and a redirect to the current
X (docs/FORMAT.md, "The inverse store").

:class:`InverseStore` is the only code that writes the root's ``zarr.json``; the
engine hands it frozen records (:class:`InverseRecord`, :class:`TermEntry`). Storage
knows what it needs to publish and resume (the term held, its directory, the tile size,
one entry per term); what the algorithm records beside that (residuals, the spectral
radius, multiply-adds) is an opaque ``details`` mapping in the same JSON objects, typed
by :mod:`bigT.algorithms.records`.

Publishing a term is: the X store records its own term, the root's redirect flips to
it (one atomic rename), then the root's record is replaced (another). A crash between
the two renames is repaired on the next open (:meth:`InverseStore.reconcile`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..atomic import hidden_sibling, remove_stale_temp_files
from ..errors import StoreError
from . import _format as fmt
from .attrs import StoreAttrs
from .block_csr import BlockCSR
from .block_csr import open as open_store
from .locks import (
    READER_LEASE,
    WRITER_LOCK,
    WriterLock,
    create_reader_lease,
    remove_trash,
    remove_unless_read,
)
from .objects import ObjectPath, as_location
from .replace import durable, remove_tree
from .writer import (
    clean_partial_rows,
    create_store,
    finalize_store,
    read_store_attrs,
)
from .replace import recover_interrupted_replace, set_redirect

#: Attribute of the root group holding the engine's record (beside the storage
#: layer's ``bigT`` attribute, which holds the redirect).
INVERSE_ATTR = fmt.INVERSE_ATTR
_TERM_DIR = re.compile(r"t(\d{4})")


def jsonable(obj):
    """A JSON-ready copy of ``obj``: numpy scalars as Python numbers, NaN/Inf as None."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


@dataclass(frozen=True)
class TermEntry:
    """One published term as the store keeps it: its number, and what the algorithm
    recorded of it (opaque to storage: JSON kept beside ``term`` in the same object,
    filled and read back by :mod:`bigT.algorithms.records`)."""

    term: int
    details: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: Mapping) -> "TermEntry":
        """Raises TypeError/ValueError on a damaged entry (not a mapping, or its
        ``term`` not a count): :meth:`InverseRecord.from_dict` names the store."""
        if not isinstance(d, Mapping):
            raise TypeError(f"a history entry is {type(d).__name__}, not a mapping")
        return cls(as_count(d.get("term"), "a term"),
                   {str(k): v for k, v in d.items() if k != "term"})

    def to_dict(self) -> dict:
        return jsonable({"term": self.term, **self.details})


@dataclass(frozen=True)
class InverseRecord:
    """The root's ``bigT_inverse`` attribute: what storage needs to publish, resume and
    repair a versioned inverse.

    Attributes
    ----------
    params : mapping
        What the inverse depends on (its writer's fingerprint); a run with other
        parameters is refused.
    term : int or None
        T_term^-1 is held (None before term 0 is complete).
    dir : int or None
        Term directory the redirect points at (``term`` may be beyond it once the
        writer says every later term equals it).
    history : tuple of TermEntry
        One per published term.
    tile_size : int or None
        Tile size of the term stores.
    details : mapping
        What the algorithm records beside these (opaque JSON, kept in the same object:
        the algorithms layer's :class:`bigT.algorithms.records.SeriesRecord` fills it
        and reads it back).
    """

    params: Mapping[str, Any]
    term: int | None = None
    dir: int | None = None
    history: tuple[TermEntry, ...] = ()
    tile_size: int | None = None
    details: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def replace(self, **changes) -> "InverseRecord":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return jsonable({"params": self.params, "term": self.term, "dir": self.dir,
                         "history": [h.to_dict() for h in self.history],
                         "tile_size": self.tile_size, **self.details})

    @classmethod
    def from_dict(cls, d: Mapping, path) -> "InverseRecord":
        try:
            if not isinstance(d.get("params"), Mapping):
                raise TypeError("no params")
            history = tuple(TermEntry.from_dict(h) for h in d.get("history") or ())
            opt_int = (lambda v: None if v is None else as_count(v, "a term"))
            details = {k: v for k, v in d.items() if k not in _RECORD_KEYS}
            return cls(dict(d["params"]), opt_int(d.get("term")), opt_int(d.get("dir")),
                       history, opt_int(d.get("tile_size")), details)
        except (TypeError, ValueError, AttributeError) as exc:
            raise damaged_record(exc, path) from None


#: The keys of the record storage reads itself; the others are the writer's details.
_RECORD_KEYS = frozenset(f.name for f in dataclasses.fields(InverseRecord)) - {"details"}


def damaged_record(exc: Exception, path) -> StoreError:
    """The error for a record that does not parse (its reason, the store named)."""
    return StoreError(f"damaged inverse record ({exc}); delete the store to start over",
                      path)


def as_count(value, name: str) -> int:
    """``value`` as a count (an int >= 0); ValueError/TypeError when it is not one."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        raise TypeError(f"{name} is {value!r}, not a whole number")
    if value < 0:
        raise ValueError(f"{name} is {value!r} < 0")
    return int(value)


def term_dir(k: int) -> str:
    return f"t{k:04d}"


class InverseStore:
    """The inverse store at ``path`` (a directory).

    Parameters
    ----------
    path : str or os.PathLike
    """

    def __init__(self, path):
        self.path = as_location(path)
        self.lock = WriterLock(self.path)
        self._removals: list = []  # threads deleting dropped terms (drop_term, settle)

    def close(self) -> None:
        """Release the writer lock (:meth:`open_or_create` took it)."""
        self.lock.release()

    def discard(self) -> None:
        """Delete the whole store (one this run created and finished no term in),
        renamed away first: a crash during the deletion leaves nothing under its name
        (the next writer deletes the trash)."""
        if isinstance(self.path, ObjectPath):  # no rename: deleted in place, lock last
            for entry in self.path.iterdir():
                if entry.name != WRITER_LOCK:
                    remove_tree(entry)
            self.lock.release()
            return
        trash = hidden_sibling(self.path, "trash")
        with contextlib.suppress(FileNotFoundError):
            os.rename(self.path, trash)
        self.lock.release()
        shutil.rmtree(trash, ignore_errors=True)

    # --- the record --------------------------------------------------------------

    def _root(self) -> dict | None:
        if not (self.path / "zarr.json").is_file():
            return None
        return fmt.read_json(self.path / "zarr.json")  # bounded, a link refused

    def read_record(self) -> InverseRecord | None:
        root = self._root()
        attributes = None if root is None else root.get("attributes") or {}
        if attributes is not None and not isinstance(attributes, dict):
            raise damaged_record(TypeError("attributes is not an object"), self.path)
        raw = None if attributes is None else attributes.get(INVERSE_ATTR)
        return None if raw is None else InverseRecord.from_dict(raw, self.path)

    def save(self, record: InverseRecord) -> None:
        """Replace the record in the root's attributes (one atomic rename), fsynced as
        ``config.DURABILITY`` says (like every other write of the stores)."""
        root = self._root() or fmt.group_json({})
        root.setdefault("attributes", {})[INVERSE_ATTR] = record.to_dict()
        fmt.write_json(self.path / "zarr.json", root, durable())

    def open_or_create(self, params: Mapping, overwrite: bool = False,
                       fresh: Callable[[InverseRecord], InverseRecord] | None = None
                       ) -> InverseRecord:
        """The record of the inverse at ``path``: a new one (the directory created), or
        the one held when it was made with the same ``params`` (reconciled). With
        ``overwrite`` an inverse held (of any parameters) is deleted and started anew;
        anything that is not a bigT inverse store is never deleted. ``fresh``, given,
        makes a new record what the caller records first (the term stores' tile
        size): saved in the same durable write as the record it is given, not a
        second one.

        Raises
        ------
        StoreError
            ``path`` holds something else, or an inverse with other parameters.
        """
        params = jsonable(params)
        recover_interrupted_replace(self.path)  # trash a killed discard() left beside it
        self._refuse_foreign()
        self.path.mkdir(parents=True, exist_ok=True)
        self.lock.acquire()  # a second writer is refused here, before any change
        try:
            return self._open_locked(params, overwrite, fresh)
        except BaseException:
            self.lock.release()  # else held as long as the traceback lives
            raise

    def _open_locked(self, params: dict, overwrite: bool, fresh=None) -> InverseRecord:
        _remove_temp_files(self.path)
        remove_trash(self.path)
        record = self.read_record()
        if overwrite and record is not None:
            self._delete_contents()
            record = None
        if record is None:  # new, or created by a run killed before its first record
            record = InverseRecord(params)
            record = record if fresh is None else fresh(record)
            self.save(record)
            return record
        if record.params != params:
            # over both key sets: a parameter its writer records only when set may be
            # the one missing from either side
            keys = list(params) + [k for k in record.params if k not in params]
            diff = [k for k in keys if record.params.get(k) != params.get(k)]
            held = ", ".join(f"{k}={record.params.get(k)}" for k in diff)
            raise StoreError("holds an inverse with different " + ", ".join(diff) + " than "
                             f"asked (it holds {held}); rerun with the same parameters to "
                             "resume, pass {option} to start anew, or choose another "
                             "path", self.path, option=("overwrite", True))
        self._check_term_held(record)
        record = self.reconcile(record)
        if record.dir is not None:  # made before leases existed, or by a crash after
            create_reader_lease(self.term_path(record.dir, "X"))
        return record

    def _check_term_held(self, record: InverseRecord) -> None:
        """A record naming a term whose X is not on disk is damaged (a crash never
        leaves one: the record is replaced after the X it names is published)."""
        if record.dir is not None and not (self.term_path(record.dir, "X") / "zarr.json").is_file():
            raise StoreError(f"damaged inverse record: it holds term {record.dir}, but "
                             f"{term_dir(record.dir)}/X is not on disk; delete the store to "
                             "start over", self.path)

    def _refuse_foreign(self) -> None:
        """Refuse a path holding something else than an inverse (or a start of one)."""
        if not self.path.exists():
            return
        if not self.path.is_dir():
            raise StoreError("exists and is a file, not a bigT inverse store; choose "
                             "another path", self.path)
        if self.read_record() is None and any(not _our_litter(e.name)
                                              for e in self.path.iterdir()):
            raise StoreError("exists and is not a bigT inverse store; choose another path "
                             "or delete it", self.path)

    def _delete_contents(self) -> None:
        """Everything but the writer lock (held). The terms are renamed away first (a
        crash then leaves no old term under a name a new run would take up), then the
        record goes, then the trash."""
        for entry in self.path.iterdir():
            if _TERM_DIR.fullmatch(entry.name):
                if isinstance(entry, ObjectPath):  # no rename: the term deleted first
                    entry.remove_tree()
                else:
                    os.rename(entry, hidden_sibling(entry, "trash"))
        (self.path / "zarr.json").unlink(missing_ok=True)
        for entry in self.path.iterdir():
            if entry.name != WRITER_LOCK:
                remove_tree(entry)  # a link is deleted as itself, never what it points at

    def reconcile(self, record: InverseRecord) -> InverseRecord:
        """Adopt the term the redirect points at when the record lags behind it (a
        crash between the flip and the record)."""
        try:
            current = open_store(self.path)
        except StoreError:
            return record
        meta = current.metadata.get("inverse") or {}
        d = meta.get("dir")
        if d is None or (record.dir is not None and d <= record.dir):
            return record
        history = record.history
        if meta.get("record"):
            history = history + (TermEntry.from_dict(meta["record"]),)
        # X's metadata is newer than the record: a detail both state (the residual of
        # the term held) is taken from it
        details = {**record.details, **{k: meta[k] for k in record.details if k in meta}}
        record = record.replace(term=d, dir=d, history=history, details=details)
        self.save(record)
        return record

    # --- term stores -------------------------------------------------------------

    def term_path(self, k: int, name: str) -> Path:
        return self.path / term_dir(k) / name

    def prepare_term_store(self, k: int, name: str, attrs: StoreAttrs) -> Path:
        """Create the store ``name`` of term ``k`` with ``attrs``, or keep the one an
        interrupted run left (its complete rows; what its writers left half done is
        deleted now, before any writer starts). Returns its path."""
        path = self.term_path(k, name)
        # the term's directory and store are cleaned below: never through a link
        fmt.check_no_links(self.path, path.relative_to(self.path).as_posix())
        fmt.check_no_links(path, fmt.ROWS_GROUP)
        if path.parent.is_dir():  # the term directory's group record, cut before renaming
            _remove_temp_files(path.parent)
        recover_interrupted_replace(path)
        if path.exists():
            try:
                old = read_store_attrs(path)
            except StoreError:  # a header that bigT before 0.2 left half written
                old = None
            # kept when its header is whole: the root's attributes and the rows group
            # (a power cut may leave either lost: the header is not fsynced, below)
            if old is not None and (old.shape, old.tile_size, old.dtype, old.version) == (
                    attrs.shape, attrs.tile_size, attrs.dtype, attrs.version) and (
                    path / fmt.ROWS_GROUP / "zarr.json").is_file():
                clean_partial_rows(path, old.grid[0])
                _remove_temp_files(path)
                return path
            remove_tree(path)
        # its header's root and name made durable by finalize_store and publish (a
        # torn or lost header is recreated above): three fsyncs fewer per store
        create_store(path, attrs, durable_header=False)
        return path

    def finalize_term_store(self, k: int, name: str, metadata: dict | None = None) -> BlockCSR:
        """:func:`finalize_store` of store ``name`` of term ``k``; ``metadata`` merged
        into its metadata in the same write (X's ``inverse``, known before it is
        written: :meth:`publish` then leaves X as it is)."""
        return finalize_store(self.term_path(k, name),
                              metadata=None if metadata is None else jsonable(metadata))

    def publish(self, record: InverseRecord, X: BlockCSR, term_metadata: Mapping) -> None:
        """Make term ``record.dir`` the one readers see: X records its own term first
        (so :meth:`reconcile` can repair a store a crash left flipped and not
        recorded, as bigT before issue #30 published in two writes), then the redirect
        flips to it and the record is replaced, in one write of the root's
        ``zarr.json`` (one durable replace, not two)."""
        self.lock.check_held()  # a writer that lost its lock publishes nothing
        inverse = jsonable(term_metadata)
        if X.metadata.get("inverse") != inverse:  # else recorded when X was finalized
            X.update_metadata(inverse=inverse)
        create_reader_lease(X.path)
        set_redirect(self.path, f"{term_dir(record.dir)}/X",
                     attributes={INVERSE_ATTR: record.to_dict()})

    def clean(self, keep: set[int]) -> None:
        """Delete term directories other than ``keep`` (left by a crash, or by a reader
        that held them when they were dropped) that no reader holds now."""
        for entry in self.path.iterdir():
            m = _TERM_DIR.fullmatch(entry.name)
            if m and int(m.group(1)) not in keep:
                remove_unless_read(entry)
        remove_trash(self.path)

    def settle(self) -> None:
        """Wait for the deletions :meth:`drop_term` left running in the background."""
        while self._removals:
            self._removals.pop().join()

    def drop_term(self, k: int, background: bool = False) -> None:
        """Delete term ``k``'s directory, or, while a reader holds its X, all of it
        but that X (deleted by a later :meth:`clean`). With ``background``, the
        directory is renamed away at once and deleted by a thread
        (:meth:`settle` waits for it). The disk holds both terms a little longer."""
        directory = self.path / term_dir(k)
        removals = self._removals if background else None
        if remove_unless_read(directory, removals) or not directory.is_dir():
            return
        for entry in directory.iterdir():
            if entry.is_dir() and not entry.is_symlink() and not (entry / READER_LEASE).exists():
                shutil.rmtree(entry, ignore_errors=True)


def _remove_temp_files(directory) -> None:
    """The temporary files killed writers left in ``directory`` (none in object
    storage, where an object is put whole)."""
    if not isinstance(directory, ObjectPath):
        remove_stale_temp_files(directory)


def _our_litter(name: str) -> bool:
    """What a run killed before its first record (or during ``--overwrite``) leaves:
    the writer lock, a temporary record file, old terms renamed to trash."""
    return (name == WRITER_LOCK or name.endswith(".trash")
            or (name.startswith(".zarr.json.") and name.endswith(".tmp")))

