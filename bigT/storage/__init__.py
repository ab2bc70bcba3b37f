"""bigT.storage: the zarr v3 block-CSR store (docs/FORMAT.md describes the layout).

Public API: :func:`open`, :func:`as_store` (a store or its path), :func:`from_scipy`, :class:`BlockCSR`,
:class:`BlockCSRWriter`, :func:`set_redirect` (for versioned stores) and
:class:`PixelOrder`; for writers in other processes: :func:`create_store`,
:func:`write_tile_row` (idempotent), :func:`finalize_store` (from the row markers);
the versioned inverse store: :class:`InverseStore`.
"""

from .attrs import StoreAttrs
from .block_csr import BlockCSR, as_store, open, row_marker, set_redirect  # noqa: A004
from .inverse_store import InverseRecord, InverseStore, TermEntry
from .pixel_order import PixelOrder
from .writer import (
    BlockCSRWriter,
    KeptTiles,
    clean_partial_rows,
    create_store,
    finalize_store,
    from_scipy,
    read_store_attrs,
    write_tile_row,
)

__all__ = [
    "BlockCSR", "BlockCSRWriter", "InverseRecord", "InverseStore", "KeptTiles", "PixelOrder",
    "StoreAttrs", "TermEntry", "as_store", "clean_partial_rows", "create_store", "finalize_store",
    "from_scipy", "open", "read_store_attrs", "row_marker", "set_redirect", "write_tile_row",
]
