"""Reading a block-CSR store's tile rows (format 2, :class:`RowReader`) and tiles
(format 1, :class:`TileReader`), checked.

Every read checks the cheap invariants of a CSR tile (lengths, monotone indptr, sorted
in-range column indices, finite values), always on: zarr reads a missing chunk as the
fill value (-1 or NaN), which none of these arrays may hold, so a damaged store fails
loudly instead of reading as a different matrix.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import BigTError, CorruptStoreError
from . import _format as fmt
from .objects import ObjectPath, concurrently

#: The stored tiles of tile row i, ``(j, tile)`` by ascending tile column j.
TileRowReader = Callable[[int], Iterable[tuple[int, sp.csr_array]]]


def zarr_array(root: Path, name: str):
    """The array ``name`` of the store at ``root`` opened by zarr-python, read only: for
    arrays whose layout bigT does not read itself (another writer's codecs). zarr is
    imported here (~0.2 s with its asyncio and fsspec machinery), not with the
    module: stores bigT wrote never need it."""
    import zarr

    if isinstance(root, ObjectPath):
        from zarr.storage import ObjectStore

        return zarr.open_array(ObjectStore(root.store, read_only=True),
                               path=f"{root.key}/{name}".lstrip("/"), mode="r")
    from zarr.storage import LocalStore

    return zarr.open_array(LocalStore(root, read_only=True), path=name, mode="r")


def open_zarr(path):
    """The zarr group or array at ``path`` (a directory or an :class:`ObjectPath`),
    opened read-only by zarr-python: for the groups around bigT's stores that bigT
    does not read itself (a scene's ground truth)."""
    import zarr

    if isinstance(path, ObjectPath):
        from zarr.storage import ObjectStore

        return zarr.open(ObjectStore(path.store, read_only=True), path=path.key, mode="r")
    return zarr.open(str(path), mode="r")


def tile_error(path: Path, i: int, j: int, problem: str) -> CorruptStoreError:
    """The error of a bad tile (i, j) of the store at ``path``."""
    return CorruptStoreError(f"tile ({i}, {j}): {problem}", path)


class TileReader:
    """Reads the tiles of the store at ``path``: from their files directly when bigT
    wrote them, else through zarr (whose opened arrays are kept for the next read)."""

    def __init__(self, path: Path):
        self._path = path
        self._arrays: dict[tuple[int, int], tuple] = {}

    def read(self, i: int, j: int, shape: tuple[int, int], nnz: int) -> sp.csr_array:
        """Tile (i, j) of ``shape`` (rows, cols) holding ``nnz`` entries, as the tile
        index records them; a csr_array with local, sorted indices.

        Raises
        ------
        CorruptStoreError
            The tile's arrays are unreadable or break a CSR invariant.
        """
        rows, cols = shape
        indptr, indices, data = self._read_arrays(i, j, (rows + 1, nnz, nnz))
        if indptr.shape != (rows + 1,) or indices.shape != (nnz,) or data.shape != (nnz,):
            raise tile_error(self._path, i, j, "array lengths disagree with the tile index")
        problem = _csr_problem(indptr, indices, data, cols)
        if problem:
            raise tile_error(self._path, i, j, problem)
        out = sp.csr_array((data, indices, indptr), shape=(rows, cols))
        out.has_sorted_indices = True  # checked above
        return out

    def _read_arrays(self, i: int, j: int, lengths: tuple[int, int, int]) -> list[np.ndarray]:
        """indptr, indices, data of tile (i, j), expected of ``lengths`` entries."""
        base = fmt.tile_path(i, j)
        try:
            direct = [fmt.read_array_files(self._path / base / name, n, root=self._path)
                      for name, n in zip(fmt.TILE_ARRAYS, lengths)]
            if any(a is None for a in direct):  # not bigT's own layout: zarr reads it
                direct = [a[...] for a in self._zarr_arrays(i, j)]
            return direct
        except BigTError:
            raise
        except Exception as exc:
            self._arrays.pop((i, j), None)
            raise tile_error(self._path, i, j,
                             f"unreadable ({type(exc).__name__}: {exc})") from None

    def _zarr_arrays(self, i: int, j: int) -> tuple:
        arrays = self._arrays.get((i, j))
        if arrays is None:
            base = fmt.tile_path(i, j)
            arrays = tuple(zarr_array(self._path, f"{base}/{name}")
                           for name in fmt.TILE_ARRAYS)
            self._arrays[(i, j)] = arrays
        return arrays


def _csr_problem(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray,
                 cols: int) -> str | None:
    """What breaks CSR in a tile of ``cols`` columns, or None: indptr (rows + 1,),
    indices and data (nnz,), of the lengths the index records."""
    nnz = indices.size
    if indptr[0] != 0 or indptr[-1] != nnz or np.any(indptr[1:] < indptr[:-1]):
        return "indptr is not monotone from 0 to the tile nnz (a chunk file is missing or damaged)"
    if nnz and (indices.min() < 0 or indices.max() >= cols):
        return "column indices out of range (a chunk file is missing or damaged)"
    if not sorted_within_rows(indptr, indices):
        return "column indices not sorted and duplicate-free within a row"
    if not np.isfinite(data).all():
        return "non-finite values (a chunk file is missing or damaged)"
    return None


def sorted_within_rows(indptr: np.ndarray, indices: np.ndarray) -> bool:
    """True when the column ``indices`` (nnz,) of a CSR tile increase strictly inside
    each row of ``indptr`` (rows + 1,). Vectorised: a step down is allowed only where
    a new row starts (~0.1 ms for a 64k-entry tile)."""
    if indices.size < 2:
        return True
    steps = np.diff(indices)
    starts = indptr[1:-1]
    steps[starts[(starts > 0) & (starts < indices.size)] - 1] = 1
    return not np.any(steps <= 0)


class RowReader:
    """Reads the tile rows of a format-2 store at ``path`` (a group of three arrays a
    tile row, global column indices): from their files directly when bigT wrote them,
    else through zarr."""

    def __init__(self, path: Path, attrs):
        self._path = path
        self._attrs = attrs

    def read(self, i: int, columns: np.ndarray, counts: np.ndarray) -> sp.csr_array:
        """Tile row ``i`` as a csr_array (rows_i, n_cols), global sorted columns; the
        row's stored tile ``columns`` (k,) hold ``counts`` (k,) entries each, as the
        tile index records them, and the row must agree.

        Raises
        ------
        CorruptStoreError
            An array unreadable, of another length, or breaking CSR; entries in tiles
            the index does not record, or other counts.
        """
        r0, r1 = self._attrs.tile_row_range(i)
        rows, n_cols = r1 - r0, self._attrs.shape[1]
        nnz = int(counts.sum())
        indptr, indices, data = self._read_arrays(i, (rows + 1, nnz, nnz))
        if indptr.shape != (rows + 1,) or indices.shape != (nnz,) or data.shape != (nnz,):
            raise row_error(self._path, i, "array lengths disagree with the tile index")
        if (indptr.dtype != np.int64 or indices.dtype.kind != "i"
                or data.dtype != self._attrs.dtype):
            raise row_error(self._path, i, f"arrays of types {indptr.dtype}, {indices.dtype}, "
                                           f"{data.dtype}: the format has an int64 indptr, "
                                           f"integer indices and {self._attrs.dtype} data")
        problem = _row_problem(indptr, indices, data, n_cols, self._attrs.tile_size,
                               columns, counts)
        if problem:
            raise row_error(self._path, i, problem)
        if nnz < np.iinfo(np.int32).max and indices.dtype == np.int32:
            indptr = indptr.astype(np.int32)  # else scipy widens (copies) the indices
        out = sp.csr_array((data, indices, indptr), shape=(rows, n_cols))
        out.has_sorted_indices = True  # checked above
        return out

    def _read_arrays(self, i: int, lengths: tuple[int, int, int]) -> list[np.ndarray]:
        base = fmt.row_path(i)

        def read(array: tuple[str, int]):
            return fmt.read_array_files(self._path / base / array[0], array[1], root=self._path)

        try:
            arrays = list(zip(fmt.TILE_ARRAYS, lengths))
            # in object storage the three arrays' requests go together (latency, not
            # bandwidth, is what a small row's read waits for)
            direct = (concurrently(read, arrays) if isinstance(self._path, ObjectPath)
                      else [read(a) for a in arrays])
            if any(a is None for a in direct):  # not bigT's own layout: zarr reads it
                direct = [zarr_array(self._path, f"{base}/{name}")[...]
                          for name in fmt.TILE_ARRAYS]
            return direct
        except BigTError:
            raise
        except Exception as exc:
            raise row_error(self._path, i, f"unreadable ({type(exc).__name__}: {exc})") from None


def row_error(path: Path, i: int, problem: str) -> CorruptStoreError:
    """The error of a bad tile row ``i`` of the store at ``path``."""
    return CorruptStoreError(f"tile row {i}: {problem}", path)


def _row_problem(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, cols: int,
                 tile_size: int, columns: np.ndarray, counts: np.ndarray) -> str | None:
    """What is wrong with a tile row's arrays (:func:`_csr_problem`, then
    :func:`_tile_count_problem`), or None. A big row is checked first in one pass of
    the kernels (:func:`bigT.kernels.row_ranges.checked_tile_counts`); only a row it
    finds wrong goes through numpy's checks, which say what."""
    if indices.size > config.KERNEL_NUMPY_MAX_WORK:
        from ..kernels.row_ranges import checked_tile_counts  # numba: only for big rows

        found = checked_tile_counts(indptr, indices, data, cols, tile_size)
        if found is not None:
            present = np.flatnonzero(found)
            if np.array_equal(present, columns) and np.array_equal(found[present], counts):
                return None
    return (_csr_problem(indptr, indices, data, cols)
            or _tile_count_problem(indices, tile_size, columns, counts))


def _tile_count_problem(indices: np.ndarray, tile_size: int, columns: np.ndarray,
                        counts: np.ndarray) -> str | None:
    """What disagrees between a row's global column ``indices`` (nnz,) and the tile
    index's stored tile ``columns`` and their ``counts`` (k,), or None."""
    if not indices.size:
        return None if not counts.size else "entries missing from stored tiles"
    found = _entries_per_tile(indices, tile_size)
    present = np.flatnonzero(found)
    if not np.array_equal(present, columns) or not np.array_equal(found[present], counts):
        return "entries per tile disagree with the tile index"
    return None


#: Widest matrix whose per-column counts :func:`_entries_per_tile` takes (a scratch of
#: 8 bytes a column, 32 MiB here): counting columns, then summing them per tile, is
#: twice as quick as dividing every index by the tile size.
_COLUMN_COUNT_MAX = 1 << 22


def _entries_per_tile(indices: np.ndarray, tile_size: int) -> np.ndarray:
    """(n_tile_cols_used,) int64: entries of each tile column, from column ``indices``
    (nnz,) checked to lie in the matrix."""
    width = int(indices.max()) + 1
    if width > _COLUMN_COUNT_MAX or width > 4 * indices.size:  # a scratch wider than the row
        return np.bincount(indices // tile_size)
    return np.add.reduceat(np.bincount(indices, minlength=width),
                           np.arange(0, width, tile_size))
