"""Writing a bigT block-CSR store: :class:`BlockCSRWriter` and :func:`from_scipy`."""

from __future__ import annotations

import errno
import json
import os
import shutil
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .. import config
from ..atomic import atomic_write_json, fsync_dir, fsync_tree, fsync_trees
from ..errors import (
    BigTError,
    DiskFullError,
    IncompleteStoreError,
    InvalidMatrixError,
    NotSquareError,
    Option,
    ShapeMismatchError,
    StoreError,
)
from . import _format as fmt
from .attrs import StoreAttrs, read_raw_attrs
from .block_csr import BlockCSR
from .block_csr import open as open_store
from .pixel_order import PIXEL_ORDERS, PixelOrder
from .objects import ObjectPath, as_location, concurrently
from .replace import (check_replaceable, durable, move_into_place, remove_existing,
                      remove_tree, temporary_sibling, write_root_attrs)


def _check_dtype(dtype, where) -> np.dtype:
    try:
        dt = np.dtype(dtype)
    except TypeError:
        dt = None
    if dt is None or dt.name not in fmt.DTYPES:
        raise InvalidMatrixError(f"dtype must be float32 or float64, got {dtype!r}", where)
    return dt


def _wrap_oserror(exc: OSError, path: Path, what: str) -> BigTError | None:
    if exc.errno == errno.ENOSPC:
        return DiskFullError(f"disk full while writing {what}; tile rows completed before it "
                             "are kept (to resume: {option})", path,
                             option=Option("resume", cli="rerun the same command"))
    return None


@contextmanager
def _deleted_on_failure(tmp: Path, path: Path, what: str):
    """Delete the directory ``tmp`` (a row or store being built aside) when the block
    fails; a full disk becomes a DiskFullError naming ``path`` and ``what``."""
    try:
        yield
    except OSError as exc:
        remove_tree(tmp)
        wrapped = _wrap_oserror(exc, path, what)
        if wrapped is not None:
            raise wrapped from exc
        raise
    except BaseException:
        remove_tree(tmp)
        raise


def _validate_block(path: Path, attrs: StoreAttrs, i: int, block) -> sp.csr_array:
    """Tile row ``i``'s block as a CSR of the store's dtype, checked (shape, CSR
    structure, finite values that fit the dtype), duplicates summed, zeros dropped."""
    r0, r1 = attrs.tile_row_range(i)
    want = (r1 - r0, attrs.shape[1])
    where = f"tile row {i}"
    if sp.issparse(block):
        if block.shape != want:
            raise ShapeMismatchError(f"{where}: block of shape {block.shape}, expected {want}", path)
        if not np.issubdtype(block.dtype, np.number) or np.issubdtype(block.dtype, np.complexfloating):
            raise InvalidMatrixError(f"{where}: values of dtype {block.dtype} are not real numbers", path)
        if block.format != "csr":
            block = block.tocsr()
        indptr, indices = np.asarray(block.indptr), np.asarray(block.indices)
        if (indptr.shape != (want[0] + 1,) or (indptr.size and indptr[0] != 0)
                or np.any(np.diff(indptr) < 0) or indptr[-1] != indices.size
                or np.asarray(block.data).size != indices.size):
            raise InvalidMatrixError(f"{where}: malformed CSR index pointer", path)
        if indices.size and (indices.min() < 0 or indices.max() >= want[1]):
            raise InvalidMatrixError(f"{where}: column indices out of range [0, {want[1]})", path)
        data = np.asarray(block.data)
        if not np.isfinite(data).all():
            bad = int(np.count_nonzero(~np.isfinite(data)))
            raise InvalidMatrixError(f"{where}: {bad} NaN/Inf values", path)
        with np.errstate(over="ignore"):
            cast = data.astype(attrs.dtype)
        if not np.isfinite(cast).all():
            raise InvalidMatrixError(f"{where}: values overflow {attrs.dtype.name}", path)
        out = sp.csr_array((cast, indices.copy(), indptr.copy()), shape=want)
    else:
        arr = np.asarray(block)
        if arr.shape != want:
            raise ShapeMismatchError(f"{where}: block of shape {arr.shape}, expected {want}", path)
        if not np.isfinite(arr).all():
            raise InvalidMatrixError(f"{where}: NaN/Inf values", path)
        out = sp.csr_array(arr.astype(attrs.dtype))
    out.sum_duplicates()
    out.eliminate_zeros()
    return out


