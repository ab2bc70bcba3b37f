"""On-disk layout of a bigT block-CSR store (docs/FORMAT.md is the reference).

Only this module and the storage modules that read and write stores know key names.
"""

from __future__ import annotations

import errno
import json
import os
import stat
from pathlib import Path, PurePosixPath
from typing import Callable, Iterator

import numpy as np

from .. import config
from ..atomic import atomic_write_json
from ..errors import CorruptStoreError, StoreError
from .objects import ObjectPath, RequestError

FORMAT_NAME = "bigT-block-csr"
#: The layout this bigT writes: 2, one group of three arrays per tile row. Version 1
#: (a group of three arrays per tile) is still read; writers refuse to add to it.
FORMAT_VERSION = 2
#: The first version whose tile rows are stored whole (:func:`row_path`'s arrays).
ROW_LAYOUT_VERSION = 2
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
#: The arrays of a tile row (version 2) and of a tile (version 1), in this order.
TILE_ARRAYS = ("indptr", "indices", "data")

#: Fill values that no valid array holds, so a chunk that zarr silently reads as
#: "missing = fill value" fails the cheap per-tile checks.
FILL_INT = -1
FILL_FLOAT = float("nan")

#: Column indices are int32 (version 1: local to the tile; version 2: global, so a
#: matrix of more than 2^31 - 1 columns stores them as int64, :func:`indices_dtype`);
#: indptr is int64 (a tile row of a dense term can pass 2^31 entries, and indptr is
#: tiny).
INDICES_DTYPE = np.int32
INDPTR_DTYPE = np.int64


def indices_dtype(n_cols: int) -> np.dtype:
    """dtype of a version-2 tile row's global column indices for ``n_cols`` columns."""
    return np.dtype(np.int32 if n_cols <= np.iinfo(np.int32).max else np.int64)


def row_path(i: int) -> str:
    return f"{ROWS_GROUP}/{i}"


def tile_path(i: int, j: int) -> str:
    """Version 1 only: the group of tile (i, j)."""
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
    level = config.ZSTD_LEVEL if level is None else int(level)
    values = np.ascontiguousarray(values)
    dtype = values.dtype.newbyteorder("<") if values.dtype.byteorder == ">" else values.dtype
    n = int(values.shape[0])
    chunk = max(1, min(n, config.CHUNK_ELEMENTS))
    meta = json.dumps(_array_json(n, chunk, np.dtype(dtype), fill_value, level), indent=2)
    adir = root / name
    if isinstance(adir, ObjectPath):
        # each object whole, chunks first: an array's zarr.json announces chunks there
        for c, frame in enumerate(_encoded_chunks(values, dtype, chunk, fill_value, level)):
            (adir / "c" / str(c)).write_bytes(frame)
        (adir / "zarr.json").write_bytes(meta.encode())
        return
    adir = Path(adir)
    (adir / "c" if n else adir).mkdir(parents=True, exist_ok=True)
    with open(adir / "zarr.json", "w", encoding="utf-8") as f:
        f.write(meta)
    for c, frame in enumerate(_encoded_chunks(values, dtype, chunk, fill_value, level)):
        with open(adir / "c" / str(c), "wb") as f:
            f.write(frame)


def _encoded_chunks(values: np.ndarray, dtype: np.dtype, chunk: int, fill_value,
                    level: int) -> Iterator[bytes]:
    """Each chunk file's bytes: the zstd frame of its little-endian values (the edge
    chunk padded with ``fill_value``) followed by the frame's crc32c."""
    import google_crc32c
    from numcodecs import Zstd  # numcodecs: ~0.15 s, kept off `import bigT.storage`

    codec = Zstd(level=level, checksum=False)
    n = int(values.shape[0])
    for start in range(0, n, chunk):
        part = values[start:start + chunk].astype(dtype.newbyteorder("<"), copy=False)
        if part.shape[0] < chunk:
            part = np.concatenate([part, np.full(chunk - part.shape[0], fill_value, dtype)])
        frame = codec.encode(part.tobytes())
        yield frame + np.uint32(google_crc32c.value(frame)).astype("<u4").tobytes()


