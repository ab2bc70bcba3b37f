"""A real dask cluster for the tests (:class:`bigT.testing.ProcessCluster`): one
``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1 only, every process
stopped by its PID when the tests end, whatever happened."""

from __future__ import annotations

import pytest

from bigT.testing import ProcessCluster as Cluster

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
