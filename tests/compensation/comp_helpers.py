"""Helpers of the compensation tests: small transports with independent references."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bigT.storage.pixel_order import PixelOrder


class _MemStore:
    """TEMPORARY stand-in for BlockCSR until bigT.storage lands (delete then)."""

    def __init__(self, A, image_shape, tile_size, pixel_order, image_tile=(8, 8)):
        self.pixel_order = PixelOrder(image_shape, pixel_order, image_tile)
        p = self.pixel_order.permutation
        A = sp.csr_array(A)
        self._A = sp.csr_array(A[p][:, p]).astype(np.float32)
        self.shape = self._A.shape
        self.dtype = np.dtype(np.float32)
        self.nnz = self._A.nnz
        self.tile_size = tile_size
        self.grid = (-(-self.shape[0] // tile_size), -(-self.shape[1] // tile_size))
        self.metadata = {}
        self.path = None

    def tile_row_range(self, i):
        return i * self.tile_size, min((i + 1) * self.tile_size, self.shape[0])

    def get_tile_row(self, i):
        a, b = self.tile_row_range(i)
        return self._A[a:b]

    def diagonal(self):
        return self._A.diagonal()


def make_store(A, path, *, image_shape, tile_size=64, pixel_order="row-major"):
    """A store of the row-major-numbered matrix ``A`` (scipy or dense)."""
    try:
        from bigT.storage import from_scipy
    except ImportError:
        return _MemStore(A, image_shape, tile_size, pixel_order)
    return from_scipy(sp.csr_array(A), path, tile_size=tile_size, image_shape=image_shape,
                      pixel_order=pixel_order, input_order="row-major", dtype="float32")


def random_transport(H, W, seed=0, density=0.05, glow=0.4):
    """A diffuse-looking transport T = (I - A)^-1 F, dense, with its exact inverse.

    A is non-negative with row sums < ``glow`` (spectral radius < 1), F a positive
    diagonal; returned row-major: (T, X = F^-1 (I - A), F, A).
    """
    rng = np.random.default_rng(seed)
    n = H * W
    A = sp.random(n, n, density=density, random_state=rng, format="csr").toarray()
    np.fill_diagonal(A, 0.0)
    A *= glow / np.maximum(A.sum(axis=1, keepdims=True), 1e-12)
    F = rng.uniform(0.6, 1.0, n)
    X = (np.eye(n) - A) / F[:, None]
    T = np.linalg.inv(X)
    return T, X, F, A