# --- what a store declares, bounded by sense -------------------------------------

#: Largest zarr.json bigT reads. The largest it writes is an inverse root's record,
#: ~0.5 KB a term of history, so 8 MiB holds ~16,000 terms (no run makes 100), while
#: a file that never ends (a FIFO, a link to /dev/zero) is refused after 8 MiB read.
METADATA_MAX_BYTES = 8 << 20
#: Largest matrix side a store may declare: 2^32 pixels is a 65536^2 image, beyond any
#: camera; its diagonal alone is 32 GiB. A larger shape is damage, not a matrix.
MAX_SIDE = 1 << 32
#: Most tile rows or tile columns a grid may have: the tile index pointer (8 bytes a
#: tile row) and an incomplete store's row scan stay under 128 MiB. Tile size 256
#: reaches it at 2^32 pixels only.
MAX_TILES_PER_SIDE = 1 << 24


def check_count(value, name: str, path, *, low: int = 0, high: int | None = None) -> int:
    """``value`` as an int when it is a JSON integer in ``[low, high]``; CorruptStoreError
    naming ``path`` otherwise (a float such as 3.5 or 3.0, a bool, a string)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise CorruptStoreError(f"{name} must be an integer, got {value!r:.60}", path)
    if value < low or (high is not None and value > high):
        bound = f"[{low}, {high}]" if high is not None else f">= {low}"
        raise CorruptStoreError(f"{name} = {value} is out of range {bound}", path)
    return value


def check_text(value, name: str, path) -> str:
    """``value`` when it is a JSON string without NUL; CorruptStoreError otherwise."""
    if not isinstance(value, str) or "\x00" in value:
        raise CorruptStoreError(f"{name} must be a string without NUL, got {value!r:.60}", path)
    return value


# --- a store is a closed world: no symbolic link below its root is followed ----------

class LinkInStoreError(CorruptStoreError):
    """A symbolic link below a store's root: bigT neither reads nor deletes through it."""


def _open_component(name: str, dir_fd: int, directory: bool, root: Path, rel: str) -> int:
    # O_NONBLOCK: a FIFO put in a store's place opens at once (and is refused as not a
    # regular file) instead of waiting for a writer that never comes
    flags = os.O_RDONLY | os.O_NOFOLLOW | (os.O_DIRECTORY if directory else os.O_NONBLOCK)
    try:
        return os.open(name, flags, dir_fd=dir_fd)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENOTDIR, errno.EMLINK):
            try:
                is_link = stat.S_ISLNK(os.lstat(name, dir_fd=dir_fd).st_mode)
            except OSError:
                is_link = False
            if is_link:
                raise LinkInStoreError(f"{rel} is a symbolic link: a store holds none, and "
                                       "bigT does not follow one (delete it, or copy what "
                                       "it points at in its place)", root) from None
        raise


def open_inside(root: Path, rel: str, directory: bool = True) -> int:
    """A descriptor of ``root/rel``, opened component by component with O_NOFOLLOW:
    a symbolic link below ``root`` (``root`` itself may be one the user named) raises
    :class:`LinkInStoreError` naming it. The caller closes the descriptor.

    Raises
    ------
    LinkInStoreError
    OSError
        FileNotFoundError and the like, as ``open`` raises them.
    """
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY)
    parts = PurePosixPath(rel).parts if rel else ()
    try:
        for n, part in enumerate(parts):
            last = n == len(parts) - 1
            child = _open_component(part, fd, directory or not last, root,
                                    "/".join(parts[:n + 1]))
            os.close(fd)
            fd = child
    except BaseException:
        os.close(fd)
        raise
    return fd


def check_no_links(root: Path, rel: str) -> None:
    """LinkInStoreError when a component of ``rel`` below ``root`` is a symbolic link;
    nothing when the path is not there (nor in object storage, which has no links)."""
    if isinstance(root, ObjectPath):
        return
    try:
        os.close(open_inside(root, rel))
    except (FileNotFoundError, NotADirectoryError):
        pass


