"""Compile bigT's numba kernels into numba's on-disk cache before the first real run.

``python -m bigT.warm`` (``make`` runs it once after installing) builds a tiny scene,
inverts it, and compensates a few frames with X streamed and held in memory, in
float32 and float64, with every product sent to the numba kernels
(``config.KERNEL_NUMPY_MAX_WORK`` set below zero for the call). numba then finds each
kernel in its cache (``cache=True``: the package directory, or ``NUMBA_CACHE_DIR``):
a user's first ``bigT invert`` of anything beyond a toy no longer waits ~10 s for the
compiler. Products under the threshold never needed numba; this only moves the
compilation of the others from the first run to the install.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from . import config, scenes
from .algorithms import stratified_inverse
from .compensation import compensate
from .compensation.resident import load_resident
from .kernels import row_ranges
from .storage import open as open_store


@contextlib.contextmanager
def _numba_for_everything():
    """Every kernel call takes its numba path for the duration (none is small enough
    for the numpy twins)."""
    saved = config.KERNEL_NUMPY_MAX_WORK
    config.KERNEL_NUMPY_MAX_WORK = -1
    try:
        yield
    finally:
        config.KERNEL_NUMPY_MAX_WORK = saved


def _exercise(tmp: Path, dtype: str) -> None:
    """Build, invert and compensate a 12x16 corner stored as ``dtype``."""
    scene = scenes.corner((12, 16), tmp / f"T-{dtype}.zarr", preview=False, progress=False,
                          dtype=dtype, tile_size=64)
    X = tmp / f"X-{dtype}.zarr"
    stratified_inverse(scene.T, X, terms=2, progress=False)
    stratified_inverse(scene.T, tmp / f"Xf-{dtype}.zarr", terms=2, prune=1e-6,
                       prune_feed=1e-4, progress=False)
    frames = np.full((2, 12, 16), 0.5)
    compensate(X, frames, batch=2)
    resident = load_resident(open_store(X))
    for batch in (1, 2):
        resident.matmul(np.ones((scene.T.shape[1], batch), np.float32))
    load_resident(open_store(X), precision="float16").matmul(np.ones(scene.T.shape[1], np.float32))


def _exercise_narrowed_product(dtype: str) -> None:
    """The kernels of a product on few lit patches (``row_ranges.narrow_columns``,
    ``restrict_to_used_rows``, ``NarrowedColumns.widen``), which the toy scene above
    never calls: every patch of a 12x16 corner is lit."""
    rng = np.random.default_rng(0)
    left = sp.random_array((64, 64), density=0.3, format="csr", dtype=dtype, rng=rng)
    right = sp.random_array((64, 64), density=0.3, format="csr", dtype=dtype, rng=rng)
    every_fourth = sp.diags_array((np.arange(64) % 4 == 0).astype(dtype))
    right = sp.csr_array(every_fourth @ right @ every_fourth)  # few rows and columns used
    for matrix in (left, right):
        matrix.indices = matrix.indices.astype(np.int32)
        matrix.indptr = matrix.indptr.astype(np.int32)
        matrix.sum_duplicates()
    row_ranges.restrict_to_used_rows(left, right, 2)
    narrowed = row_ranges.narrow_columns(right, 2)
    narrowed.widen(sp.csr_array(left @ narrowed.matrix), 2)


def warm() -> float:
    """Compile (or load from the cache) every kernel a first run needs; returns the
    seconds it took."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bigT-warm-") as tmp, _numba_for_everything():
        for dtype in ("float32", "float64"):
            _exercise(Path(tmp), dtype)
            _exercise_narrowed_product(dtype)
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"bigT: numba kernels compiled and cached in {warm():.1f} s")
