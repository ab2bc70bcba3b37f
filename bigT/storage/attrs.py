"""A store's attributes as one frozen, validated record (as zarr-python's
``ArrayV3Metadata`` is): :meth:`StoreAttrs.from_dict` parses and checks the
``attributes["bigT"]`` of a root ``zarr.json`` once, :meth:`StoreAttrs.to_dict` is the
only way back, and a change is a new record (:meth:`StoreAttrs.replace`).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from ..errors import BigTError, CorruptStoreError, IncompleteStoreError, StoreError
from . import _format as fmt
from .channel_mixing import ChannelMixing
from .objects import ObjectPath
from .pixel_order import PixelOrder


def _frozen(mapping) -> Mapping[str, Any]:
    return MappingProxyType(dict(mapping or {}))


def _plain(value):
    """JSON-ready copy of ``value`` (read-only mappings become dicts)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


@dataclass(frozen=True)
class StoreAttrs:
    """``attributes["bigT"]`` of a block-CSR store's root group (docs/FORMAT.md).

    Attributes
    ----------
    shape : (int, int)
    tile_size : int >= 1
    dtype : numpy.dtype, float32 or float64
    inner_format : str, "csr"
    nnz : int or None, None until the store is finalized
    complete : bool
    metadata : read-only mapping, free JSON
    pixel_order : PixelOrder or None
    version : int, the format version written
    mixing : ChannelMixing or None
        Colour only: the store represents (I (x) L) S (I (x) R), S its tiles
        (:mod:`bigT.storage.channel_mixing`); None is the identity.
    """

    shape: tuple[int, int]
    tile_size: int
    dtype: np.dtype
    inner_format: str = "csr"
    nnz: int | None = None
    complete: bool = False
    metadata: Mapping[str, Any] = field(default_factory=dict)
    pixel_order: PixelOrder | None = None
    version: int = fmt.FORMAT_VERSION
    mixing: ChannelMixing | None = None

    def __post_init__(self):
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        object.__setattr__(self, "tile_size", int(self.tile_size))
        object.__setattr__(self, "dtype", np.dtype(self.dtype))
        object.__setattr__(self, "metadata", _frozen(self.metadata))

    @property
    def channels(self) -> int:
        """Values per pixel: 1 (grey), or 3 (R, G, B; index 3 p + c) for a colour store."""
        return 1 if self.pixel_order is None else self.pixel_order.channels

    @property
    def grid(self) -> tuple[int, int]:
        """(n_tile_rows, n_tile_cols)."""
        ts = self.tile_size
        return -(-self.shape[0] // ts), -(-self.shape[1] // ts)

    def tile_row_range(self, i: int) -> tuple[int, int]:
        """(start, stop) matrix rows of tile row ``i``."""
        return i * self.tile_size, min((i + 1) * self.tile_size, self.shape[0])

    def replace(self, **changes) -> "StoreAttrs":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The JSON object stored under ``attributes["bigT"]``."""
        out = {
            "format": fmt.FORMAT_NAME, "version": self.version,
            "inner_format": self.inner_format, "shape": list(self.shape),
            "tile_size": self.tile_size, "dtype": self.dtype.name, "nnz": self.nnz,
            "complete": self.complete, "metadata": _plain(self.metadata),
        }
        if self.pixel_order is not None:
            out.update(self.pixel_order.to_attrs())
        if self.mixing is not None:
            out["mixing"] = self.mixing.to_attrs()
        return out

    def check_json(self, path) -> None:
        """BigTError naming ``path`` when the metadata is not JSON-serialisable."""
        try:
            json.dumps(self.to_dict(), allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise BigTError(f"metadata is not JSON-serialisable ({exc})", path) from None

    @classmethod
    def from_dict(cls, attrs: Mapping, path) -> "StoreAttrs":
        """Parse ``attributes["bigT"]`` of a (non-redirect) store.

        Raises
        ------
        CorruptStoreError
            A field is missing or out of range.
        StoreError
            An inner format this bigT does not read.
        """
        try:
            shape, tile_size = _checked_grid(attrs, path)
            dtype = np.dtype(fmt.check_text(attrs["dtype"], "dtype", path))
            nnz = attrs.get("nnz")
            if nnz is not None:
                nnz = fmt.check_count(nnz, "nnz", path, high=shape[0] * shape[1])
            complete = attrs.get("complete", False)
            if not isinstance(complete, bool):
                raise TypeError(f"complete must be true or false, got {complete!r:.60}")
            metadata = attrs.get("metadata") or {}
            if not isinstance(metadata, Mapping):
                raise TypeError("metadata is not an object")
            pixel_order = PixelOrder.from_attrs(dict(attrs))
            if pixel_order is None and attrs.get("channels", 1) != 1:
                raise ValueError("channels without image_shape (a colour store maps images)")
            version = fmt.check_count(attrs.get("version", fmt.FORMAT_VERSION), "version",
                                      path, low=1)
            mixing = attrs.get("mixing")
            if mixing is not None:
                if pixel_order is None or pixel_order.channels != 3:
                    raise ValueError("mixing without channels 3 (it mixes a pixel's R, G, B)")
                mixing = ChannelMixing.from_attrs(mixing, path)
        except CorruptStoreError:
            raise
        except (KeyError, TypeError, ValueError, BigTError) as exc:
            raise CorruptStoreError(f"bad bigT attributes ({exc!r:.200})", path) from None
        if dtype.name not in fmt.DTYPES:
            raise CorruptStoreError(f"unsupported dtype {dtype.name}", path)
        if pixel_order is not None and not pixel_order.n == shape[0] == shape[1]:
            raise CorruptStoreError(f"image_shape {list(pixel_order.image_shape)} has "
                                    f"{pixel_order.n} values, the matrix is {shape[0]}x{shape[1]}",
                                    path)
        if pixel_order is not None and tile_size % pixel_order.channels:
            raise CorruptStoreError(f"tile_size {tile_size} of a colour store is not a multiple "
                                    f"of its {pixel_order.channels} channels", path)
        inner = attrs.get("inner_format", "csr")
        if inner not in fmt.INNER_FORMATS:
            raise StoreError(f"inner_format {inner!r:.60} is not supported by this bigT "
                             f"(supported: {', '.join(fmt.INNER_FORMATS)})", path)
        return cls(shape, tile_size, dtype, inner, nnz, complete, metadata, pixel_order, version,
                   mixing)


def _checked_grid(attrs: Mapping, path) -> tuple[tuple[int, int], int]:
    """(shape, tile_size) of ``attrs``, integers within sense (``fmt.MAX_SIDE``, at
    most ``fmt.MAX_TILES_PER_SIDE`` tiles a side): every later allocation is sized
    from them. CorruptStoreError naming ``path`` otherwise."""
    shape = attrs["shape"]
    if not isinstance(shape, (list, tuple)) or len(shape) != 2:
        raise CorruptStoreError(f"shape must be [n_rows, n_cols], got {shape!r:.60}", path)
    shape = tuple(fmt.check_count(s, "shape", path, high=fmt.MAX_SIDE) for s in shape)
    tile_size = fmt.check_count(attrs["tile_size"], "tile_size", path, low=1,
                                high=fmt.MAX_SIDE)
    for side in shape:
        tiles = -(-side // tile_size)
        if tiles > fmt.MAX_TILES_PER_SIDE:
            raise CorruptStoreError(f"shape {list(shape)} with tile_size {tile_size} is a grid "
                                    f"of {tiles} tiles a side, more than bigT reads "
                                    f"({fmt.MAX_TILES_PER_SIDE})", path)
    return shape, tile_size


def read_raw_attrs(path: Path) -> dict:
    """``attributes["bigT"]`` of the group at ``path`` as stored (a store's, or a
    redirect's), after the checks every reader makes.

    Raises
    ------
    StoreError
        No such directory, no zarr v3 group, no bigT attributes, a newer version.
    """
    if isinstance(path, ObjectPath):  # one request: a missing zarr.json is no store
        if not (path / "zarr.json").is_file():
            raise StoreError("no such store", path)
    elif not path.exists():
        raise StoreError("no such store", path)
    elif not path.is_dir():
        raise StoreError("not a bigT store (not a directory)", path)
    meta = fmt.read_json(path / "zarr.json")
    if meta.get("zarr_format") != 3 or meta.get("node_type") != "group":
        raise StoreError("not a bigT store (zarr.json is not a zarr v3 group)", path)
    group_attrs = meta.get("attributes") or {}
    if not isinstance(group_attrs, dict):
        raise CorruptStoreError("attributes of zarr.json is not an object", path / "zarr.json")
    attrs = group_attrs.get(fmt.ATTRS_KEY)
    if attrs is None and fmt.INVERSE_ATTR in group_attrs:
        raise IncompleteStoreError("an inverse whose first term is not finished yet: wait "
                                   "for bigT invert, or rerun it if it was stopped", path)
    if not isinstance(attrs, dict) or attrs.get("format") != fmt.FORMAT_NAME:
        raise StoreError(f"not a bigT store (zarr group without attrs['{fmt.ATTRS_KEY}'] "
                         f"of format {fmt.FORMAT_NAME!r})", path)
    version = attrs.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version > fmt.FORMAT_VERSION:
        raise StoreError(f"unsupported {fmt.FORMAT_NAME} version {version!r:.60} "
                         f"(this bigT reads up to {fmt.FORMAT_VERSION})", path)
    return attrs
