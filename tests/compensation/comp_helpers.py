"""Helpers of the compensation tests: small transports with independent references."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

import bigT


def make_store(A, path, *, image_shape, tile_size=64, pixel_order="row-major"):
    """A store of the row-major-numbered matrix ``A`` (scipy or dense)."""
    return bigT.from_scipy(sp.csr_array(A), path, tile_size=tile_size, image_shape=image_shape,
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