def _read_at(name: str, dir_fd: int, max_bytes: int, root: Path, rel: str) -> bytes:
    """At most ``max_bytes`` of file ``name`` in ``dir_fd`` (not followed if a link);
    ValueError past that."""
    fd = _open_component(name, dir_fd, False, root, rel)
    with os.fdopen(fd, "rb") as f:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):  # a FIFO or a device: no end, or no size
            raise ValueError(f"{rel} is not a regular file")
        if info.st_size > max_bytes:
            raise ValueError(f"{rel} is larger than {max_bytes} bytes")
        raw = f.read(max_bytes + 1)  # a file still growing stops here
    if len(raw) > max_bytes:
        raise ValueError(f"{rel} is larger than {max_bytes} bytes")
    return raw


def parse_json(raw: bytes, what: str, path) -> dict:
    """The JSON object ``raw``; CorruptStoreError naming ``path`` for anything else
    (not JSON, not an object, nested deeper than the parser's recursion)."""
    try:
        meta = json.loads(raw)
    except RecursionError:
        raise CorruptStoreError(f"unreadable {what} (JSON nested too deeply)", path) from None
    except ValueError as exc:
        raise CorruptStoreError(f"unreadable {what} ({exc})", path) from None
    if not isinstance(meta, dict):
        raise CorruptStoreError(f"unreadable {what} (not a JSON object)", path)
    return meta


# --- the arrays' own files ----------------------------------------------------------

def _frame_content_size(frame: bytes) -> int | None:
    """The decompressed size a zstd frame's header declares, None when it declares
    none (RFC 8878, 3.1.1.1). ValueError for a frame shorter than its header."""
    if len(frame) < 5 or frame[:4] != b"\x28\xb5\x2f\xfd":
        raise ValueError("not a zstd frame")
    descriptor = frame[4]
    fcs_flag, single_segment, dict_flag = descriptor >> 6, (descriptor >> 5) & 1, descriptor & 3
    size_bytes = (1 if single_segment else 0, 2, 4, 8)[fcs_flag]
    if not size_bytes:
        return None
    start = 5 + (0 if single_segment else 1) + (0, 1, 2, 4)[dict_flag]
    if len(frame) < start + size_bytes:
        raise ValueError("truncated zstd frame header")
    value = int.from_bytes(frame[start:start + size_bytes], "little")
    return value + 256 if size_bytes == 2 else value


def _decode_chunk(frame: bytes, out: np.ndarray, name: str) -> None:
    """Decompress ``frame`` into ``out`` (the chunk's declared size) and nowhere else:
    a frame that declares or holds more, or less, raises ValueError. Memory is the
    chunk's declared size, whatever the frame claims."""
    from numcodecs.zstd import decompress  # numcodecs: ~0.15 s, kept off `import bigT.storage`

    declared = _frame_content_size(frame)
    if declared is not None and declared != out.nbytes:
        raise ValueError(f"chunk file {name} decompresses to {declared} bytes, its array "
                         f"declares {out.nbytes}")
    try:
        # a frame without a size is decoded into ``out`` and fails when it overflows it
        decompress(frame, out.view(np.uint8))
    except RuntimeError as exc:
        raise ValueError(f"chunk file {name}: {exc}") from None


