"""What a resumable inverse depends on: the fingerprint recorded in its store
(``params`` of the store's record) and compared when a run resumes it; a run whose
fingerprint differs is refused (:meth:`bigT.storage.InverseStore.open_or_create`)."""

from __future__ import annotations

import hashlib
import os

import numpy as np

from .first_bounce import FirstBounce
from .settings import Thresholds

#: The layout of the fingerprint itself.
FINGERPRINT_FORMAT = 1


def inverse_fingerprint(T, fb: FirstBounce, thresholds: Thresholds, method: str) -> dict:
    """The fingerprint (JSON) of the inverse of ``T`` by ``method``.

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
        Identified by its absolute path, shape, nnz, tile size, dtype and a hash of its
        tile index (which tiles hold how many entries).
    fb : FirstBounce
        Its kind and the digest of F.
    thresholds : Thresholds
        ``prune``, and ``prune_feed``/``prune_operator`` only when set (stores made
        before these existed resume).
    method : str
    """
    h = hashlib.sha1()
    h.update(np.asarray(T.tile_indptr, dtype=np.int64).tobytes())
    h.update(np.asarray(T.tile_indices, dtype=np.int64).tobytes())
    h.update(np.asarray(T.tile_nnz, dtype=np.int64).tobytes())
    return {
        "format": FINGERPRINT_FORMAT,
        "T": {"path": os.path.abspath(T.path), "shape": list(T.shape), "nnz": int(T.nnz),
              "tile_size": int(T.tile_size), "dtype": str(np.dtype(T.dtype)),
              "tiles": h.hexdigest()[:16]},
        **thresholds.recorded(),
        "method": method,
        "first_bounce": {"kind": fb.kind, "digest": fb.digest},
    }
