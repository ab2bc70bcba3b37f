"""A real S3-compatible server for the object-storage tests: moto's server mode
(:class:`bigT.testing.S3Server`) as its own process on 127.0.0.1, one per test module,
stopped by its PID. Nothing here reaches any other address: the endpoint is loopback
and ``AWS_ENDPOINT_URL`` points every client (this process, the dask workers) at it."""

from __future__ import annotations

import itertools

import pytest

from bigT.testing import S3Server

_names = itertools.count()


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    server = S3Server(tmp_path_factory.mktemp("moto"))
    mp = pytest.MonkeyPatch()
    try:
        for key, value in server.env.items():
            mp.setenv(key, value)
        yield server
    finally:
        mp.undo()
        server.stop()


@pytest.fixture
def s3_url(s3):
    """A fresh prefix of the bucket, ``s3://bigt-test/tN``, for one test."""
    return s3.url(f"t{next(_names)}")
