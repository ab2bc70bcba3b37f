"""The stratified inverse with T and X in a bucket (moto on 127.0.0.1), on threads:
equal to the same run on a local directory, through both engine paths, resumed after
an interruption, and from the command line."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest

import bigT
from bigT.storage import as_location
from bigT.storage.upgrade import upgrade_store

TERMS = 3


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "T.zarr"
    return bigT.scenes.corner(size=(24, 32), path=path, tile_size=128, preview=False)


@pytest.fixture(scope="module")
def local_X_path(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "X.zarr"
    bigT.stratified_inverse(scene.T, out, terms=TERMS, progress=False, in_memory=False)
    return out


@pytest.fixture(scope="module")
def local_X(local_X_path):
    return bigT.open(local_X_path).to_scipy()


@pytest.fixture(scope="module")
def T_url(scene, s3):
    url = s3.url("scene/T.zarr")
    S = upgrade_store(scene.T.path, url)  # pixel order and metadata travel with it
    assert S.pixel_order == scene.T.pixel_order
    return url


@pytest.mark.parametrize("in_memory", [False, True])
def test_the_inverse_in_the_bucket_equals_the_local_one(T_url, local_X, s3_url, in_memory):
    report = bigT.stratified_inverse(T_url, f"{s3_url}/X.zarr", terms=TERMS, progress=False,
                                     in_memory=in_memory)
    assert report.terms == TERMS
    X = bigT.open(f"{s3_url}/X.zarr")
    assert re.search(r"X\.zarr/t\d{4}/X$", X.path.key)  # the redirect was followed
    assert abs(X.to_scipy() - local_X).max() == 0


def test_an_interrupted_inverse_in_the_bucket_resumes(T_url, local_X, s3_url):
    out = f"{s3_url}/X.zarr"
    bigT.stratified_inverse(T_url, out, terms=1, progress=False, in_memory=False)
    report = bigT.stratified_inverse(T_url, out, terms=TERMS, progress=False, in_memory=False)
    assert report.resumed_from == 1
    assert abs(bigT.open(out).to_scipy() - local_X).max() == 0
    # the dropped terms are gone from the bucket: only the current one is held
    terms = sorted(p.name for p in as_location(out).iterdir() if p.name.startswith("t0"))
    assert terms == [bigT.open(out).path.parent.name]


def test_invert_from_the_command_line_with_urls(T_url, local_X, s3_url):
    out = subprocess.run([sys.executable, "-m", "bigT.cli", "invert", T_url, "-o",
                          f"{s3_url}/X.zarr", "--terms", str(TERMS), "--prune", "1e-5", "-q"],
                         capture_output=True, text=True, env=dict(os.environ), timeout=600)
    assert out.returncode == 0, out.stderr
    assert abs(bigT.open(f"{s3_url}/X.zarr").to_scipy() - local_X).max() == 0


def test_compensate_reads_the_inverse_from_the_bucket(T_url, local_X_path, s3_url, tmp_path):
    import imageio.v3 as iio

    bigT.stratified_inverse(T_url, f"{s3_url}/X.zarr", terms=TERMS, progress=False)
    desired = (np.random.default_rng(0).random((24, 32)) * 200 + 20).astype(np.uint8)
    iio.imwrite(tmp_path / "desired.png", desired)
    outputs = []
    for name, X in (("s3", f"{s3_url}/X.zarr"), ("local", local_X_path)):
        out = subprocess.run([sys.executable, "-m", "bigT.cli", "compensate", str(X),
                              str(tmp_path / "desired.png"), "-o", str(tmp_path / f"{name}.png"),
                              "-q"], capture_output=True, text=True, env=dict(os.environ),
                             timeout=300)
        assert out.returncode == 0, out.stderr
        outputs.append(iio.imread(tmp_path / f"{name}.png"))
    np.testing.assert_array_equal(outputs[0], outputs[1])


def test_storage_options_given_in_python_travel_with_the_stores(T_url, local_X, s3, s3_url,
                                                                monkeypatch):
    """No AWS_* variable in the environment: the endpoint and credentials are the
    stores' own options (as_location), and every term store the run opens keeps them."""
    options = {"endpoint": s3.endpoint, "access_key_id": "testing",
               "secret_access_key": "testing", "region": "us-east-1"}
    for key in s3.env:  # (nothing is opened without options: no request leaves loopback)
        monkeypatch.delenv(key, raising=False)
    T = as_location(T_url, options)
    out = as_location(f"{s3_url}/X.zarr", options)
    bigT.stratified_inverse(T, out, terms=TERMS, progress=False, in_memory=False)
    assert abs(bigT.open(out).to_scipy() - local_X).max() == 0
    assert abs(bigT.open(str(out), storage_options=options).to_scipy() - local_X).max() == 0
