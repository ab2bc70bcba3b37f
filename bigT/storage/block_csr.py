"""Reading a bigT block-CSR store: :func:`open` and :class:`BlockCSR`.

The tile index (which tiles of which tile row are stored, and their nnz) is read once
on open and kept in memory. A format-2 store keeps each tile row whole (three arrays,
global columns): a tile row is one read, and a tile is cut from its row; a format-1
store (a group per tile) is read tile by tile, as it was written.

Pixel-indexed vectors and matrices the public methods take or return (``A @ x``,
:meth:`BlockCSR.matmul`, :meth:`BlockCSR.to_scipy`, :meth:`BlockCSR.diagonal`) are in
row-major image order (``image.ravel()``, what ``bigT export`` writes) by default. The
store's own order (tile-major for scenes, :mod:`bigT.storage.pixel_order`) is the
engine's: ``order="matrix"`` / ``output_order="matrix"`` asks for it explicitly, and
the tile methods (``get_tile``, ``get_tile_row``, ``get_rows``) speak only it.

A colour store may be factored (``BlockCSR.mixing``, docs/FORMAT.md "Colour"): it
represents (I (x) L) S (I (x) R) with S its tiles. The public products (``@``,
``matmul``, ``to_scipy``, ``diagonal``, ``represented_rows``) are of the represented
matrix; the tile methods read S as stored.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import MemoryLimitError, ShapeMismatchError, StoreError
from . import _format as fmt
from . import checks
from .attrs import StoreAttrs, read_raw_attrs
from .channel_mixing import ChannelMixing, mixed_diagonal, mixed_product, mixed_rows
from .locks import ReaderLease
from .objects import ObjectPath, as_location
from .products import (
    diagonal_of_tiles,
    matmul_rows,
    matmul_tiles,
    reordering,
    to_row_major,
)
from .replace import recover_interrupted_replace, write_root_attrs
from .rows import join_tile_row, rows_between
from .summary import summary
from .tile_index import read_tile_index
from .tiles import RowReader, TileReader

# --- the store ---------------------------------------------------------------------


@dataclass(frozen=True)
class DiagonalScan:
    """What reading a store's diagonal learned (:meth:`BlockCSR.diagonal_scan`).

    Attributes
    ----------
    diagonal : ndarray, shape (min(shape),), the store's dtype
    smallest : float or None
        The smallest stored entry, capped at 0 (min(0, entries)): a value < 0 says
        the matrix has a negative entry, 0.0 that it has none. None where the read
        did not see every entry (diagonal tiles only, a tile row without one, a
        factored colour store).
    """

    diagonal: np.ndarray
    smallest: float | None

#: Most tile rows ``diagonal`` reads at once (format 2): each is held whole.
_DIAGONAL_READERS = 4

#: Times ``open`` follows a redirect that moved on while it took the term's lease.
_LEASE_ATTEMPTS = 5


def as_store(A, name: str = "matrix") -> "BlockCSR":
    """The store ``A`` stands for: a :class:`BlockCSR` as it is, a path opened with
    :func:`open`. The one way every layer turns an argument into a store.

    Raises
    ------
    StoreError
        ``A`` is neither (naming ``name`` and the type given).
    """
    if isinstance(A, BlockCSR):
        return A
    if isinstance(A, (str, os.PathLike, ObjectPath)):
        return open(A)
    raise StoreError(f"{name} must be a bigT store (BlockCSR) or the path of one, "
                     f"got {type(A).__name__}")


def open(path, *, allow_incomplete: bool = False,  # noqa: A001
         storage_options: dict | None = None) -> "BlockCSR":
    """Open a bigT block-CSR store for reading.

    Parameters
    ----------
    path : str, os.PathLike or URL
        Directory of the zarr v3 group, or its URL in object storage
        (``s3://bucket/prefix/T.zarr``, ``gs://``, ``az://``, ``memory://``). A group
        whose ``attrs["bigT"]["redirect"]`` names a sub-path is followed (one level):
        that is a versioned store.
    allow_incomplete : bool
        Open a store whose writing was interrupted; tile rows not marked complete then
        read as empty (``.missing_tile_rows`` lists them).
    storage_options : dict, optional
        For a URL: options of the object store (``endpoint``, ``region``,
        ``client_options``...); the standard environment variables give the rest
        (``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``, ...).

    Raises
    ------
    StoreError
        Not a bigT store; a redirect that is invalid or points at another redirect.
    IncompleteStoreError
        Some tile rows are not marked complete, or the writer never finalized.
    CorruptStoreError
        The tile index is damaged or disagrees with the recorded nnz.
    """
    root = as_location(path, storage_options)
    if not root.exists():
        recover_interrupted_replace(root)  # a replace killed half way: the old store back
    for _attempt in range(_LEASE_ATTEMPTS):
        lease = ReaderLease(root)  # before reading: the store stays while it is held
        attrs = read_raw_attrs(root)
        if "redirect" not in attrs:
            return BlockCSR(root, StoreAttrs.from_dict(attrs, root),
                            allow_incomplete=allow_incomplete, lease=lease)
        lease.release()
        target = fmt.redirect_target(attrs["redirect"], root)
        # the lease keeps the term from being deleted while this reader holds it
        lease = ReaderLease(target)
        if lease.valid:
            attrs = read_raw_attrs(target)
            if "redirect" in attrs:
                raise StoreError("redirect points at another redirect (one level is followed)",
                                 root)
            return BlockCSR(target, StoreAttrs.from_dict(attrs, target),
                            allow_incomplete=allow_incomplete, redirected_from=root,
                            lease=lease)
        lease.release()  # deleted before the lease was taken: the redirect moved on
    raise StoreError("its current term was replaced while opening, again and again; "
                     "try again", root)


class BlockCSR:
    """A sparse matrix stored as a grid of CSR tiles in a zarr v3 group.

    Use :func:`bigT.storage.open` or :func:`bigT.storage.from_scipy` to get one.

    Attributes
    ----------
    path : pathlib.Path
        Directory of the store actually read (the redirect target, if any).
    shape : (int, int)
    dtype : numpy.dtype
        float32 or float64.
    nnz : int
    tile_size : int
    grid : (int, int)
        (n_tile_rows, n_tile_cols); the last tile row/column may be ragged.
    pixel_order : PixelOrder or None
        How image pixels are numbered in the stored matrix. Vectors of ``A @ x``,
        ``matmul``, ``to_scipy`` and ``diagonal`` are row-major image vectors unless
        asked for in ``"matrix"`` order; tiles and rows are always in matrix order.
    channels : int
        1 for grey; 3 for colour, where index 3 p + c is channel c (R, G, B) of the
        pixel numbered p (the vector of an (H, W, 3) image is its row-major ravel).
    mixing : ChannelMixing or None
        Colour only, a factored store: the matrix represented is (I (x) L) S (I (x) R)
        with ``(L, R) = mixing`` and S the stored tiles. ``@``, ``matmul``,
        ``to_scipy``, ``diagonal`` and ``represented_rows`` honour it; the tile and row
        methods (``get_tile``, ``iter_tiles``, ``get_tile_row``, ``get_rows``) return S.
    metadata : dict
        Free JSON metadata (the inverse engine records term, prune, residual there).
    tile_indptr : (n_tile_rows + 1,) int64
    tile_indices : (n_tiles_stored,) int64
        Tile columns of the stored tiles, tile row by tile row, ascending.
    tile_nnz : (n_tiles_stored,) int64
    """

    def __init__(self, path: Path, attrs: StoreAttrs, *, allow_incomplete: bool = False,
                 redirected_from: Path | None = None, lease: ReaderLease | None = None):
        self.path = as_location(path)
        self._lease = lease  # released with this object
        self.redirected_from = redirected_from
        self.attrs = attrs
        self.shape = attrs.shape
        self.tile_size = attrs.tile_size
        self.dtype = attrs.dtype
        self.inner_format = attrs.inner_format
        self.complete = attrs.complete
        self.grid = attrs.grid
        self.pixel_order = attrs.pixel_order
        self.channels = attrs.channels
        self.mixing: ChannelMixing | None = attrs.mixing
        self.metadata = dict(attrs.metadata)
        self._index = read_tile_index(self.path, attrs, allow_incomplete=allow_incomplete)
        self.tile_indptr = self._index.indptr
        self.tile_indices = self._index.indices
        self.tile_nnz = self._index.nnz
        self.nnz = self._index.total_nnz
        self.missing_tile_rows: list[int] = list(self._index.missing_tile_rows)
        self._missing_rows = frozenset(self.missing_tile_rows)  # format 2: no files
        #: True for format 2 (a tile row is stored whole), False for format 1 (tiles)
        self.row_layout = attrs.version >= fmt.ROW_LAYOUT_VERSION
        self._rows = RowReader(self.path, attrs) if self.row_layout else None
        self._tiles = None if self.row_layout else TileReader(self.path)

    # --- geometry ------------------------------------------------------------------

    @property
    def n_tiles_stored(self) -> int:
        return int(self.tile_indices.size)

    def _check_tile_row(self, i: int) -> int:
        i = int(i)
        if not 0 <= i < self.grid[0]:
            raise ShapeMismatchError(f"tile row {i} out of range [0, {self.grid[0]})", self.path)
        return i

    def tile_row_range(self, i: int) -> tuple[int, int]:
        """(start, stop) matrix rows of tile row ``i``."""
        i = self._check_tile_row(i)
        return i * self.tile_size, min((i + 1) * self.tile_size, self.shape[0])

    def tile_col_range(self, j: int) -> tuple[int, int]:
        """(start, stop) matrix columns of tile column ``j``."""
        j = int(j)
        if not 0 <= j < self.grid[1]:
            raise ShapeMismatchError(f"tile column {j} out of range [0, {self.grid[1]})", self.path)
        return j * self.tile_size, min((j + 1) * self.tile_size, self.shape[1])

    def tile_shape(self, i: int, j: int) -> tuple[int, int]:
        r0, r1 = self.tile_row_range(i)
        c0, c1 = self.tile_col_range(j)
        return r1 - r0, c1 - c0

    def tile_columns(self, i: int) -> np.ndarray:
        """(k,) int64: tile columns of the stored tiles of tile row ``i``, ascending."""
        i = self._check_tile_row(i)
        return self.tile_indices[self.tile_indptr[i]:self.tile_indptr[i + 1]]

    def _position(self, i: int, j: int) -> int:
        """Index of tile (i, j) in tile_indices, or -1 when the tile is not stored."""
        i = self._check_tile_row(i)
        self.tile_col_range(j)
        return self._index.position(i, int(j))

    def has_tile(self, i: int, j: int) -> bool:
        return self._position(i, j) >= 0

    # --- tiles ---------------------------------------------------------------------

    def _read_tile(self, i: int, j: int, k: int) -> sp.csr_array:
        """Stored tile (i, j), entry ``k`` of the tile index, read and checked."""
        if self.row_layout:
            return self._cut_tile(self._read_row(i), j)
        return self._tiles.read(i, j, self.tile_shape(i, j), int(self.tile_nnz[k]))

    def _read_row(self, i: int) -> sp.csr_array:
        """Format 2: tile row ``i`` as stored, read and checked (global columns)."""
        lo, hi = self.tile_indptr[i], self.tile_indptr[i + 1]
        if lo == hi and i in self._missing_rows:  # never written: reads as empty
            r0, r1 = self.tile_row_range(i)
            return sp.csr_array((r1 - r0, self.shape[1]), dtype=self.dtype)
        return self._rows.read(i, self.tile_indices[lo:hi], self.tile_nnz[lo:hi])

    def _cut_tile(self, row: sp.csr_array, j: int) -> sp.csr_array:
        """Tile column ``j`` of a tile ``row`` (global columns), local columns."""
        c0, c1 = self.tile_col_range(j)
        tile = sp.csr_array(row[:, c0:c1])
        tile.has_sorted_indices = True
        return tile

    def get_tile(self, i: int, j: int) -> sp.csr_array:
        """Tile (i, j) as a csr_array of shape ``tile_shape(i, j)`` (local indices).

        An empty csr_array of that shape when the tile is not stored.
        """
        k = self._position(i, j)
        if k < 0:
            return sp.csr_array(self.tile_shape(i, j), dtype=self.dtype)
        return self._read_tile(int(i), int(j), k)

    def iter_tiles(self, i: int, columns=None):
        """Yield ``(j, tile)`` for the stored tiles of tile row ``i`` (only those in
        ``columns``, a collection of tile columns, when given)."""
        i = self._check_tile_row(i)
        wanted = None if columns is None else {int(j) for j in columns}
        if self.row_layout:
            yield from self._row_tiles(i, wanted)
            return
        for k in range(self.tile_indptr[i], self.tile_indptr[i + 1]):
            j = int(self.tile_indices[k])
            if wanted is None or j in wanted:
                yield j, self._read_tile(i, j, int(k))

    def _row_tiles(self, i: int, wanted: set[int] | None):
        """Format 2: ``(j, tile)`` of tile row ``i``, one read of the row, split."""
        from ..kernels.csr import split_column_tiles  # numba: only once a row is split

        row = self._read_row(i)
        if not row.nnz:
            return
        tiles = split_column_tiles(row.indptr, row.indices, row.data, self.tile_size)
        for t, j in enumerate(tiles.cols):
            j = int(j)
            if wanted is not None and j not in wanted:
                continue
            part = slice(tiles.bounds[t], tiles.bounds[t + 1])
            tile = sp.csr_array((tiles.data[part], tiles.indices[part], tiles.indptr[t]),
                                shape=self.tile_shape(i, j))
            tile.has_sorted_indices = True
            yield j, tile

    def get_tile_row(self, i: int, columns=None) -> sp.csr_array:
        """Tile row ``i`` as a csr_array of shape (rows_i, n_cols), global columns in
        matrix order; only the tiles in ``columns`` (tile columns) when given, the
        others empty."""
        r0, r1 = self.tile_row_range(i)
        if not self.row_layout:
            return join_tile_row(self.iter_tiles(i, columns), r1 - r0, self.attrs, self.dtype)
        row = self._read_row(self._check_tile_row(i))
        if columns is None:
            return row
        keep = np.isin(row.indices // self.tile_size, np.asarray(list(columns), np.int64))
        if keep.all():
            return row
        return _entries_kept(row, keep)

    def get_rows(self, start: int, stop: int) -> sp.csr_array:
        """Matrix rows ``start:stop`` as a csr_array of shape (stop - start, n_cols),
        global columns, in matrix order; the range may lie inside one tile row or span
        several."""
        start, stop = int(start), int(stop)
        if not 0 <= start <= stop <= self.shape[0]:
            raise ShapeMismatchError(f"rows {start}:{stop} out of range [0, {self.shape[0]}]",
                                     self.path)
        return rows_between(start, stop, self.attrs, self.dtype, self.get_tile_row)

    def diagonal(self, output_order: str = "row-major") -> np.ndarray:
        """The main diagonal, reading diagonal tiles only.

        Parameters
        ----------
        output_order : {"row-major", "matrix"}
            "row-major" (default): entry p is pixel p of ``image.ravel()``, the same as
            ``to_scipy().diagonal()``. "matrix": as stored (the engine's order).

        Returns
        -------
        ndarray, shape (min(shape),), of the store's dtype
        """
        return self.diagonal_scan(output_order).diagonal

    def diagonal_scan(self, output_order: str = "row-major", keep=None) -> DiagonalScan:
        """:meth:`diagonal`, and the smallest stored entry where the diagonal's read
        saw every stored entry (format 2 reads each tile row that holds a diagonal
        tile whole): a transport known to have no negative entry then costs no pass
        of its own (:meth:`bigT.algorithms.matvecs.MatVecs.m_nonpositive`).
        ``keep(i, row)``, when given, is handed each tile row read whole (global
        columns, not to be modified), for a caller that uses it next."""
        order = reordering(self.pixel_order, output_order, "output_order")
        smallest = None
        if self.mixing is None and self.row_layout:
            diag, smallest = self._diagonal_of_rows(keep)
        elif self.mixing is None:
            diag = diagonal_of_tiles(self.attrs, self._diagonal_tile)
        else:
            diag = mixed_diagonal(self.mixing, self._stored_pixel_blocks()).astype(self.dtype)
        return DiagonalScan(diag if order is None else diag[order.inverse_permutation],
                            smallest)

    def _diagonal_of_rows(self, keep=None) -> tuple[np.ndarray, float | None]:
        """Format 2: the main diagonal in the stored order, each tile row that holds
        its diagonal tile read whole; rows are read on a few threads (decoding and
        checking release the GIL), since every entry of them is read. Also the
        smallest entry of those rows (0.0 for none), or None when a tile row holding
        entries was not read (no diagonal tile): then it is not T's smallest."""
        from concurrent.futures import ThreadPoolExecutor

        n, ts = min(self.shape), self.tile_size
        out = np.zeros(n, dtype=self.dtype)
        rows = [i for i in range(min(self.grid)) if self._position(i, i) >= 0]

        def part(i: int) -> tuple[int, np.ndarray, float]:
            row = self._read_row(i)
            low = float(row.data.min(initial=0.0))  # an empty row: nothing below 0
            if keep is not None:
                keep(i, row)
            return i, row.diagonal(k=i * ts), low  # entries (r, i ts + r)

        # a few threads: each holds a whole tile row
        workers = max(1, min(len(rows), os.cpu_count() or 1, _DIAGONAL_READERS))
        smallest = 0.0
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for i, d, low in pool.map(part, rows):
                out[i * ts:i * ts + d.size] = d[:n - i * ts]
                smallest = min(smallest, low)
        unread = np.diff(np.asarray(self.tile_indptr)) > 0
        unread[rows] = False
        return out, (None if unread.any() else smallest)

    def _diagonal_tile(self, i: int) -> sp.csr_array | None:
        """Tile (i, i), or None when it is not stored."""
        k = self._position(i, i)
        return None if k < 0 else self._read_tile(i, i, k)

    def _stored_pixel_blocks(self) -> np.ndarray:
        """(n / 3, 3, 3) float64: S's 3x3 diagonal blocks of a colour store, matrix
        order, from the diagonal tiles (a tile size that is a multiple of 3 holds each)."""
        out = np.zeros((self.shape[0] // 3, 3, 3))
        for i in range(min(self.grid)):
            tile = self._diagonal_tile(i)
            if tile is None:
                continue
            coo = sp.coo_array(tile)
            same = coo.row // 3 == coo.col // 3
            r, c = coo.row[same].astype(np.int64), coo.col[same].astype(np.int64)
            np.add.at(out, ((i * self.tile_size + r) // 3, r % 3, c % 3), coo.data[same])
        return out

    def represented_rows(self, start: int, stop: int) -> sp.csr_array:
        """Rows ``start:stop`` of the matrix the store represents (``get_rows`` with
        the mixing applied: whole pixels, ``start`` and ``stop`` multiples of 3, for a
        factored store), matrix order, global columns."""
        return mixed_rows(self.mixing, self.get_rows(start, stop), int(start))

    def csr_bytes(self) -> int:
        """Bytes of the CSR arrays of the whole matrix in memory (int64 index)."""
        return self.nnz * (self.dtype.itemsize + 8) + (self.shape[0] + 1) * 8

    def to_scipy(self, max_bytes: int | None = None,
                 output_order: str = "row-major") -> sp.csr_array:
        """The whole matrix in memory as a csr_array.

        Parameters
        ----------
        max_bytes : int, optional
            Refuse (MemoryLimitError) beyond this many bytes of CSR arrays; default
            ``config.TO_SCIPY_MAX_BYTES``.
        output_order : {"row-major", "matrix"}
            "row-major" (default): rows and columns in row-major image order, so that
            ``to_scipy() @ image.ravel()`` is ``A @ image.ravel()``; the matrix ``bigT
            export`` writes. "matrix": as stored (the engine's order, no permutation).
            The two are the same for a store that records no pixel order.

        Returns
        -------
        scipy.sparse.csr_array, shape ``shape``, sorted indices
        """
        order = reordering(self.pixel_order, output_order, "output_order")
        limit = config.TO_SCIPY_MAX_BYTES if max_bytes is None else int(max_bytes)
        need = self.csr_bytes() * (1 if self.mixing is None else 3)  # mixed: 3x3 blocks
        if need > limit:
            raise MemoryLimitError(f"to_scipy needs about {need / 2**20:.1f} MiB of CSR arrays, "
                                   f"over the limit of {limit / 2**20:.1f} MiB; stream tile rows "
                                   f"(get_tile_row) or raise max_bytes", self.path)
        if self.grid[0] == 0:
            out = sp.csr_array(self.shape, dtype=self.dtype)
        else:
            out = sp.vstack([self.get_tile_row(i) for i in range(self.grid[0])], format="csr")
            out = mixed_rows(self.mixing, sp.csr_array(out), 0)
        if order is not None:
            out = to_row_major(out, order)
        out.has_sorted_indices = True
        return out

    # --- products ------------------------------------------------------------------

    def matmul(self, x: np.ndarray, *, order: str = "row-major") -> np.ndarray:
        """``A @ x`` for dense x of shape (n_cols,) or (n_cols, k), streaming tile rows.

        Parameters
        ----------
        x : ndarray, shape (n_cols,) or (n_cols, k)
        order : {"row-major", "matrix"}
            The order of the pixels of ``x`` and of the result. "row-major" (default):
            ``image.ravel()`` vectors, ``A @ image.ravel()`` equals ``A.to_scipy() @
            image.ravel()`` and ``bigT.relight(A, image).ravel()``; x and the result are
            permuted to and from the stored order. "matrix": the store's own order, no
            permutation (the engine's). The same for a store without a pixel order.

        Returns
        -------
        ndarray, shape (n_rows,) or (n_rows, k), of the promoted float dtype
        """
        reorder = reordering(self.pixel_order, order, "order")
        x = np.asarray(x)
        if x.ndim not in (1, 2) or x.shape[0] != self.shape[1]:
            raise ShapeMismatchError(f"cannot multiply a {self.shape} matrix by an array of shape "
                                     f"{x.shape}: need ({self.shape[1]},) or ({self.shape[1]}, k)",
                                     self.path)
        dtype = np.result_type(self.dtype, x.dtype, np.float32)
        X = x.reshape(self.shape[1], -1)
        if reorder is not None:
            X = X[reorder.permutation]  # row-major pixels to matrix indices (a copy)
        Y = mixed_product(self.mixing, self._stored_product, np.ascontiguousarray(X, dtype=dtype))
        if reorder is not None:
            Y = Y[reorder.inverse_permutation]  # matrix indices back to row-major pixels
        return Y[:, 0] if x.ndim == 1 else Y

    def _stored_product(self, X: np.ndarray) -> np.ndarray:
        """S X of the stored tiles, X (n_cols, k) in matrix order."""
        if self.row_layout:
            return matmul_rows(self.attrs, self.get_tile_row, np.ascontiguousarray(X))
        return matmul_tiles(self.attrs, self.iter_tiles, np.ascontiguousarray(X))

    def __matmul__(self, x):
        """``A @ x``: :meth:`matmul` of row-major image vectors (scipy's convention)."""
        if sp.issparse(x):
            return NotImplemented
        return self.matmul(x)

    # --- metadata, checks, summary ---------------------------------------------------

    def update_metadata(self, **items) -> None:
        """Merge ``items`` into the free metadata dict, atomically on disk."""
        on_disk = StoreAttrs.from_dict(read_raw_attrs(self.path), self.path)
        attrs = on_disk.replace(metadata={**on_disk.metadata, **items})
        attrs.check_json(self.path)
        write_root_attrs(self.path, attrs)
        self.attrs = attrs
        self.metadata = dict(attrs.metadata)

    def check_chunks_exist(self) -> None:
        """Cheap existence check of every chunk file; CorruptStoreError naming the first missing."""
        checks.check_chunks_exist(self.path, self.attrs, self._index)

    def verify(self, progress: bool | None = False) -> dict:
        """Full check of every tile and every chunk file (``bigT verify``).

        Checks that the store holds no symbolic link, that every chunk file exists,
        that every checksum matches, the CSR structure of every tile (monotone indptr,
        sorted duplicate-free in-range indices, finite data) and that the per-tile nnz
        add up to the recorded nnz.

        Returns
        -------
        dict
            ``{"tiles": n_tiles_checked, "nnz": nnz}``.

        Raises
        ------
        CorruptStoreError
            Naming the store and the first bad tile or chunk.
        """
        return checks.verify(self.path, self.attrs, self._index, self.iter_tiles,
                             complete=self.complete, progress=progress)

    def info(self) -> dict:
        """Summary: shape, nnz, density, tile fill, diagonal statistics, bytes on disk."""
        return summary(self)

    def __repr__(self) -> str:
        return (f"<BlockCSR {self.shape[0]}x{self.shape[1]} {self.dtype.name} nnz={self.nnz} "
                f"tile_size={self.tile_size} tiles={self.n_tiles_stored} at {str(self.path)!r}>")


def _entries_kept(row: sp.csr_array, keep: np.ndarray) -> sp.csr_array:
    """The entries of CSR ``row`` where the bool mask ``keep`` (nnz,) is set, sorted."""
    indptr = np.zeros(row.shape[0] + 1, np.int64)
    if row.nnz:
        # a trailing 0 keeps reduceat's indices in range for empty last rows; it repeats
        # the next value for every empty row, so those are zeroed
        counts = np.add.reduceat(np.append(keep, False).astype(np.int64), row.indptr[:-1])
        counts[np.diff(row.indptr) == 0] = 0
        np.cumsum(counts, out=indptr[1:])
    out = sp.csr_array((row.data[keep], row.indices[keep], indptr), shape=row.shape)
    out.has_sorted_indices = True
    return out
