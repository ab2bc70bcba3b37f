"""The tile index of a block-CSR store: which tiles of which tile row are stored, and
their nnz, read once when a store is opened and checked before anything is trusted.

A finalized store keeps its index in three arrays (``tile_indptr``, ``tile_indices``,
``tile_nnz``); an unfinalized one has only the completion marker of each written tile
row, from which the index is rebuilt (:func:`read_tile_index` picks the source).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import BigTError, CorruptStoreError, IncompleteStoreError, Option
from . import _format as fmt
from .attrs import StoreAttrs
from .tiles import zarr_array


@dataclass(frozen=True)
class TileIndex:
    """Which tiles a store holds, tile row by tile row (a CSR pattern of the tile grid).

    Attributes
    ----------
    indptr : (n_tile_rows + 1,) int64
        Tile row ``i`` owns entries ``indptr[i]:indptr[i + 1]`` of the two arrays below.
    indices : (n_tiles_stored,) int64
        Tile columns of the stored tiles, ascending within each tile row.
    nnz : (n_tiles_stored,) int64
        Entries of each stored tile (at least 1, at most its area).
    missing_tile_rows : tuple of int
        Tile rows not marked complete (an unfinalized store opened with
        ``allow_incomplete``); they read as empty.
    """

    indptr: np.ndarray
    indices: np.ndarray
    nnz: np.ndarray
    missing_tile_rows: tuple[int, ...] = ()

    @property
    def total_nnz(self) -> int:
        """Entries of the whole matrix."""
        return int(self.nnz.sum())

    def columns(self, i: int) -> np.ndarray:
        """(k,) int64: tile columns of the stored tiles of tile row ``i`` (unchecked ``i``)."""
        return self.indices[self.indptr[i]:self.indptr[i + 1]]

    def counts(self, i: int) -> np.ndarray:
        """(k,) int64: nnz of the stored tiles of tile row ``i`` (unchecked ``i``)."""
        return self.nnz[self.indptr[i]:self.indptr[i + 1]]

    def position(self, i: int, j: int) -> int:
        """Entry of tile (i, j) in ``indices``, or -1 when it is not stored (unchecked)."""
        lo, hi = self.indptr[i], self.indptr[i + 1]
        k = lo + int(np.searchsorted(self.indices[lo:hi], j))
        return k if k < hi and self.indices[k] == j else -1


def read_tile_index(path: Path, attrs: StoreAttrs, *, allow_incomplete: bool) -> TileIndex:
    """The checked tile index of the store at ``path``: its index arrays when it is
    finalized, else its row markers.

    Raises
    ------
    CorruptStoreError
        The index (or a row marker) is damaged or disagrees with ``attrs``.
    IncompleteStoreError
        The store is unfinalized and ``allow_incomplete`` is False.
    """
    if attrs.complete:
        return _load_index(path, attrs)
    return _scan_rows(path, attrs, allow_incomplete)


# --- a finalized store: the index arrays --------------------------------------------

def _load_index(path: Path, attrs: StoreAttrs) -> TileIndex:
    n_rows, n_cols = attrs.grid
    # each array's declared length is checked against what the grid and the arrays
    # read before it imply, before anything of that length is allocated
    indptr = _read_index_array(path, "tile_indptr", n_rows + 1)
    problem = _indptr_problem(indptr, n_rows * n_cols)
    if problem:
        raise CorruptStoreError(problem, path)
    indices = _read_index_array(path, "tile_indices", int(indptr[-1]))
    nnz = _read_index_array(path, "tile_nnz", int(indptr[-1]))
    problem = _entries_problem(attrs, indptr, indices, nnz)
    if problem:
        raise CorruptStoreError(problem, path)
    return TileIndex(indptr, indices, nnz)


def _indptr_problem(indptr: np.ndarray, n_tiles: int) -> str | None:
    """What is wrong with ``indptr`` (n_tile_rows + 1,) for a grid of ``n_tiles``, or None."""
    if indptr[0] != 0 or np.any(np.diff(indptr) < 0):
        return "tile_indptr is not a valid index pointer for the tile grid"
    if indptr[-1] > n_tiles:
        return f"tile_indptr counts {indptr[-1]} tiles, the grid has {n_tiles}"
    return None


def _entries_problem(attrs: StoreAttrs, indptr: np.ndarray, indices: np.ndarray,
                     nnz: np.ndarray) -> str | None:
    """What is wrong with the tile columns and counts (n_tiles_stored,), or None; the
    first problem found, in the order the checks are listed."""
    if indices.size and (indices.min() < 0 or indices.max() >= attrs.grid[1]):
        return "tile_indices out of range (a chunk file is missing or damaged)"
    if nnz.size and nnz.min() < 1:
        return "tile_nnz holds non-positive counts (a chunk file is missing or damaged)"
    if np.any(nnz > _tile_areas(attrs, indptr, indices)):
        return "tile_nnz holds counts larger than their tile"
    if int(nnz.sum()) != (-1 if attrs.nnz is None else attrs.nnz):
        return f"tile_nnz sums to {int(nnz.sum())}, attrs record nnz={attrs.nnz}"
    bad = _first_unordered_row(indptr, indices)
    if bad is not None:
        return f"tile_indices of tile row {bad} not strictly increasing"
    return None


def _first_unordered_row(indptr: np.ndarray, indices: np.ndarray) -> int | None:
    """The first tile row whose tile columns do not strictly increase, or None."""
    # within a tile row, tile columns strictly increase: a step down or a repeat is
    # allowed only where a new tile row starts
    steps = np.diff(indices)
    starts = indptr[1:-1]
    steps[starts[(starts > 0) & (starts < indices.size)] - 1] = 1
    if not np.any(steps <= 0):
        return None
    return int(np.searchsorted(indptr, np.flatnonzero(steps <= 0)[0] + 1, "right")) - 1


def _tile_areas(attrs: StoreAttrs, indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(n_tiles_stored,) int64: rows x columns of each stored tile (ragged edges)."""
    ts = attrs.tile_size
    tile_rows = np.repeat(np.arange(indptr.size - 1, dtype=np.int64), np.diff(indptr))
    heights = np.minimum(ts, attrs.shape[0] - tile_rows * ts)
    widths = np.minimum(ts, attrs.shape[1] - indices * ts)
    return heights * widths


