"""bigT.kernels: numba kernels on raw CSR arrays, with checked scipy.sparse wrappers.

No zarr or dask here (docs/DESIGN.md): the schedule layer feeds tiles in and gets
``scipy.sparse.csr_array`` (sorted, duplicate-free) back.
"""

from .csr import (
    add_diag_scaled,
    choose_index_dtype,
    diagonal,
    prune,
    release_workspaces,
    scale_cols,
    scale_cols_off_diagonal,
    scale_rows,
    spgemm,
    spmm_dense,
    workspace_bytes,
)
from ._constants import GROUP as SPGEMM_GROUP
from .block_diagonal import BlockDiagonal, diagonal_blocks, off_block_diagonal

__all__ = [
    "spgemm",
    "add_diag_scaled",
    "scale_rows",
    "scale_cols",
    "scale_cols_off_diagonal",
    "diagonal",
    "prune",
    "spmm_dense",
    "choose_index_dtype",
    "SPGEMM_GROUP",
    "release_workspaces",
    "workspace_bytes",
    "BlockDiagonal",
    "diagonal_blocks",
    "off_block_diagonal",
]
