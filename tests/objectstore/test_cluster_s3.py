"""A dask cluster whose workers share nothing but the bucket: real ``dask scheduler``
and ``dask worker`` processes on 127.0.0.1, each worker in a temporary directory of its
own, reaching moto on loopback through ``AWS_ENDPOINT_URL``; ``bigT invert`` and
compensation with T and X in the bucket equal the same run on local threads."""

from __future__ import annotations

import numpy as np
import pytest

import bigT
from bigT.errors import SchedulerError
from bigT.storage.upgrade import upgrade_store
from bigT.testing import ProcessCluster

TERMS = 3


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "T.zarr"
    return bigT.scenes.corner(size=(48, 64), path=path, tile_size=256, preview=False)


@pytest.fixture(scope="module")
def cluster(s3, tmp_path_factory):
    c = ProcessCluster(tmp_path_factory.mktemp("cluster"), worker_env=s3.env,
                       separate_dirs=True)
    try:
        yield c
    finally:
        c.stop()


def test_workers_sharing_only_the_bucket_invert_equal_to_local_threads(scene, cluster, s3,
                                                                        tmp_path):
    T_url = s3.url("cluster/T.zarr")
    upgrade_store(scene.T.path, T_url)
    local = tmp_path / "X.zarr"
    bigT.stratified_inverse(scene.T, local, terms=TERMS, progress=False, in_memory=False)
    report = bigT.stratified_inverse(T_url, s3.url("cluster/X.zarr"), terms=TERMS,
                                     progress=False, scheduler=cluster.address,
                                     in_memory=False)
    assert "dask cluster" in report.scheduler
    X = bigT.open(s3.url("cluster/X.zarr")).to_scipy()
    assert abs(X - bigT.open(local).to_scipy()).max() == 0
    # the workers wrote nothing in their own directories but dask's scratch space
    for home in cluster.worker_dirs():
        assert not [p for p in home.rglob("*.zarr")], home
    # compensation on the cluster reads X from the bucket too
    frames = np.random.default_rng(0).random((2, 48, 64))
    seen = bigT.compensate(s3.url("cluster/X.zarr"), frames, scheduler=cluster.address)
    np.testing.assert_allclose(seen, bigT.compensate(local, frames), rtol=1e-5, atol=1e-6)


def test_a_memory_store_is_refused_for_worker_processes(scene, cluster):
    bigT.storage.from_scipy(scene.T.to_scipy(), "memory:///c/T.zarr", tile_size=256)
    with pytest.raises(SchedulerError, match="memory"):
        bigT.stratified_inverse("memory:///c/T.zarr", "memory:///c/X.zarr", terms=1,
                                progress=False, scheduler=cluster.address, in_memory=False)


@pytest.mark.slow  # ~80 s: three runs on the cluster (make test-all)
def test_a_worker_killed_mid_run_is_survived_with_the_stores_in_the_bucket(scene, cluster, s3,
                                                                           tmp_path):
    """``bigT invert`` with T and X in the bucket, worker1 SIGKILLed at 40 % of an
    undisturbed run and replaced: exit 0 and the local threaded inverse."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parents[1] / "cluster"))
    from worker_loss import run_with_kill

    T_url = s3.url("loss/T.zarr")
    upgrade_store(scene.T.path, T_url)
    local = tmp_path / "X.zarr"
    bigT.stratified_inverse(scene.T, local, terms=TERMS, progress=False, in_memory=False)

    def command(out):
        return [sys.executable, "-m", "bigT.cli", "invert", T_url, "-o", out, "--terms",
                str(TERMS), "--scheduler", cluster.address, "--no-progress"]

    undisturbed = run_with_kill(cluster, command(s3.url("loss/X0.zarr")), None)
    assert undisturbed.returncode == 0, undisturbed.output
    run = run_with_kill(cluster, command(s3.url("loss/X1.zarr")), 0.4 * undisturbed.seconds)
    assert run.returncode == 0, run.output
    assert run.killed
    assert abs(bigT.open(s3.url("loss/X1.zarr")).to_scipy()
               - bigT.open(local).to_scipy()).max() == 0
    cluster.wait_for_workers(2)