def create_store(path, attrs: StoreAttrs, durable_header: bool = True) -> None:
    """Write the header of an empty store at ``path`` (root and ``rows`` groups):
    what :func:`write_tile_row` and :func:`finalize_store` need to find.

    Without ``durable_header`` the root's ``zarr.json`` and the store's name are not
    fsynced here (the ``rows`` group is): for a store whose owner recreates it when a
    power cut leaves its header torn or its name lost (an inverse's term stores,
    :meth:`bigT.storage.InverseStore.prepare_term_store`), and makes its name durable
    before it publishes it (:func:`set_redirect` fsyncs the term's directory).
    :func:`finalize_store` replaces the root's ``zarr.json`` durably, after fsyncing
    the store's directory, either way."""
    path = as_location(path)
    attrs.check_json(path)
    try:
        # in object storage, in place: objects are put whole, and the root's
        # ``complete`` flag, set last by finalize_store, is what readers trust
        if isinstance(path, ObjectPath) or path.exists() or path.name.endswith(".partial"):
            # an empty directory to write into (the caller's choice), or a store built
            # aside already (nobody reads it before it is renamed into place)
            path.mkdir(parents=True, exist_ok=True)
            _write_header(path, attrs, durable_header)
            return
        # else built aside and renamed: a crash never leaves a header half written
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = temporary_sibling(path)
        try:
            tmp.mkdir()
            _write_header(tmp, attrs, durable_header)
            os.rename(tmp, path)
            if durable() and durable_header:
                fsync_dir(path.parent)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    except OSError as exc:
        raise (_wrap_oserror(exc, path, "the store header") or exc) from exc


def _write_header(path: Path, attrs: StoreAttrs, durable_header: bool = True) -> None:
    (path / fmt.ROWS_GROUP).mkdir(exist_ok=True)
    fmt.write_json(path / fmt.ROWS_GROUP / "zarr.json", fmt.group_json({}), durable())
    write_root_attrs(path, attrs, sync=durable_header)


def read_store_attrs(path) -> StoreAttrs:
    """The attributes of the (non-redirect) store at ``path``."""
    path = as_location(path)
    raw = read_raw_attrs(path)
    if "redirect" in raw:
        raise StoreError("is a redirect (versioned) store root, not a store to write", path)
    return StoreAttrs.from_dict(raw, path)


@dataclass(frozen=True)
class KeptTiles:
    """Tiles of tile row ``i`` of the finished store ``store`` (same shape, tile size
    and dtype) to carry into a new store's row unchanged. When they are the whole old
    row and nothing else is written to it, the row's files are hard-linked, neither
    read nor rewritten (store files are written once and never modified in place, so a
    link is as good as a copy, and deleting the old store leaves the new one whole);
    otherwise their entries are read and written with the row.

    ``columns`` : tile columns, each stored in the old row; ``nnz`` : their entries
    (the old store's ``tile_nnz``), in the same order.
    """

    store: Path
    columns: tuple[int, ...]
    nnz: tuple[int, ...]