def _read_index_array(path: Path, name: str, length: int) -> np.ndarray:
    """One array of the tile index, of ``length`` entries, as int64; read from its
    files directly when bigT wrote them (zarr's open and read cost ~5 ms a store,
    more than a small term's work), else through zarr.

    Raises
    ------
    CorruptStoreError
        Its metadata declares another length, or a chunk is damaged.
    """
    try:
        values = fmt.read_array_files(path / name, length, root=path)
        if values is None:
            values = zarr_array(path, name)[...]
        return np.asarray(values, dtype=np.int64)
    except BigTError:
        raise
    except FileNotFoundError:
        raise CorruptStoreError(f"cannot read the tile index: {name} is missing",
                                path) from None
    except Exception as exc:
        raise CorruptStoreError(f"cannot read the tile index ({type(exc).__name__}: {exc})",
                                path) from None


# --- an unfinalized store: the row markers ------------------------------------------

def _scan_rows(path: Path, attrs: StoreAttrs, allow_incomplete: bool) -> TileIndex:
    """The tile index of an unfinalized store, from the row markers on disk: only
    rows whose directory is listed are read (a store declaring 10^12 rows costs what
    it holds, not what it declares)."""
    n_rows = attrs.grid[0]
    lengths = np.zeros(n_rows, np.int64)
    cols, counts, present = [], [], []
    for i in fmt.stored_tile_rows(path, n_rows):
        rec = fmt.row_marker(path, i)
        if rec is None:
            continue
        c, k = _checked_marker(path, attrs, i, rec)
        present.append(i)
        cols.extend(c)
        counts.extend(k)
        lengths[i] = len(c)
    is_present = np.zeros(n_rows, bool)
    is_present[present] = True
    missing = np.flatnonzero(~is_present).tolist()
    if not allow_incomplete:
        raise _incomplete(path, missing, n_rows)
    return TileIndex(
        np.concatenate([[0], np.cumsum(lengths, dtype=np.int64)]).astype(np.int64),
        np.asarray(cols, dtype=np.int64), np.asarray(counts, dtype=np.int64), tuple(missing))


def _incomplete(path: Path, missing: list[int], n_rows: int) -> IncompleteStoreError:
    """The error of an unfinalized store opened without ``allow_incomplete``, naming
    the first ``missing`` tile rows and how to finish the store."""
    if missing:
        first = ", ".join(str(i) for i in missing[:5]) + (", ..." if len(missing) > 5 else "")
        msg = (f"incomplete store: {len(missing)} of {n_rows} tile rows are missing "
               f"(rows {first}); to resume writing: {{option}}")
    else:
        msg = "incomplete store: all tile rows written but the writer never finalized; " \
              "to finish it: {option}"
    return IncompleteStoreError(msg, path, option=Option(
        "resume", python="resume=True, then finalize()",
        cli="rerun the command that wrote it"))


def _checked_marker(path: Path, attrs: StoreAttrs, i: int,
                    rec: dict) -> tuple[list[int], list[int]]:
    """(tile_columns, tile_nnz) of tile row ``i``'s completion marker, checked:
    integers, columns strictly increasing inside the grid, counts within their
    tile. CorruptStoreError naming the marker's file otherwise."""
    where = path / fmt.row_path(i) / "zarr.json"
    c, k = rec.get("tile_columns", []), rec.get("tile_nnz", [])
    if not isinstance(c, list) or not isinstance(k, list) or len(c) != len(k):
        raise CorruptStoreError("completion marker: tile_columns and tile_nnz must be "
                                "lists of the same length", where)
    ts = attrs.tile_size
    height = min(ts, attrs.shape[0] - i * ts)
    previous = -1
    for j, count in zip(c, k):
        fmt.check_count(j, "tile column", where, low=previous + 1, high=attrs.grid[1] - 1)
        width = min(ts, attrs.shape[1] - j * ts)
        fmt.check_count(count, "tile nnz", where, low=1, high=height * width)
        previous = j
    return c, k
