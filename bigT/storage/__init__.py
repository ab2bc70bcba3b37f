"""bigT.storage: the zarr v3 block-CSR store (docs/FORMAT.md describes the layout).

Public API: :func:`open`, :func:`as_store` (a store or its path), :func:`from_scipy`, :class:`BlockCSR`,
:class:`BlockCSRWriter`, :func:`set_redirect` (for versioned stores) and
:class:`PixelOrder`; for writers in other processes: :func:`create_store`,
:func:`write_tile_row` (idempotent), :func:`finalize_store` (from the row markers);
the versioned inverse store: :class:`InverseStore`; building a store or a file tree
aside and moving it into place: :func:`temporary_sibling`, :func:`check_replaceable`,
:func:`move_into_place`, :func:`write_group` (:mod:`bigT.storage.replace`); a
directory's size on disk: :func:`disk_bytes`; a store in object storage (a URL):
:func:`as_location`, :class:`ObjectPath`, :func:`is_url`.
"""

from .attrs import StoreAttrs
from ._format import row_marker
from .block_csr import BlockCSR, as_store, open  # noqa: A004
from .inverse_store import InverseRecord, InverseStore, TermEntry
from .objects import ObjectPath, as_location, is_url, store_identity, upload_tree
from .pixel_order import PixelOrder
from .tiles import open_zarr
from ._format import disk_bytes
from .replace import (check_replaceable, move_into_place, set_redirect, temporary_sibling,
                      write_group)
from .writer import (
    BlockCSRWriter,
    KeptTiles,
    clean_partial_rows,
    completed_rows,
    create_store,
    finalize_store,
    from_scipy,
    read_store_attrs,
    write_tile_row,
)

__all__ = [
    "BlockCSR", "BlockCSRWriter", "InverseRecord", "InverseStore", "KeptTiles", "ObjectPath",
    "PixelOrder", "as_location", "is_url", "open_zarr", "store_identity", "upload_tree",
    "StoreAttrs", "TermEntry", "as_store", "check_replaceable", "clean_partial_rows",
    "completed_rows", "create_store", "disk_bytes", "finalize_store", "move_into_place",
    "temporary_sibling", "write_group",
    "from_scipy", "open", "read_store_attrs", "row_marker", "set_redirect", "write_tile_row",
]