def write_tile_row(path, attrs: StoreAttrs, i: int, block, zstd_level=None,
                   keep: KeptTiles | None = None) -> bool:
    """Write tile row ``i`` of the store at ``path`` whole, idempotently.

    The row's three arrays are built in a hidden sibling directory
    (``rows/.{i}.<hex>.partial``), its completion marker written last, and the
    directory then renamed to ``rows/{i}``: a row is on disk complete or not at all.
    Durably so (``config.DURABILITY``): the row's files are fsynced in one pass before
    the marker, the marker before the rename, ``rows/`` after it, so a power cut never
    leaves a marker over lost data. A row already complete is left alone, so a task
    run twice (a scheduler's retry after a worker loss, or two processes at once)
    writes it once; the loser of a race deletes its own copy.

    Parameters
    ----------
    path : str or os.PathLike, a store created by :func:`create_store`
    attrs : StoreAttrs, the store's (shape, tile size, dtype)
    i : int, ``0 <= i < attrs.grid[0]``
    block : sparse matrix/array or ndarray, shape (rows_i, n_cols), global columns
    keep : KeptTiles, optional
        Tiles carried from the same row of an older store; ``block`` holds no entry
        in their tile columns. The whole old row with an empty ``block`` is linked.

    Returns
    -------
    bool
        False when the row was already complete (nothing written).
    """
    path, i = as_location(path), int(i)
    if not 0 <= i < attrs.grid[0]:
        raise ShapeMismatchError(f"tile row {i} out of range [0, {attrs.grid[0]})", path)
    _check_writable_version(path, read_store_attrs(path))  # the disk's, not the caller's
    if fmt.row_marker(path, i) is not None:
        return False
    block = _validate_block(path, attrs, i, block)
    linked_from = None
    if keep is not None:
        block, linked_from = _with_kept_tiles(keep, attrs, i, block, path)
    if isinstance(path, ObjectPath):
        return _put_row(path, attrs, i, block, zstd_level, linked_from)
    tmp = path / fmt.ROWS_GROUP / f".{i}.{uuid.uuid4().hex[:12]}.partial"
    with _deleted_on_failure(tmp, path, f"tile row {i}"):
        if linked_from is not None:
            _link_row(linked_from, tmp)
        else:
            _write_row(tmp, attrs, block, zstd_level)
        return _move_row_into_place(tmp, path, i)


def _check_writable_version(path: Path, attrs: StoreAttrs) -> None:
    """StoreError naming ``path`` for a store of an older layout: rows are added only
    in this bigT's (a format-1 store is read, and upgraded by ``convert``)."""
    if attrs.version != fmt.FORMAT_VERSION:
        raise StoreError(f"written in bigT store format {attrs.version} (a directory per "
                         f"tile): this bigT reads it but adds no rows to it; upgrade it "
                         f"with {{option}}", path,
                         option=Option("convert(old, new)", cli="bigT convert OLD -o NEW"))


def _put_row(path: ObjectPath, attrs: StoreAttrs, i: int, block: sp.csr_array, level,
             linked_from: ObjectPath | None) -> bool:
    """:func:`write_tile_row` in object storage, where nothing is renamed: the row's
    objects are put in place, then its marker, created only where none is
    (``If-None-Match``). A row without its marker is invisible to readers (and deleted
    by :func:`clean_partial_rows`); of two writers of one row (a retried task) the
    second's marker is refused and it returns False. Their arrays are the same bytes:
    a row's computation is deterministic (docs/FORMAT.md, "Object storage")."""
    dest = path / fmt.row_path(i)
    if linked_from is not None:  # copied in the server: no byte comes here
        for name in fmt.TILE_ARRAYS:
            (linked_from / name).copy_tree_to(dest / name)
        marker = (linked_from / "zarr.json").read_bytes(fmt.METADATA_MAX_BYTES)
    else:
        marker = _write_row_arrays(dest, attrs, block, level)
    return (dest / "zarr.json").create(marker)


def _write_row(tmp: Path, attrs: StoreAttrs, block: sp.csr_array, level) -> None:
    """The row's group in ``tmp``: its three arrays, then (last) its marker."""
    tmp.mkdir()
    marker = _write_row_arrays(tmp, attrs, block, level)
    if durable():
        fsync_tree(tmp, include_root=False)  # the marker's own fsyncs cover tmp itself
    atomic_write_json(tmp / "zarr.json", json.loads(marker), durable())