def _array_meta(meta: dict, length: int, path) -> tuple[int, np.dtype, object, bool]:
    """(chunk, dtype, fill, direct) of an array's zarr.json, checked against the
    ``length`` the store's shape implies before anything is allocated; ``direct`` is
    False for another layout than :func:`write_array_files`'s."""
    shape = meta.get("shape")
    if not isinstance(shape, list) or len(shape) != 1:
        raise CorruptStoreError(f"array shape {shape!r:.60} is not 1-D", path)
    check_count(shape[0], "array length", path)
    if shape[0] != length:
        raise CorruptStoreError(f"array declares {shape[0]} entries, the store's index "
                                f"says {length}", path)
    try:
        (chunk,) = meta["chunk_grid"]["configuration"]["chunk_shape"]
        codecs_ = meta["codecs"]
        direct = (meta["chunk_grid"]["name"] == "regular"
                  and meta["chunk_key_encoding"] == {"name": "default",
                                                     "configuration": {"separator": "/"}}
                  and [c["name"] for c in codecs_] == ["bytes", "zstd", "crc32c"]
                  and codecs_[0]["configuration"]["endian"] == "little"
                  and not meta.get("storage_transformers"))
        dtype = np.dtype(check_text(meta["data_type"], "data_type", path)).newbyteorder("<")
        fill = meta["fill_value"]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise CorruptStoreError(f"bad array metadata ({exc!r:.80})", path) from None
    # a chunk larger than the array would let one chunk file claim more than it holds
    check_count(chunk, "chunk length", path, low=1, high=max(length, 1))
    if dtype.kind not in "if":
        raise CorruptStoreError(f"array of data_type {dtype.name}, not a number", path)
    fill = float("nan") if fill == "NaN" else fill
    if isinstance(fill, bool) or not isinstance(fill, (int, float)):
        raise CorruptStoreError(f"fill_value {fill!r:.60} is not a number", path)
    return chunk, dtype, fill, direct


def read_array_files(adir: Path, length: int | None = None, *,
                     root: Path | None = None) -> np.ndarray | None:
    """The whole 1-D array in directory ``adir``, read from its files directly; None
    when its zarr.json is not the layout :func:`write_array_files` produces (the
    caller then reads it through zarr).

    Memory is bounded by ``length``, which a reader derives from the store's validated
    shape and index: the declared length must equal it (None takes the declared one,
    for tools that read a single array), each chunk is decompressed into its declared
    size and fails past it. No symbolic link between ``root`` (the store; default
    ``adir``'s parent) and the files is followed (:class:`LinkInStoreError`).

    Same semantics as zarr's read otherwise: a missing chunk file reads as the fill
    value (the tile checks catch that), a damaged one raises ``ValueError`` naming the
    checksum. Why: zarr's per-array open and read cost ~2 ms, a tile row reads ~60
    arrays.

    Raises
    ------
    CorruptStoreError
        Metadata that is not JSON, a declared length other than ``length``, a chunk
        longer than the array, a link.
    ValueError
        A chunk's checksum, or a frame that does not decompress to its declared size.
    """
    if isinstance(adir, ObjectPath):
        return _read_array_objects(adir, length)
    adir = Path(adir)
    root = adir.parent if root is None else Path(root)
    rel = adir.relative_to(root).as_posix()
    dfd = open_inside(root, rel)
    try:
        raw = _read_at("zarr.json", dfd, METADATA_MAX_BYTES, root, f"{rel}/zarr.json")
        length, chunk, dtype, fill, direct = _declared(raw, length, adir / "zarr.json")
        if not direct:
            check_tree_has_no_links(root, rel)  # zarr reads it by path
            return None
        if not length:
            return np.empty(0, dtype.newbyteorder("="))
        try:
            cfd = _open_component("c", dfd, True, root, f"{rel}/c")
        except FileNotFoundError:
            return np.full(length, fill, dtype.newbyteorder("="))
        try:
            return _decoded_chunks(
                lambda c, most: _read_at(str(c), cfd, most, root, f"{rel}/c/{c}"),
                length, chunk, dtype, fill, rel)
        finally:
            os.close(cfd)
    finally:
        os.close(dfd)


def _read_array_objects(adir: ObjectPath, length: int | None) -> np.ndarray | None:
    """:func:`read_array_files` of an array in object storage: the same checks, each
    file an object (there are no links to refuse)."""
    try:
        raw = (adir / "zarr.json").read_bytes(METADATA_MAX_BYTES)
    except ValueError as exc:
        raise CorruptStoreError(str(exc), adir / "zarr.json") from None
    length, chunk, dtype, fill, direct = _declared(raw, length, adir / "zarr.json")
    if not direct:
        return None
    if not length:
        return np.empty(0, dtype.newbyteorder("="))
    return _decoded_chunks(lambda c, most: (adir / "c" / str(c)).read_bytes(most),
                           length, chunk, dtype, fill, str(adir))


