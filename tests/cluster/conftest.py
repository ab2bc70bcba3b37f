"""A real dask cluster for the tests (:class:`bigT.testing.ProcessCluster`): one
``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1 only, every process
stopped by its PID when the tests end, whatever happened."""

from __future__ import annotations

import pytest

import bigT
from bigT.testing import ProcessCluster as Cluster

#: Terms of the inverse the cluster tests compare against the local one.
TERMS = 3

@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A cluster shared by the tests of a module (none of them kills a worker)."""
    c = Cluster(tmp_path_factory.mktemp("cluster"))
    try:
        yield c
    finally:
        c.stop()


@pytest.fixture
def fresh_cluster(tmp_path):
    """A cluster of the test's own (it may kill its workers)."""
    c = Cluster(tmp_path)
    try:
        yield c
    finally:
        c.stop()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The 48x64 corner in 12 tile rows of 256: enough tasks for both workers in every
    pass."""
    path = tmp_path_factory.mktemp("scene") / "T.zarr"
    return bigT.scenes.corner(size=(48, 64), path=path, tile_size=256, preview=False)


@pytest.fixture(scope="module")
def local_inverse(scene, tmp_path_factory):
    """The scene's TERMS-term inverse on this process's threads, dense."""
    out = tmp_path_factory.mktemp("local") / "X.zarr"
    bigT.stratified_inverse(scene.T, out, terms=TERMS, progress=False)
    return bigT.open(out).to_scipy().toarray()