def _write_row_arrays(tmp, attrs: StoreAttrs, block: sp.csr_array, level) -> bytes:
    """Write the row's three arrays below ``tmp``; returns its marker's JSON bytes."""
    indices = block.indices.astype(fmt.indices_dtype(attrs.shape[1]), copy=False)
    arrays = [("indptr", block.indptr.astype(fmt.INDPTR_DTYPE, copy=False), fmt.FILL_INT, level),
              ("indices", indices, fmt.FILL_INT, level),
              # the values at their own level unless the caller chose one for every array
              ("data", block.data, fmt.FILL_FLOAT,
               config.ZSTD_LEVEL_VALUES if level is None else level)]
    if isinstance(tmp, ObjectPath):  # the three arrays' PUTs in flight together
        concurrently(lambda a: fmt.write_array_files(tmp, *a), arrays)
    else:
        for a in arrays:
            fmt.write_array_files(tmp, *a)
    counts = np.bincount(indices // attrs.tile_size) if indices.size else np.zeros(0, np.int64)
    cols = np.flatnonzero(counts)
    return json.dumps(fmt.group_json({fmt.ROW_ATTRS_KEY: {
        "complete": True, "tile_columns": cols.tolist(), "tile_nnz": counts[cols].tolist()}}),
        indent=2).encode()


def _with_kept_tiles(keep: KeptTiles, attrs: StoreAttrs, i: int, block: sp.csr_array,
                     path: Path) -> tuple[sp.csr_array, Path | None]:
    """(the row to write, the old row's directory to link instead or None): ``keep``'s
    tiles checked against the old row's marker (a row that claims tiles it does not
    hold would be a store that lies), then linked when they are the whole old row and
    ``block`` is empty, else read and added to ``block``."""
    source = as_location(keep.store)
    old_attrs = read_store_attrs(source)

    def layout(a: StoreAttrs):
        return a.shape, a.tile_size, a.dtype, a.inner_format

    if layout(old_attrs) != layout(attrs):
        raise StoreError(f"tile row {i}: kept tiles come from a store of another "
                         f"shape, tile size or dtype ({source})", path)
    marker = fmt.row_marker(source, i)
    old = {} if marker is None else dict(zip(marker["tile_columns"], marker["tile_nnz"]))
    written = set(np.unique(block.indices // attrs.tile_size).tolist()) if block.nnz else set()
    for j, nnz in zip(keep.columns, keep.nnz, strict=True):
        if old.get(int(j)) != nnz or int(j) in written:
            raise StoreError(f"tile row {i}: tile column {int(j)} is " + (
                "also written" if int(j) in written
                else f"not stored with {nnz} entries in {source}"), path)
    whole = sorted(int(j) for j in keep.columns) == sorted(old)
    if not block.nnz and whole and old_attrs.version == fmt.FORMAT_VERSION:
        return block, source / fmt.row_path(i)
    kept = open_store(source).get_tile_row(i, columns=keep.columns)
    out = sp.csr_array(block + kept.astype(block.dtype, copy=False))
    out.sort_indices()
    return out, None


def _link_row(src: Path, tmp: Path) -> None:
    """The old row ``src`` recreated at ``tmp`` with its files hard-linked (copied where
    the file system cannot link), its marker last and, when durable, after the arrays'
    files and directories are fsynced: a copy's pages reach the disk before a marker
    announces them, as a written row's do."""
    tmp.mkdir()
    for entry in os.scandir(src):
        if entry.name != "zarr.json":
            _link_tree(Path(entry.path), tmp / entry.name) if entry.is_dir(
                follow_symlinks=False) else _link_file(entry.path, tmp / entry.name)
    if durable():
        fsync_tree(tmp, include_root=False)
    _link_file(src / "zarr.json", tmp / "zarr.json")
    if durable():
        fsync_dir(tmp)


def _link_file(src, dst: Path) -> None:
    """``dst`` a hard link of ``src``, or a copy where the file system cannot link."""
    try:
        os.link(src, dst)
    except OSError as exc:
        # file systems without links answer EXDEV, EPERM, EMLINK, ENOTSUP, ENOSYS,
        # EINVAL...: copy instead; a full disk is a full disk
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise
        shutil.copyfile(src, dst)


def _link_tree(src: Path, dst: Path) -> None:
    """Recreate directory ``src`` at ``dst`` with every file hard-linked (copied where
    the file system cannot link)."""
    dst.mkdir()
    for entry in os.scandir(src):
        target = dst / entry.name
        if entry.is_dir(follow_symlinks=False):
            _link_tree(Path(entry.path), target)
        else:
            _link_file(entry.path, target)


def _move_row_into_place(tmp: Path, path: Path, i: int) -> bool:
    """Rename the complete row ``tmp`` to ``rows/{i}``; False (and ``tmp`` deleted)
    when another writer got there first."""
    try:
        os.rename(tmp, path / fmt.row_path(i))  # replaces an empty directory only
        if durable():
            fsync_dir(path / fmt.ROWS_GROUP)
        return True
    except OSError as exc:
        if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST) or fmt.row_marker(path, i) is None:
            raise
    shutil.rmtree(tmp, ignore_errors=True)
    return False


def completed_rows(path, n_rows: int) -> dict[int, tuple[list[int], list[int]]]:
    """``{i: (tile_columns, tile_nnz)}`` of the tile rows marked complete on disk."""
    out = {}
    path = as_location(path)
    for i in range(n_rows):
        rec = fmt.row_marker(path, i)
        if rec is not None:
            out[i] = (list(rec["tile_columns"]), list(rec["tile_nnz"]))
    return out


def clean_partial_rows(path, n_rows: int) -> int:
    """Delete what interrupted writers left in ``rows/``: hidden ``.partial`` rows and
    row directories without a completion marker (bigT before 0.2 wrote rows in
    place). Run by the one process that owns the store, before writers start, never
    while they write. Returns the number of directories deleted."""
    path = as_location(path)
    rows = path / fmt.ROWS_GROUP
    gone = 0
    if not rows.is_dir():
        return 0
    for entry in rows.iterdir():
        stale = entry.name.endswith(".partial") or (
            entry.name.isdigit() and int(entry.name) < n_rows
            and fmt.row_marker(path, int(entry.name)) is None)
        if stale and entry.is_dir():
            remove_tree(entry)
            gone += 1
    return gone


def finalize_store(path, zstd_level=None, metadata: dict | None = None) -> BlockCSR:
    """Write the tile index from the row markers on disk, mark the store complete and
    open it: whoever wrote the rows (threads, other processes), only the markers count.
    The index is fsynced before the completion flag (``config.DURABILITY``).
    ``metadata``, items merged into the store's free metadata in the same write as
    the flag (a store complete already is opened as it is).

    Raises
    ------
    IncompleteStoreError
        Naming the tile rows not yet written.
    """
    path = as_location(path)
    local = not isinstance(path, ObjectPath)  # an object is durable once put
    attrs = read_store_attrs(path)
    if attrs.complete:
        return open_store(path)
    n_rows = attrs.grid[0]
    rows = completed_rows(path, n_rows)
    missing = [i for i in range(n_rows) if i not in rows]
    if missing:
        first = ", ".join(str(i) for i in missing[:5]) + (", ..." if len(missing) > 5 else "")
        raise IncompleteStoreError(f"cannot finalize: {len(missing)} of {n_rows} tile rows "
                                   f"not written (rows {first})", path)
    tile_indptr = np.zeros(n_rows + 1, dtype=np.int64)
    np.cumsum([len(rows[i][0]) for i in range(n_rows)], out=tile_indptr[1:])
    tile_indices = np.array([j for i in range(n_rows) for j in rows[i][0]], dtype=np.int64)
    tile_nnz = np.array([c for i in range(n_rows) for c in rows[i][1]], dtype=np.int64)
    try:
        for name, values in zip(fmt.INDEX_ARRAYS, (tile_indptr, tile_indices, tile_nnz)):
            fmt.write_array_files(path, name, values, fmt.FILL_INT, zstd_level)
        if durable() and local:  # the three arrays' fsyncs in one pass
            fsync_trees([path / name for name in fmt.INDEX_ARRAYS])
        if durable() and local:
            fsync_dir(path)  # the arrays' names, before the flag that says they are there
        write_root_attrs(path, attrs.replace(nnz=int(tile_nnz.sum()), complete=True,
                                             metadata={**attrs.metadata, **(metadata or {})}))
    except OSError as exc:
        raise (_wrap_oserror(exc, path, "the tile index") or exc) from exc
    return open_store(path)


def default_tile_size(channels: int = 1) -> int:
    """The tile size a store of ``channels`` values per pixel gets when none is asked for."""
    return config.DEFAULT_TILE_SIZE if channels == 1 else config.DEFAULT_COLOUR_TILE_SIZE


def checked_tile_size(tile_size, channels: int, path) -> int:
    """``tile_size`` (the default for ``channels`` when None) once it is >= 1 and, for a
    colour store, a multiple of 3 (a pixel's 3x3 block within one tile);
    ShapeMismatchError naming ``path`` otherwise."""
    tile_size = int(default_tile_size(channels) if tile_size is None else tile_size)
    if tile_size < 1:
        raise ShapeMismatchError(f"tile_size must be >= 1, got {tile_size}", path)
    if tile_size % channels:
        raise ShapeMismatchError(f"tile_size {tile_size} is not a multiple of {channels}: a "
                                 f"colour store keeps each pixel's {channels} channels in one "
                                 f"tile (e.g. {channels * max(1, tile_size // channels)})", path)
    return tile_size


class BlockCSRWriter:
    """Write a block-CSR store tile row by tile row.

    Parameters
    ----------
    path : str or os.PathLike
        Directory of the new store.
    shape : (int, int)
    tile_size : int, optional
        Default ``config.DEFAULT_TILE_SIZE``.
    dtype : {"float32", "float64"}
    pixel_order : PixelOrder, optional
        Recorded so images map back; its ``n`` must equal both sides of ``shape``.
    metadata : dict, optional
        Free JSON metadata.
    resume : bool
        Continue an interrupted store at ``path``: complete tile rows are kept and
        ``write_tile_row`` skips them; what interrupted writers left is deleted.
    overwrite : bool
        Replace an existing bigT store at ``path`` (never anything else).
    zstd_level : int, optional
        Default ``config.ZSTD_LEVEL`` (``config.ZSTD_LEVEL_VALUES`` for the tiles' values).

    Notes
    -----
    Rows go through :func:`write_tile_row` (whole, idempotent, any order, any number
    of threads or processes); :meth:`finalize` is :func:`finalize_store`, which reads
    the row markers on disk.
    """

    def __init__(self, path, shape, *, tile_size: int | None = None, dtype="float32",
                 pixel_order: PixelOrder | None = None, metadata: dict | None = None,
                 resume: bool = False, overwrite: bool = False, zstd_level: int | None = None):
        self.path = as_location(path)
        try:
            shape = tuple(int(s) for s in shape)
        except (TypeError, ValueError):
            raise ShapeMismatchError(f"shape must be (n_rows, n_cols), got {shape!r}", self.path) from None
        if len(shape) != 2 or min(shape) < 0:
            raise ShapeMismatchError(f"shape must be (n_rows, n_cols) >= 0, got {shape}", self.path)
        if pixel_order is not None and not isinstance(pixel_order, PixelOrder):
            raise TypeError("pixel_order must be a PixelOrder or None")
        channels = 1 if pixel_order is None else pixel_order.channels
        tile_size = checked_tile_size(tile_size, channels, self.path)
        dt = _check_dtype(dtype, self.path)
        if pixel_order is not None and shape != (pixel_order.n, pixel_order.n):
            raise ShapeMismatchError(f"image shape {pixel_order.frame_shape} has {pixel_order.n} "
                                     f"values, the matrix is {shape}", self.path)
        self.zstd_level = zstd_level
        attrs = StoreAttrs(shape, tile_size, dt, metadata=metadata or {},
                           pixel_order=pixel_order)
        if resume and self.path.exists() and not (self.path.is_dir() and not any(self.path.iterdir())):
            self.attrs = self._resume(attrs)
        else:
            remove_existing(self.path, overwrite)
            create_store(self.path, attrs)
            self.attrs = attrs
        self.shape, self.tile_size, self.dtype = shape, tile_size, dt
        self.pixel_order = pixel_order
        self.grid = attrs.grid
        self._rows = set(completed_rows(self.path, self.grid[0]))

    def _resume(self, attrs: StoreAttrs) -> StoreAttrs:
        old = read_store_attrs(self.path)
        for key in ("shape", "tile_size", "dtype", "inner_format"):
            if getattr(old, key) != getattr(attrs, key):
                raise ShapeMismatchError(f"cannot resume: store has {key}={getattr(old, key)!r}, "
                                         f"writer asks {getattr(attrs, key)!r}", self.path)
        if old.pixel_order != attrs.pixel_order:
            raise ShapeMismatchError(f"cannot resume: store has pixel order {old.pixel_order}, "
                                     f"writer asks {attrs.pixel_order}", self.path)
        _check_writable_version(self.path, old)
        clean_partial_rows(self.path, old.grid[0])
        if attrs.metadata and not old.complete:
            old = old.replace(metadata={**old.metadata, **attrs.metadata})
            old.check_json(self.path)
            write_root_attrs(self.path, old)
        return old

    # --- writing -------------------------------------------------------------------

    @property
    def completed_tile_rows(self) -> list[int]:
        """Sorted tile rows already complete on disk."""
        return sorted(self._rows)

    @property
    def missing_tile_rows(self) -> list[int]:
        return [i for i in range(self.grid[0]) if i not in self._rows]

    def tile_row_range(self, i: int) -> tuple[int, int]:
        return self.attrs.tile_row_range(i)

    def write_tile_row(self, i: int, block) -> bool:
        """Write tile row ``i`` whole, then mark it complete (:func:`write_tile_row`).

        Parameters
        ----------
        i : int
            Tile row, ``0 <= i < grid[0]``.
        block : sparse matrix/array or ndarray, shape (rows_i, n_cols)
            Global column indices; converted to CSR of the store's dtype, duplicates
            summed, explicit zeros dropped, then cut into tiles (empty tiles dropped).

        Returns
        -------
        bool
            False when the row was already complete (a resumed writer skips it).
        """
        i = int(i)
        if i in self._rows and 0 <= i < self.grid[0]:
            return False
        written = write_tile_row(self.path, self.attrs, i, block, self.zstd_level)
        self._rows.add(i)
        return written

    def finalize(self) -> BlockCSR:
        """Write the tile index from the row markers, mark the store complete and open
        it for reading (:func:`finalize_store`).

        Raises
        ------
        IncompleteStoreError
            Naming the tile rows not yet written.
        """
        return finalize_store(self.path, self.zstd_level)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.finalize()
        return False


def _stored_dtype(dtype) -> str:
    """The store dtype that keeps values of ``dtype``: float64 stays float64."""
    return "float64" if np.dtype(dtype) == np.float64 else "float32"


def _as_checked_csr(A, path, require_square: bool) -> sp.csr_array:
    """Validate ``A`` whole before anything is written."""
    if sp.issparse(A):
        if A.ndim != 2:
            raise ShapeMismatchError(f"matrix must be 2-D, got shape {A.shape}", path)
        A = sp.csr_array(A)
    else:
        arr = np.asarray(A)
        if arr.ndim != 2:
            raise ShapeMismatchError(f"matrix must be 2-D, got shape {arr.shape}", path)
        if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            raise InvalidMatrixError(f"values of dtype {arr.dtype} are not numbers", path)
        A = sp.csr_array(arr)
    if np.issubdtype(A.dtype, np.complexfloating) or not (
            np.issubdtype(A.dtype, np.number) or A.dtype == bool):
        raise InvalidMatrixError(f"values of dtype {A.dtype} are not real numbers", path)
    if require_square and A.shape[0] != A.shape[1]:
        raise NotSquareError(f"matrix must be square, got shape {A.shape}", path)
    bad = ~np.isfinite(A.data)
    if bad.any():
        r = int(np.searchsorted(A.indptr, np.flatnonzero(bad)[0], side="right") - 1)
        raise InvalidMatrixError(f"{int(bad.sum())} NaN/Inf values (first in row {r})", path)
    if A.nnz and (A.indices.min() < 0 or A.indices.max() >= A.shape[1]):
        raise InvalidMatrixError(f"column indices out of range [0, {A.shape[1]})", path)
    return A


def from_scipy(A, path, *, tile_size: int | None = None, dtype=None, image_shape=None,
               pixel_order: str = "row-major", image_tile=None, input_order: str = "row-major",
               metadata: dict | None = None, overwrite: bool = False,
               require_square: bool = False, channels: int = 1) -> BlockCSR:
    """Store a scipy sparse matrix (or 2-D ndarray) as a bigT block-CSR store.

    The store is written to a temporary sibling directory and moved into place only
    when complete, so a failed call leaves ``path`` as it was.

    Parameters
    ----------
    A : scipy sparse matrix/array or ndarray, shape (n_rows, n_cols)
    path : str or os.PathLike
    tile_size : int, optional
        Default ``config.DEFAULT_TILE_SIZE`` (``config.DEFAULT_COLOUR_TILE_SIZE`` for
        colour); a multiple of 3 for colour.
    dtype : {"float32", "float64"}, optional
        Default: A's own float dtype (float32 for integer or boolean values), so float64
        is never rounded unless asked for.
    image_shape : (H, W), optional
        The matrix maps H x W images (then it must be square with n = H W channels).
    pixel_order : {"row-major", "tile-major"}
        Pixel order of the store.
    image_tile : (th, tw), optional
        Image tile of "tile-major"; default ``config.DEFAULT_IMAGE_TILE``.
    input_order : {"row-major", "matrix"}
        "row-major": A is numbered in row-major image order and is permuted into
        ``pixel_order``; "matrix": A is already in the stored order.
    metadata : dict, optional
    overwrite : bool
        Replace an existing bigT store at ``path``.
    require_square : bool
        Raise NotSquareError for a non-square A.
    channels : {1, 3}
        3 for a colour transport: index 3 p + c (docs/FORMAT.md, "Colour"); needs
        ``image_shape``.

    Returns
    -------
    BlockCSR
    """
    path = as_location(path)
    if input_order not in ("row-major", "matrix"):
        raise ValueError(f"input_order must be 'row-major' or 'matrix', got {input_order!r}")
    if pixel_order not in PIXEL_ORDERS:
        raise ValueError(f"pixel_order must be one of {PIXEL_ORDERS}, got {pixel_order!r}")
    A = _as_checked_csr(A, path, require_square or image_shape is not None)
    dt = _check_dtype(_stored_dtype(A.dtype) if dtype is None else dtype, path)
    po = None
    if image_shape is not None:
        kw = {} if image_tile is None else {"image_tile": tuple(image_tile)}
        po = PixelOrder(tuple(image_shape), pixel_order, channels=channels, **kw)
        if A.shape != (po.n, po.n):
            raise ShapeMismatchError(f"image shape {po.frame_shape} has {po.n} values, the "
                                     f"matrix is {A.shape}", path)
    elif pixel_order != "row-major":
        raise ShapeMismatchError(f"pixel_order {pixel_order!r} needs image_shape", path)
    elif channels != 1:
        raise ShapeMismatchError(f"a colour matrix (channels={channels}) needs image_shape",
                                 path)
    tile_size = checked_tile_size(tile_size, channels, path)
    check_replaceable(path, overwrite)

    with np.errstate(over="ignore"):
        data = A.data.astype(dt)
    if not np.isfinite(data).all():
        raise InvalidMatrixError(f"values overflow {dt.name}", path)
    A = sp.csr_array((data, A.indices, A.indptr), shape=A.shape)
    if po is not None and input_order == "row-major" and po.order != "row-major":
        perm = po.permutation
        A = sp.csr_array(A[perm][:, perm])
    A.sum_duplicates()
    A.eliminate_zeros()

    path.parent.mkdir(parents=True, exist_ok=True)
    with built_aside(path) as tmp:
        writer = BlockCSRWriter(tmp, A.shape, tile_size=tile_size, dtype=dt,
                                pixel_order=po, metadata=metadata)
        for i in range(writer.grid[0]):
            r0, r1 = writer.tile_row_range(i)
            writer.write_tile_row(i, A[r0:r1])
        writer.finalize()
    return open_store(path)


@contextmanager
def built_aside(path: Path):
    """A fresh sibling directory of ``path`` to build a whole store in, moved into place
    when the block ends and deleted when it fails, so ``path`` is never half written;
    a full disk is a DiskFullError saying nothing changed at ``path``.

    In object storage there is no rename: the store is built at ``path`` itself (an
    old one deleted first), and until ``finalize`` marks it complete readers refuse it
    as incomplete; a failure leaves it so, for a rerun to replace."""
    if isinstance(path, ObjectPath):
        if path.exists():
            remove_tree(path)  # check_replaceable allowed it: a bigT store, overwrite
        yield path
        return
    tmp = temporary_sibling(path)
    try:
        with _deleted_on_failure(tmp, path, "the store"):
            yield tmp
            move_into_place(tmp, path)
    except DiskFullError as exc:
        raise DiskFullError(f"disk full while writing ({exc.template}); nothing was changed at the "
                            f"destination", path, option=exc.option) from exc
