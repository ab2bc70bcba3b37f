"""A colour store's factored channel mixing: the store represents (I (x) L) S (I (x) R),
S its stored tiles, L and R one 3x3 matrix each for every pixel (docs/FORMAT.md,
"Colour": the ``mixing`` attribute).

The global-mixing inverse is X = (I (x) P^-1) U^-1 (I (x) C^-1) with U^-1 channel-
diagonal: kept factored, X has U^-1's entries (a third of a composed X's, whose every
pixel pair is a dense 3x3 block). Every product of such a store goes through
:func:`mixed_product`, so that no reader of a product forgets a side.

In any pixel order a pixel's three values are adjacent (index 3 p + c), so (I (x) L)
acts on a matrix-ordered (n, K) array as ``L`` on each pixel's (3, K) slice, and
commutes with the stores' pixel permutations.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from ..errors import CorruptStoreError


class ChannelMixing(NamedTuple):
    """The two sides of a factored colour store: (I (x) left) S (I (x) right).

    Attributes
    ----------
    left : (3, 3) float64
        Applied to each pixel's channel triple after the stored matrix.
    right : (3, 3) float64
        Applied to each pixel's channel triple before it.
    """

    left: np.ndarray
    right: np.ndarray

    def to_attrs(self) -> dict:
        """The ``mixing`` object of ``attributes["bigT"]``: 3x3 lists of rows."""
        return {"left": self.left.tolist(), "right": self.right.tolist()}

    @classmethod
    def from_attrs(cls, value, path) -> "ChannelMixing":
        """Parse the ``mixing`` attribute; CorruptStoreError naming ``path`` when it is not
        ``{"left": 3x3, "right": 3x3}`` of finite numbers."""
        try:
            if not isinstance(value, Mapping) or set(value) != {"left", "right"}:
                raise ValueError("not an object of left and right")
            left, right = (np.array(value[k], dtype=np.float64) for k in ("left", "right"))
            if left.shape != (3, 3) or right.shape != (3, 3):
                raise ValueError("left and right must be 3x3")
            if not (np.isfinite(left).all() and np.isfinite(right).all()):
                raise ValueError("left and right must be finite")
        except (TypeError, ValueError) as exc:
            raise CorruptStoreError(f"bad mixing attribute ({exc})", path) from None
        left.flags.writeable = right.flags.writeable = False
        return cls(left, right)


def mix_channels(M: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """(I (x) M) Y: ``M`` (3, 3) applied to every pixel's channel triple of ``Y``.

    Parameters
    ----------
    M : (3, 3)
    Y : (n,) or (n, K), n a multiple of 3, any pixel order

    Returns
    -------
    ndarray of Y's shape and dtype (float32 stays float32)
    """
    stacked = Y.reshape(Y.shape[0] // 3, 3, -1)
    out = np.einsum("ij,pjk->pik", M.astype(Y.dtype, copy=False), stacked)
    return out.reshape(Y.shape)


def mixed_product(mixing: ChannelMixing | None,
                  product: Callable[[np.ndarray], np.ndarray], V: np.ndarray) -> np.ndarray:
    """``L product(R V)``: the represented matrix times ``V`` from the stored matrix's
    ``product``; ``product(V)`` itself when there is no mixing.

    Parameters
    ----------
    mixing : ChannelMixing or None
    product : callable, (n, K) -> (n, K), the stored matrix S times its argument
    V : (n,) or (n, K), matrix order (or any pixel order the product takes)
    """
    if mixing is None:
        return product(V)
    return mix_channels(mixing.left, product(mix_channels(mixing.right, V)))


def kron_identity(M: np.ndarray, pixels: int, dtype) -> sp.csr_array:
    """I (x) M as a sparse (3 pixels, 3 pixels) matrix of ``dtype``."""
    return sp.csr_array(sp.kron(sp.identity(pixels, dtype=dtype, format="csr"),
                                sp.csr_array(M.astype(dtype)), format="csr"))


def mixed_rows(mixing: ChannelMixing | None, rows: sp.csr_array, start: int) -> sp.csr_array:
    """Rows ``start:start + rows.shape[0]`` of the represented matrix from the same rows
    ``rows`` of S (``start`` and the row count multiples of 3: whole pixels).

    Returns
    -------
    csr_array of ``rows``' shape and dtype, sorted indices
    """
    if mixing is None:
        return rows
    if start % 3 or rows.shape[0] % 3:
        raise ValueError(f"rows {start}:{start + rows.shape[0]} of a factored colour store "
                         "must be whole pixels (multiples of 3)")
    dtype = rows.dtype
    out = (kron_identity(mixing.left, rows.shape[0] // 3, dtype) @ rows
           @ kron_identity(mixing.right, rows.shape[1] // 3, dtype))
    out = sp.csr_array(out)
    out.sort_indices()
    return out


def mixed_diagonal(mixing: ChannelMixing, blocks: np.ndarray) -> np.ndarray:
    """The diagonal of L B_p R for each pixel's stored 3x3 diagonal block B_p.

    Parameters
    ----------
    blocks : (pixels, 3, 3)

    Returns
    -------
    (3 pixels,) the represented matrix's main diagonal
    """
    return np.einsum("ci,pij,jc->pc", mixing.left, blocks, mixing.right).ravel()


def mixed_blocks(mixing: ChannelMixing | None, blocks: np.ndarray) -> np.ndarray:
    """(pixels, 3, 3) L B_p R of each stored diagonal block B_p; ``blocks`` itself
    without mixing."""
    if mixing is None:
        return blocks
    return np.einsum("ci,pij,jd->pcd", mixing.left, blocks, mixing.right)
