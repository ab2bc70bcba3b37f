"""The one place where ``bigT.schedule``'s modules reach the storage and kernel layers:
they import stores and kernels from here, so the layers' contracts
(docs/CONTRACTS.md) are used in one spot. Other layers import ``bigT.storage`` and
``bigT.kernels`` themselves."""

from __future__ import annotations

from bigT.kernels import (SPGEMM_GROUP, BlockDiagonal, add_diag_scaled, diagonal_blocks,
                          off_block_diagonal, prune, release_workspaces, scale_cols,
                          scale_cols_off_diagonal, scale_rows, spgemm, spmm_dense,
                          workspace_bytes)
from bigT.kernels.row_ranges import add_diag_scaled_rows, multiply_adds
from bigT.storage import (BlockCSR, KeptTiles, ObjectPath, as_location, from_scipy, is_url,
                          read_store_attrs, row_marker, store_identity, write_tile_row)
from bigT.storage import open as open_store

__all__ = [
    "SPGEMM_GROUP", "BlockCSR", "BlockDiagonal", "KeptTiles", "ObjectPath", "add_diag_scaled",
    "add_diag_scaled_rows", "multiply_adds",
    "as_location", "is_url", "store_identity",
    "diagonal_blocks", "from_scipy", "off_block_diagonal", "open_store", "prune",
    "read_store_attrs", "release_workspaces", "row_marker", "scale_cols",
    "scale_cols_off_diagonal", "scale_rows", "spgemm",
    "spmm_dense", "workspace_bytes", "write_tile_row",
]
