"""Whole-store checks of a block-CSR store: every chunk file a tile row needs is on disk
(:func:`check_chunks_exist`, stat only) and every tile reads back as valid CSR
(:func:`verify`, what ``bigT verify`` runs).

They take what they check (the store's directory, attributes and tile index, and a
way to read a tile row's tiles) rather than the :class:`~bigT.storage.BlockCSR`, so
that the reader depends on them and not the other way round.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import CorruptStoreError
from ..progress import progress_bar
from . import _format as fmt
from .attrs import StoreAttrs
from .tile_index import TileIndex
from .tiles import TileRowReader, tile_error, zarr_array

def check_chunks_exist(path: Path, attrs: StoreAttrs, index: TileIndex) -> None:
    """Cheap existence check of every chunk file; CorruptStoreError naming the first missing."""
    missing = missing_chunk_files(path, attrs, index, limit=1)
    if missing:
        raise CorruptStoreError(f"missing chunk file {missing[0]}", path)


def verify(path: Path, attrs: StoreAttrs, index: TileIndex, iter_tiles: TileRowReader, *,
           complete: bool, progress: bool | None = False) -> dict:
    """Full check of every tile and every chunk file of the store at ``path``; see
    :meth:`bigT.storage.BlockCSR.verify`. ``complete``: the store is finalized, so
    every tile row has a completion marker that must agree with ``index``.

    Returns
    -------
    dict
        ``{"tiles": n_tiles_checked, "nnz": nnz}``.
    """
    fmt.check_tree_has_no_links(path, "")  # a store is a closed world
    check_chunks_exist(path, attrs, index)
    total = 0
    for i in progress_bar(range(attrs.grid[0]), progress=progress, desc="verify",
                          unit="tile row"):
        if complete:
            check_row_marker(path, index, i)
        for j, t in iter_tiles(i):
            _check_tile_entries(path, i, j, t)
            total += t.nnz
    if total != index.total_nnz:
        raise CorruptStoreError(f"tiles hold {total} entries, the index records "
                                f"{index.total_nnz}", path)
    return {"tiles": int(index.indices.size), "nnz": total}


def _check_tile_entries(path: Path, i: int, j: int, tile: sp.csr_array) -> None:
    """A stored tile is not empty and its column indices increase strictly in each row."""
    if tile.nnz == 0:
        raise tile_error(path, i, j, "stored tile is empty")
    d = np.diff(tile.indices)
    starts = tile.indptr[1:-1]
    ok = np.ones(d.size, dtype=bool)
    ok[starts[(starts > 0) & (starts <= d.size)] - 1] = False  # row boundaries
    if np.any(d[ok] <= 0):
        raise tile_error(path, i, j, "column indices not sorted and duplicate-free within a row")


def check_row_marker(path: Path, index: TileIndex, i: int) -> None:
    """Tile row ``i`` of a finalized store has a completion marker that agrees with
    ``index``; CorruptStoreError otherwise."""
    rec = fmt.row_marker(path, i)
    if rec is None:
        raise CorruptStoreError(f"tile row {i} has no completion marker "
                                f"({fmt.row_path(i)}/zarr.json missing or damaged)", path)
    if (list(rec.get("tile_columns", [])) != index.columns(i).tolist()
            or list(rec.get("tile_nnz", [])) != index.counts(i).tolist()):
        raise CorruptStoreError(f"tile row {i}: completion marker disagrees with the "
                                "tile index", path)


def missing_chunk_files(path: Path, attrs: StoreAttrs, index: TileIndex,
                        limit: int | None = None) -> list[str]:
    """Chunk files the stored tiles need but that are not on disk (stat only), as
    paths inside the store; the first ``limit`` found when given."""
    missing = []
    not_written = frozenset(index.missing_tile_rows)  # incomplete store: rows without files
    n_rows, n_cols = attrs.grid
    for i in range(n_rows):
        r0, r1 = attrs.tile_row_range(i)
        rows = r1 - r0 if n_cols else 0
        if attrs.version >= fmt.ROW_LAYOUT_VERSION:  # a tile row's three arrays
            if i in not_written:
                continue
            nnz = int(index.counts(i).sum())
            for name, length in (("indptr", rows + 1), ("indices", nnz), ("data", nnz)):
                missing += _missing_array_files(path, f"{fmt.row_path(i)}/{name}", length)
            if limit and len(missing) >= limit:
                return missing
            continue
        for k in range(index.indptr[i], index.indptr[i + 1]):
            tile = fmt.tile_path(i, int(index.indices[k]))
            nnz = int(index.nnz[k])
            for name, length in (("indptr", rows + 1), ("indices", nnz), ("data", nnz)):
                missing += _missing_array_files(path, f"{tile}/{name}", length)
                if limit and len(missing) >= limit:
                    return missing
    return missing


def _missing_array_files(path: Path, array: str, length: int) -> list[str]:
    """The files of the array at ``array`` (inside the store at ``path``) of ``length``
    entries that are not on disk: its zarr.json, else those of its chunks."""
    arr_dir = path / array
    if not (arr_dir / "zarr.json").is_file():
        return [f"{array}/zarr.json"]
    keys = _chunk_keys(path, arr_dir, length, config.CHUNK_ELEMENTS)
    return [f"{array}/{key}" for key in keys if not (arr_dir / key).is_file()]


def _chunk_keys(path: Path, arr_dir: Path, length: int, default_chunk: int) -> list[str]:
    """The chunk files of the array in ``arr_dir`` of ``length`` entries, from its
    zarr.json read as every metadata file is (bounded, no link, no FIFO); those of
    ``default_chunk`` entries when it is not bigT's layout."""
    meta = fmt.read_json(arr_dir / "zarr.json", root=path)
    try:
        (chunk,) = meta["chunk_grid"]["configuration"]["chunk_shape"]
        default_keys = meta["chunk_key_encoding"] == {"name": "default",
                                                      "configuration": {"separator": "/"}}
    except (KeyError, TypeError, ValueError):
        chunk, default_keys = default_chunk, True
    if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
        chunk = default_chunk
    n_chunks = -(-length // chunk)
    if not default_keys:  # another writer's key encoding: zarr spells the keys
        arr = zarr_array(path, arr_dir.relative_to(path).as_posix())
        return [arr.metadata.encode_chunk_key((c,)) for c in range(n_chunks)]
    return [f"c/{c}" for c in range(n_chunks)]
