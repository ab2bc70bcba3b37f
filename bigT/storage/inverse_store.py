"""The versioned inverse store: a root group whose record says which term it holds,
one subgroup per term (``tKKKK/X``, ``tKKKK/P``, ...), and a redirect to the current
X (docs/FORMAT.md, "The inverse store").

:class:`InverseStore` is the only code that writes the root's ``zarr.json``; the
engine hands it frozen records (:class:`InverseRecord`, :class:`TermRecord`).
Publishing a term is: the X store records its own term, the root's redirect flips to
it (one atomic rename), then the root's record is replaced (another). A crash between
the two renames is repaired on the next open (:meth:`InverseStore.reconcile`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..atomic import atomic_write_json, hidden_sibling, remove_stale_temp_files
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
class TermRecord:
    """One row of the report: the state after term ``term``.

    ``seconds`` is the term's wall time, its residual estimate's ``residual_seconds``
    included; ``multiply_adds`` counts its sparse products' multiply-adds and
    ``kernel_seconds`` the time its tasks spent inside the product kernel (summed over
    tasks: thread-seconds). Records written before these were counted read 0.
    """

    term: int
    seconds: float
    nnz_P: int
    nnz_X: int
    tiles_computed: int
    tiles_skipped: int
    rows_skipped: int
    residual: float | None
    residual_abs: float | None
    multiply_adds: int = 0
    kernel_seconds: float = 0.0
    residual_seconds: float = 0.0

    @classmethod
    def from_dict(cls, d: Mapping) -> "TermRecord":
        """Raises TypeError/ValueError on fields of the wrong type or sign (a damaged
        record: :meth:`InverseRecord.from_dict` names the store)."""
        values = {}
        for f in dataclasses.fields(cls):
            v = d.get(f.name, None if f.default is dataclasses.MISSING else f.default)
            if f.name in ("residual", "residual_abs"):
                values[f.name] = None if v is None else float(v)
            elif f.type in ("float", float):  # a string under future annotations
                values[f.name] = float(v or 0.0)
            else:
                values[f.name] = _count(v, f.name)
        return cls(**values)

    def to_dict(self) -> dict:
        return jsonable(dataclasses.asdict(self))


@dataclass(frozen=True)
class InverseRecord:
    """The root's ``bigT_inverse`` attribute.

    Attributes
    ----------
    params : mapping
        What the inverse depends on (T's identity, prune, method, first bounce); a
        run with other parameters is refused.
    term : int or None
        T_term^-1 is held (None before term 0 is complete).
    dir : int or None
        Term directory the redirect points at (``term`` once the series is exhausted
        may be beyond it: every later term equals it).
    history : tuple of TermRecord
    spectral_radius : float or None
        The estimate of rho(M) made before term 0 (:mod:`bigT.spectral`).
    spectral_uncertainty : float or None
        Its Ritz residual: rho is believed within ``spectral_radius`` +- this.
    spectral_products : int or None
        Products with M the estimate took.
    exhausted_at : int or None
    tile_size : int or None
        Tile size of the term stores (T's, or a divisor of it for more tasks).
    excluded_pixels : int or None
    residual : float or None, the last term's relative residual estimate
    """

    params: Mapping[str, Any]
    term: int | None = None
    dir: int | None = None
    history: tuple[TermRecord, ...] = ()
    spectral_radius: float | None = None
    exhausted_at: int | None = None
    tile_size: int | None = None
    excluded_pixels: int | None = None
    residual: float | None = None
    spectral_uncertainty: float | None = None
    spectral_products: int | None = None

    def replace(self, **changes) -> "InverseRecord":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["history"] = [h.to_dict() for h in self.history]
        return jsonable(d)

    @classmethod
    def from_dict(cls, d: Mapping, path) -> "InverseRecord":
        try:
            if not isinstance(d.get("params"), Mapping):
                raise TypeError("no params")
            history = tuple(TermRecord.from_dict(h) for h in d.get("history") or ())
            opt_int = (lambda v: None if v is None else _count(v, "a term"))
            opt_float = (lambda v: None if v is None else float(v))
            return cls(dict(d["params"]), opt_int(d.get("term")), opt_int(d.get("dir")),
                       history, opt_float(d.get("spectral_radius")),
                       opt_int(d.get("exhausted_at")), opt_int(d.get("tile_size")),
                       opt_int(d.get("excluded_pixels")), opt_float(d.get("residual")),
                       opt_float(d.get("spectral_uncertainty")),
                       opt_int(d.get("spectral_products")))
        except (TypeError, ValueError, AttributeError) as exc:
            raise StoreError(f"damaged inverse record ({exc}); delete the store to start "
                             "over", path) from None


def _count(value, name: str) -> int:
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
        self.path = Path(os.fspath(path))
        self.lock = WriterLock(self.path)
        self._removals: list = []  # threads deleting dropped terms (drop_term, settle)

    def close(self) -> None:
        """Release the writer lock (:meth:`open_or_create` took it)."""
        self.lock.release()

    def discard(self) -> None:
        """Delete the whole store (one this run created and finished no term in),
        renamed away first: a crash during the deletion leaves nothing under its name
        (the next writer deletes the trash)."""
        trash = hidden_sibling(self.path, "trash")
        with contextlib.suppress(FileNotFoundError):
            os.rename(self.path, trash)
        self.lock.release()
        shutil.rmtree(trash, ignore_errors=True)

    # --- the record --------------------------------------------------------------

    def _root(self) -> dict | None:
        try:
            with open(self.path / "zarr.json") as f:
                return json.load(f)
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            raise StoreError(f"unreadable zarr.json ({exc})", self.path) from None

    def read_record(self) -> InverseRecord | None:
        root = self._root()
        raw = None if root is None else (root.get("attributes") or {}).get(INVERSE_ATTR)
        return None if raw is None else InverseRecord.from_dict(raw, self.path)

    def save(self, record: InverseRecord) -> None:
        """Replace the record in the root's attributes (one atomic rename)."""
        root = self._root() or fmt.group_json({})
        root.setdefault("attributes", {})[INVERSE_ATTR] = record.to_dict()
        atomic_write_json(self.path / "zarr.json", root)

    def open_or_create(self, params: Mapping, overwrite: bool = False) -> InverseRecord:
        """The record of the inverse at ``path``: a new one (the directory created), or
        the one held when it was made with the same ``params`` (reconciled). With
        ``overwrite`` an inverse held (of any parameters) is deleted and started anew;
        anything that is not a bigT inverse store is never deleted.

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
            return self._open_locked(params, overwrite)
        except BaseException:
            self.lock.release()  # else held as long as the traceback lives
            raise

    def _open_locked(self, params: dict, overwrite: bool) -> InverseRecord:
        remove_stale_temp_files(self.path)
        remove_trash(self.path)
        record = self.read_record()
        if overwrite and record is not None:
            self._delete_contents()
            record = None
        if record is None:  # new, or created by a run killed before its first record
            record = InverseRecord(params)
            self.save(record)
            return record
        if record.params != params:
            # over both key sets: a parameter recorded only when set (prune_feed) may be
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
                os.rename(entry, hidden_sibling(entry, "trash"))
        (self.path / "zarr.json").unlink(missing_ok=True)
        for entry in self.path.iterdir():
            if entry.name != WRITER_LOCK:
                shutil.rmtree(entry) if entry.is_dir() else entry.unlink()

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
            history = history + (TermRecord.from_dict(meta["record"]),)
        record = record.replace(term=d, dir=d, residual=meta.get("residual"), history=history)
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
        if path.parent.is_dir():  # the term directory's group record, cut before renaming
            remove_stale_temp_files(path.parent)
        recover_interrupted_replace(path)
        if path.exists():
            try:
                old = read_store_attrs(path)
            except StoreError:  # a header that bigT before 0.2 left half written
                old = None
            if old is not None and (old.shape, old.tile_size, old.dtype) == (
                    attrs.shape, attrs.tile_size, attrs.dtype):
                clean_partial_rows(path, old.grid[0])
                remove_stale_temp_files(path)
                return path
            shutil.rmtree(path)
        create_store(path, attrs)
        return path

    def finalize_term_store(self, k: int, name: str) -> BlockCSR:
        return finalize_store(self.term_path(k, name))

    def publish(self, record: InverseRecord, X: BlockCSR, term_metadata: Mapping) -> None:
        """Make term ``record.dir`` the one readers see: X records its own term first
        (so :meth:`reconcile` can repair a crash after the flip), then the redirect
        flips to it, then the record is replaced."""
        X.update_metadata(inverse=jsonable(term_metadata))
        create_reader_lease(X.path)
        set_redirect(self.path, f"{term_dir(record.dir)}/X")
        self.save(record)

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
            if entry.is_dir() and not (entry / READER_LEASE).exists():
                shutil.rmtree(entry, ignore_errors=True)


def _our_litter(name: str) -> bool:
    """What a run killed before its first record (or during ``--overwrite``) leaves:
    the writer lock, a temporary record file, old terms renamed to trash."""
    return (name == WRITER_LOCK or name.endswith(".trash")
            or (name.startswith(".zarr.json.") and name.endswith(".tmp")))

