"""bigT.warm fills numba's cache with every kernel a first run needs (make runs it after
installing): checked in an empty NUMBA_CACHE_DIR, then a first invert and a first
in-memory compensation in a new process compile nothing more."""

import os
import subprocess
import sys
from pathlib import Path

import pytest


def _cached(cache: Path) -> set[str]:
    return {p.name.split("-")[0] for p in cache.rglob("*.nbi")}


@pytest.mark.slow
def test_warm_caches_what_a_first_run_compiles(tmp_path):
    cache = tmp_path / "numba-cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    subprocess.run([sys.executable, "-m", "bigT.warm"], env=env, check=True,
                   capture_output=True, timeout=600)
    warmed = _cached(cache)
    for kernel in ("_csr_kernels.spgemm_grouped_internal", "_csr_kernels.prune_internal",
                   "_csr_kernels.spmm_dense_rows_internal",
                   "_csr_kernels.add_diag_scaled_internal",
                   # the narrowed product's (few lit patches), which the toy scene skips
                   "_row_kernels.relabel_internal", "_row_kernels.kept_by_column_internal",
                   "_row_kernels.select_by_column_into_internal"):
        assert kernel in warmed, kernel
    files = {p.name for p in cache.rglob("*.nbc")}
    first_run = (
        "import numpy as np, bigT\n"
        "from bigT.compensation.resident import load_resident\n"
        f"sc = bigT.scenes.corner((24, 32), r'{tmp_path / 'T.zarr'}', preview=False,"
        " progress=False)\n"
        f"bigT.stratified_inverse(sc.T, r'{tmp_path / 'X.zarr'}', progress=False)\n"
        f"load_resident(bigT.open(r'{tmp_path / 'X.zarr'}')).matmul("
        "np.ones((768, 2), np.float32))\n")
    subprocess.run([sys.executable, "-c", first_run], env=env, check=True,
                   capture_output=True, timeout=600)
    assert {p.name for p in cache.rglob("*.nbc")} == files  # nothing compiled anew