def _declared(raw: bytes, length: int | None, where) -> tuple:
    """(length, chunk, dtype, fill, direct) of an array's zarr.json ``raw``, its length
    the caller's when known (else the declared one, bounded by :data:`MAX_SIDE`)."""
    meta = parse_json(raw, "zarr.json", where)
    if length is None:
        length = check_count((meta.get("shape") or [None])[0], "array length", where,
                             high=MAX_SIDE)
    return (length, *_array_meta(meta, length, where))


def _decoded_chunks(read_chunk: Callable[[int, int], bytes], length: int, chunk: int,
                    dtype: np.dtype, fill, rel: str) -> np.ndarray:
    """The array of ``length`` values whose chunk ``c``'s file ``read_chunk(c,
    max_bytes)`` returns (FileNotFoundError: the chunk reads as ``fill``), each
    checked against its crc32c and decoded into its declared size."""
    import google_crc32c

    out = np.empty(length, dtype)
    chunk_buf = np.empty(chunk if length % chunk else 0, dtype)
    max_frame = chunk * dtype.itemsize * 2 + 1024 + 4  # zstd's worst case is ~raw size
    for c, start in enumerate(range(0, length, chunk)):
        stop = min(start + chunk, length)
        name = f"{rel}/c/{c}"
        try:
            raw = read_chunk(c, max_frame)
        except FileNotFoundError:
            out[start:stop] = fill
            continue
        frame, stored = raw[:-4], raw[-4:]
        if len(raw) < 4 or np.frombuffer(stored, "<u4")[0] != google_crc32c.value(frame):
            raise ValueError(f"crc32c checksum mismatch in chunk file {name}")
        if stop - start == chunk:  # a whole chunk: decoded in place, no copy
            if _frame_content_size(frame) is None:
                out[start:stop] = fill  # what a short frame leaves, the checks catch
            _decode_chunk(frame, out[start:stop], name)
            continue
        # the edge chunk through a buffer: its frame holds the padding too
        _decode_chunk(frame, chunk_buf, name)
        out[start:stop] = chunk_buf[:stop - start]
    return out.astype(dtype.newbyteorder("="), copy=False)


def check_tree_has_no_links(root: Path, rel: str) -> None:
    """LinkInStoreError for a symbolic link anywhere below ``root/rel`` (an array that
    zarr reads by path; the whole store for ``verify``); object storage has none."""
    if isinstance(root, ObjectPath):
        return
    for dirpath, dirnames, filenames in os.walk(root / rel if rel else root):
        for name in dirnames + filenames:
            if os.path.islink(os.path.join(dirpath, name)):
                link = os.path.relpath(os.path.join(dirpath, name), root)
                raise LinkInStoreError(f"{link} is a symbolic link: a store holds none, and "
                                       "bigT does not follow one", root)


def read_json(path: Path, root: Path | None = None) -> dict:
    """Parse a zarr.json (at most :data:`METADATA_MAX_BYTES`); StoreError naming the
    file when it is absent, CorruptStoreError when it is not a JSON object. With
    ``root``, no symbolic link between ``root`` and the file is followed."""
    if isinstance(path, ObjectPath):
        return _read_json_object(path)
    root = path.parent if root is None else root
    rel = path.relative_to(root).as_posix()
    parent, _, name = rel.rpartition("/")
    try:
        dfd = open_inside(root, parent)
        try:
            raw = _read_at(name, dfd, METADATA_MAX_BYTES, root, rel)
        finally:
            os.close(dfd)
    except FileNotFoundError:
        raise StoreError("not a zarr v3 group (no zarr.json)", path.parent) from None
    except NotADirectoryError:
        raise StoreError("not a bigT store (not a directory)", path.parent) from None
    except (OSError, ValueError) as exc:
        if isinstance(exc, StoreError):
            raise
        raise StoreError(f"unreadable zarr.json ({exc})", path.parent) from None
    return parse_json(raw, "zarr.json", path)


