"""bigT.storage: the zarr v3 block-CSR store (docs/FORMAT.md describes the layout).

Public API: :func:`open`, :func:`from_scipy`, :class:`BlockCSR`,
:class:`BlockCSRWriter`, :func:`set_redirect` (for versioned stores) and
:class:`PixelOrder`.
"""

from .block_csr import BlockCSR, open, set_redirect  # noqa: A004
from .pixel_order import PixelOrder
from .writer import BlockCSRWriter, from_scipy

__all__ = ["BlockCSR", "BlockCSRWriter", "PixelOrder", "from_scipy", "open", "set_redirect"]
