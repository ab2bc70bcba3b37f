"""On-disk layout of a bigT block-CSR store (docs/FORMAT.md is the reference).

Only this module and the storage modules that read and write stores know key names.
"""

from __future__ import annotations

import json
import os
from pathlib import Path, PurePosixPath

import numpy as np

from .. import config
from ..errors import StoreError

FORMAT_NAME = "bigT-block-csr"
FORMAT_VERSION = 1
#: attrs key of the root group that holds everything bigT records.
ATTRS_KEY = "bigT"
#: Attribute of an inverse store's root holding the engine's record.
INVERSE_ATTR = "bigT_inverse"
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


def _array_json(n: int, chunk: int, dtype: np.dtype, fill_value, level: int) -> dict:
    """The zarr.json zarr-python 3 writes for :func:`write_array_files`'s arrays."""
    if isinstance(fill_value, float) and np.isnan(fill_value):
        fill = "NaN"
    else:
        fill = float(fill_value) if dtype.kind == "f" else int(fill_value)
    return {
        "shape": [n],
        "data_type": dtype.name,
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [chunk]}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": fill,
        "codecs": [
            {"name": "bytes", "configuration": {"endian": "little"}},
            {"name": "zstd", "configuration": {"level": level, "checksum": False}},
            {"name": "crc32c"},
        ],
        "attributes": {},
        "zarr_format": 3,
        "node_type": "array",
        "storage_transformers": [],
    }


def write_array_files(root: Path, name: str, values: np.ndarray, fill_value,
                      level: int | None = None) -> None:
    """Create the 1-D zarr v3 array ``name`` under ``root`` holding ``values``, written
    whole, as files.

    Codecs bytes (little endian), zstd (``config.ZSTD_LEVEL``), crc32c; chunks of
    ``min(len, config.CHUNK_ELEMENTS)``; every chunk written (zarr's
    ``write_empty_chunks=True``), so a chunk file that is later missing is damage.

    Why: zarr-python spends ~3 ms per array in its event-loop round trips and
    metadata machinery, more than the encoding of a typical tile; a tile row of a
    dense term has ~20 tiles of 3 arrays. The files are the ones zarr writes (the
    zarr.json, and per chunk the zstd frame of the little-endian bytes, edge chunk
    padded with the fill value, followed by its crc32c): ``tests/storage`` compares
    them with zarr's, byte for byte, and reads them back through zarr.
    """
    import google_crc32c
    from numcodecs import Zstd  # numcodecs: ~0.15 s, kept off `import bigT.storage`

    level = config.ZSTD_LEVEL if level is None else int(level)
    values = np.ascontiguousarray(values)
    dtype = values.dtype.newbyteorder("<") if values.dtype.byteorder == ">" else values.dtype
    n = int(values.shape[0])
    chunk = max(1, min(n, config.CHUNK_ELEMENTS))
    adir = Path(root) / name
    (adir / "c" if n else adir).mkdir(parents=True, exist_ok=True)
    with open(adir / "zarr.json", "w", encoding="utf-8") as f:
        json.dump(_array_json(n, chunk, np.dtype(dtype), fill_value, level), f, indent=2)
    codec = Zstd(level=level, checksum=False)
    for c, start in enumerate(range(0, n, chunk)):
        part = values[start:start + chunk].astype(dtype.newbyteorder("<"), copy=False)
        if part.shape[0] < chunk:
            part = np.concatenate([part, np.full(chunk - part.shape[0], fill_value, dtype)])
        frame = codec.encode(part.tobytes())
        crc = np.uint32(google_crc32c.value(frame)).astype("<u4").tobytes()
        with open(adir / "c" / str(c), "wb") as f:
            f.write(frame)
            f.write(crc)


def read_array_files(adir: Path) -> np.ndarray | None:
    """The whole 1-D array in directory ``adir``, read from its files directly; None
    when its zarr.json is not the layout :func:`write_array_files` produces (the caller
    then reads it through zarr).

    Same semantics as zarr's read: a missing chunk file reads as the fill value (the
    tile checks catch that), a damaged one raises ``ValueError`` naming the checksum.
    Why: zarr's per-array open and read cost ~2 ms, a tile row reads ~60 arrays.
    """
    import google_crc32c
    from numcodecs import Zstd  # numcodecs: ~0.15 s, kept off `import bigT.storage`

    with open(adir / "zarr.json", "rb") as f:
        meta = json.load(f)
    try:
        (n,) = meta["shape"]
        (chunk,) = meta["chunk_grid"]["configuration"]["chunk_shape"]
        codecs_ = meta["codecs"]
        ok = (meta["chunk_grid"]["name"] == "regular"
              and meta["chunk_key_encoding"] == {"name": "default",
                                                 "configuration": {"separator": "/"}}
              and [c["name"] for c in codecs_] == ["bytes", "zstd", "crc32c"]
              and codecs_[0]["configuration"]["endian"] == "little"
              and not meta.get("storage_transformers"))
        dtype = np.dtype(meta["data_type"]).newbyteorder("<")
        fill = meta["fill_value"]
    except (KeyError, TypeError, ValueError):
        return None
    if not ok:
        return None
    fill = float("nan") if fill == "NaN" else fill
    out = np.empty(n, dtype)
    codec = Zstd()
    for c, start in enumerate(range(0, n, chunk)):
        stop = min(start + chunk, n)
        try:
            with open(adir / "c" / str(c), "rb") as f:
                raw = f.read()
        except FileNotFoundError:
            out[start:stop] = fill
            continue
        frame, stored = raw[:-4], raw[-4:]
        if len(raw) < 4 or np.frombuffer(stored, "<u4")[0] != google_crc32c.value(frame):
            raise ValueError(f"crc32c checksum mismatch in chunk file {adir.name}/c/{c}")
        # not decoded in place: a frame shorter than the chunk must fail here, not
        # leave the rest of ``out`` unset
        out[start:stop] = np.frombuffer(codec.decode(frame), dtype)[:stop - start]
    return out.astype(dtype.newbyteorder("="), copy=False)


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


def group_json(attributes: dict) -> dict:
    """The zarr.json of a zarr v3 group holding ``attributes``."""
    return {"zarr_format": 3, "node_type": "group", "attributes": attributes}


def redirect_target(target: str, root: Path) -> Path:
    """The directory a redirect ``target`` names inside the store at ``root``;
    StoreError for anything but a relative path that stays inside it."""
    p = PurePosixPath(target)
    if not target or p.is_absolute() or ".." in p.parts:
        raise StoreError(f"invalid redirect {target!r}: must be a relative path inside the store", root)
    return root.joinpath(*p.parts)


def row_marker(path: Path, i: int) -> dict | None:
    """The completion record of tile row ``i`` (``{"complete": True, "tile_columns":
    [...], "tile_nnz": [...]}``), or None when the row is not complete."""
    try:
        with open(path / row_path(i) / "zarr.json", "rb") as f:
            meta = json.load(f)
    except (OSError, ValueError):
        return None
    rec = (meta.get("attributes") or {}).get(ROW_ATTRS_KEY) or {}
    return rec if rec.get("complete") is True else None