def _read_json_object(path: ObjectPath) -> dict:
    """:func:`read_json` of an object."""
    try:
        raw = path.read_bytes(METADATA_MAX_BYTES)
    except FileNotFoundError:
        raise StoreError("not a zarr v3 group (no zarr.json)", path.parent) from None
    except ValueError as exc:
        raise StoreError(f"unreadable zarr.json ({exc})", path.parent) from None
    except OSError as exc:
        raise StoreError(f"unreadable zarr.json ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0][:160]})", path.parent) from None
    return parse_json(raw, "zarr.json", path)


def write_json(path, obj: dict, durable: bool = True) -> None:
    """Replace the JSON file ``path`` whole: a reader sees the old one or the new one
    (:func:`bigT.atomic.atomic_write_json` for a file; one PUT for an object, which
    an object store applies whole)."""
    if isinstance(path, ObjectPath):
        path.write_bytes(json.dumps(obj, indent=2, allow_nan=False).encode())
    else:
        atomic_write_json(path, obj, durable)


def disk_bytes(path) -> int:
    """Bytes of all files (objects) under ``path``."""
    if isinstance(path, ObjectPath):
        return sum(size for _, size in path.walk_objects())
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                # lstat: a link counts as itself, what it points at is not the store's
                total += os.lstat(os.path.join(root, name)).st_size
            except OSError:
                pass
    return total


def group_json(attributes: dict) -> dict:
    """The zarr.json of a zarr v3 group holding ``attributes``."""
    return {"zarr_format": 3, "node_type": "group", "attributes": attributes}


def redirect_target(target, root: Path) -> Path:
    """The directory a redirect ``target`` names inside the store at ``root``;
    StoreError for anything but a relative path that stays inside it, through no
    symbolic link."""
    if not isinstance(target, str) or "\x00" in target:
        raise CorruptStoreError(f"invalid redirect {target!r:.60}: must be a string "
                                "(a relative path inside the store)", root / "zarr.json")
    p = PurePosixPath(target)
    if not target or p.is_absolute() or ".." in p.parts:
        raise StoreError(f"invalid redirect {target!r}: must be a relative path inside the store", root)
    check_no_links(root, p.as_posix())
    return root.joinpath(*p.parts)


def row_marker(path: Path, i: int) -> dict | None:
    """The completion record of tile row ``i`` (``{"complete": True, "tile_columns":
    [...], "tile_nnz": [...]}``), or None when the row is not complete (its
    zarr.json missing, unreadable, larger than :data:`METADATA_MAX_BYTES`, or a link).
    The record's values are the caller's to check."""
    rel = row_path(i)
    if isinstance(path, ObjectPath):
        try:
            meta = parse_json((path / rel / "zarr.json").read_bytes(METADATA_MAX_BYTES),
                              "zarr.json", path)
        except RequestError:  # no answer is not "no row": a complete row stays
            raise
        except (OSError, ValueError):
            return None
        return _complete_row(meta)
    try:
        dfd = open_inside(path, rel)
        try:
            raw = _read_at("zarr.json", dfd, METADATA_MAX_BYTES, path, f"{rel}/zarr.json")
        finally:
            os.close(dfd)
        meta = parse_json(raw, "zarr.json", path)
    except (OSError, ValueError):  # StoreError is a ValueError
        return None
    return _complete_row(meta)


def _complete_row(meta: dict) -> dict | None:
    rec = meta.get("attributes")
    rec = rec.get(ROW_ATTRS_KEY) if isinstance(rec, dict) else None
    return rec if isinstance(rec, dict) and rec.get("complete") is True else None


def stored_tile_rows(path: Path, n_tile_rows: int) -> list[int]:
    """The tile rows below ``n_tile_rows`` whose directory exists under ``rows/``, from
    one listing: a loop over them is bounded by what is on disk, not by the grid the
    store declares."""
    check_no_links(path, ROWS_GROUP)
    try:
        names = (path / ROWS_GROUP).child_names() if isinstance(path, ObjectPath) else (
            os.listdir(path / ROWS_GROUP))
    except (FileNotFoundError, NotADirectoryError):
        return []
    rows = (int(name) for name in names if name.isdigit() and name.isascii()
            and name == str(int(name)))
    return sorted(i for i in rows if i < n_tile_rows)
