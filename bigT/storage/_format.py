"""On-disk layout of a bigT block-CSR store (docs/FORMAT.md is the reference).

Only this module and its two users (``block_csr.py``, ``writer.py``) know key names.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec

from .. import config
from ..errors import StoreError

FORMAT_NAME = "bigT-block-csr"
FORMAT_VERSION = 1
#: attrs key of the root group that holds everything bigT records.
ATTRS_KEY = "bigT"
#: attrs key of a tile-row group; its ``complete`` flag is written last.
ROW_ATTRS_KEY = "bigT_row"
INNER_FORMATS = ("csr",)
DTYPES = ("float32", "float64")

ROWS_GROUP = "rows"
INDEX_ARRAYS = ("tile_indptr", "tile_indices", "tile_nnz")
TILE_ARRAYS = ("indptr", "indices", "data")

#: Fill values that no valid array holds, so a chunk that zarr silently reads as
#: "missing = fill value" fails the cheap per-tile checks.
FILL_INT = -1
FILL_FLOAT = float("nan")

#: Local column indices of a tile are int32; a tile's indptr is int64 (a tile of
#: 46341^2 entries could overflow int32, and indptr is tiny).
INDICES_DTYPE = np.int32
INDPTR_DTYPE = np.int64


def row_path(i: int) -> str:
    return f"{ROWS_GROUP}/{i}"


def tile_path(i: int, j: int) -> str:
    return f"{ROWS_GROUP}/{i}/{j}"


def codecs(level: int | None = None) -> list:
    """zstd then crc32c: the checksum covers the compressed bytes as stored."""
    return [ZstdCodec(level=config.ZSTD_LEVEL if level is None else level), Crc32cCodec()]


def write_array(store, name: str, values: np.ndarray, fill_value, level: int | None = None):
    """Create the 1-D zarr array ``name`` holding ``values`` (written whole).

    ``write_empty_chunks=True`` so every chunk exists on disk: a chunk file that is
    later missing is then damage, never a legitimately "empty" chunk.
    """
    n = int(values.shape[0])
    chunk = max(1, min(n, config.CHUNK_ELEMENTS))
    arr = zarr.create_array(
        store, name=name, shape=(n,), dtype=values.dtype, chunks=(chunk,),
        fill_value=fill_value, compressors=codecs(level), filters=None,
        config={"write_empty_chunks": True}, overwrite=True,
    )
    if n:
        arr[...] = values
    return arr


def read_json(path: Path) -> dict:
    """Parse a zarr.json; StoreError naming the file when it is absent or not JSON."""
    try:
        with open(path, "rb") as f:
            return json.load(f)
    except FileNotFoundError:
        raise StoreError("not a zarr v3 group (no zarr.json)", path.parent) from None
    except (OSError, ValueError) as exc:
        raise StoreError(f"unreadable zarr.json ({exc})", path.parent) from None


def disk_bytes(path: str | os.PathLike) -> int:
    """Bytes of all files under ``path``."""
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                total += os.path.getsize(os.path.join(root, name))
            except OSError:
                pass
    return total
