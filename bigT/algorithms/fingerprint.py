"""What a resumable inverse depends on: the fingerprint recorded in its store
(``params`` of the store's record) and compared when a run resumes it; a run whose
fingerprint differs is refused (:meth:`bigT.storage.InverseStore.open_or_create`)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np

from ..errors import BigTError
from ..storage import InverseStore
from ..schedule.runner import worker_path
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
        "T": {"path": str(worker_path(T.path)), "shape": list(T.shape), "nnz": int(T.nnz),
              "tile_size": int(T.tile_size), "dtype": str(np.dtype(T.dtype)),
              "tiles": h.hexdigest()[:16]},
        **thresholds.recorded(),
        "method": method,
        "first_bounce": {"kind": fb.kind, "digest": fb.digest},
    }


@dataclass(frozen=True)
class RecordedSetting:
    """The method and thresholds an inverse store was made with."""

    method: str
    thresholds: Thresholds


def recorded_setting(T, fb: FirstBounce, out) -> RecordedSetting | None:
    """The setting of the inverse of ``T`` (first bounce ``fb``) that ``out`` holds,
    read from its fingerprint: a run with it resumes the store, whatever defaults made
    it (a store of bigT 0.x's ``prune 1e-5`` and no feed threshold, say). None when
    ``out`` holds no inverse, or one of another T or first bounce, or a record this
    cannot read: the engine's own checks then decide (and refuse what is not a bigT
    inverse, naming the path)."""
    try:
        record = InverseStore(out).read_record()
    except (BigTError, OSError, ValueError):
        return None
    if record is None:
        return None
    params = record.params
    try:
        setting = RecordedSetting(str(params["method"]), Thresholds(
            float(params["prune"]), _optional(params.get("prune_feed")),
            _optional(params.get("prune_operator"))))
    except (KeyError, TypeError, ValueError):
        return None
    # the whole fingerprint, as JSON stores it: T's identity and F's digest included
    mine = json.loads(json.dumps(inverse_fingerprint(T, fb, setting.thresholds,
                                                     setting.method)))
    return setting if mine == json.loads(json.dumps(dict(params))) else None


def _optional(value) -> float | None:
    return None if value is None else float(value)
