"""A real S3-compatible server for the object-storage tests: moto's server mode
(:class:`bigT.testing.S3Server`) as its own process on 127.0.0.1, one for the session
(each test writes under a prefix of its own; a server takes seconds to start), stopped
by its PID. Nothing here reaches any other address: the endpoint is loopback
and ``AWS_ENDPOINT_URL`` points every client (this process, the dask workers) at it."""

from __future__ import annotations

import itertools

import pytest

from bigT.testing import S3Server

_names = itertools.count()


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory):
    server = S3Server(tmp_path_factory.mktemp("moto"))
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="module")
def s3(s3_server):
    """The server, with ``AWS_ENDPOINT_URL`` and its credentials in the environment for
    the module's tests (and the processes they start) only."""
    mp = pytest.MonkeyPatch()
    try:
        for key, value in s3_server.env.items():
            mp.setenv(key, value)
        yield s3_server
    finally:
        mp.undo()


@pytest.fixture
def s3_url(s3):
    """A fresh prefix of the bucket, ``s3://bigt-test/tN``, for one test."""
    return s3.url(f"t{next(_names)}")
