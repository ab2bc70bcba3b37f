"""Stores in a bucket of a real S3-compatible server (moto on 127.0.0.1): written and
read back equal to scipy, through the library and the command line, and every check a
local store gets (damage, a second writer, hostile URLs)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.errors import CorruptStoreError, StoreError
from bigT.storage import ObjectPath, as_location, disk_bytes, from_scipy


def _matrix(n=700, seed=1):
    R = sp.random(n, n, density=0.04, random_state=seed, format="csr", dtype=np.float32)
    return (sp.eye(n, dtype=np.float32) + R * (0.5 / abs(R).sum(1).max())).tocsr()


def test_a_store_written_to_the_bucket_reads_back_equal_to_scipy(s3_url):
    A = _matrix()
    S = from_scipy(A, f"{s3_url}/T.zarr", tile_size=128)
    assert isinstance(S.path, ObjectPath)
    back = bigT.open(f"{s3_url}/T.zarr")
    assert (back.to_scipy() != A).nnz == 0
    x = np.random.default_rng(0).random(A.shape[0])
    np.testing.assert_allclose(back @ x, A @ x, rtol=1e-5)
    np.testing.assert_array_equal(back.diagonal(), A.diagonal())
    assert back.verify()["nnz"] == A.nnz
    assert disk_bytes(back.path) > 0


def test_the_bucket_holds_the_keys_a_local_store_holds_as_files(s3_url, tmp_path):
    A = _matrix(300)
    from_scipy(A, tmp_path / "T.zarr", tile_size=128)
    S = from_scipy(A, f"{s3_url}/T.zarr", tile_size=128)
    local = sorted(p.relative_to(tmp_path / "T.zarr").as_posix()
                   for p in (tmp_path / "T.zarr").rglob("*") if p.is_file())
    remote = sorted(k[len(S.path.key) + 1:] for k, _ in S.path.walk_objects())
    assert remote == [k for k in local if not k.startswith(".")]


def test_a_damaged_object_is_found_by_verify(s3_url):
    S = from_scipy(_matrix(300), f"{s3_url}/T.zarr", tile_size=128)
    chunk = S.path / "rows" / "1" / "data" / "c" / "0"
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    chunk.write_bytes(bytes(raw))
    with pytest.raises((CorruptStoreError, ValueError), match="rows/1|checksum|tile row 1"):
        bigT.open(S.path).verify()


def test_a_second_writer_of_an_inverse_is_refused_by_the_lock_object(s3_url):
    import json

    from bigT.storage.locks import WriterLock

    first = WriterLock(as_location(f"{s3_url}/X.zarr")).acquire()
    try:
        with pytest.raises(StoreError, match="is being written by"):
            WriterLock(as_location(f"{s3_url}/X.zarr")).acquire()
    finally:
        first.release()
    WriterLock(as_location(f"{s3_url}/X.zarr")).acquire().release()  # free again
    lock = as_location(f"{s3_url}/X.zarr") / ".bigT-writer.lock"
    assert json.loads(lock.read_bytes())["released"] is True  # released, not deleted


def test_a_lock_of_a_dead_process_of_this_machine_is_taken_over(s3_url):
    import json

    from bigT.storage.object_lock import _machine

    lock = as_location(f"{s3_url}/X.zarr") / ".bigT-writer.lock"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    record = {"command": "bigT invert", "pid": dead.pid, **_machine()}
    lock.write_bytes(json.dumps(record).encode())
    from bigT.storage.locks import WriterLock

    held = WriterLock(lock.parent).acquire()
    assert json.loads(lock.read_bytes())["pid"] == os.getpid()
    held.release()
    # the same dead PID in another PID namespace (a container sharing the host name)
    # is no proof of death: refused until the lease runs out
    lock.write_bytes(json.dumps({**record, "pidns": -1}).encode())
    with pytest.raises(StoreError, match="is being written by"):
        WriterLock(lock.parent).acquire()


@pytest.mark.parametrize("url, problem", [
    ("s3:///T.zarr", "without a bucket"),
    ("s3://bucket/a/../T.zarr", "'..'"),
    ("http://example.com/T.zarr", "not served"),
])
def test_a_bad_url_is_refused_in_one_line(url, problem):
    with pytest.raises(StoreError, match=problem):
        bigT.open(url)


def _cli(*args, env=None, cwd=None):
    return subprocess.run([sys.executable, "-m", "bigT.cli", *map(str, args)],
                          capture_output=True, text=True, env={**os.environ, **(env or {})},
                          timeout=300, cwd=cwd)


def test_convert_to_a_url_writes_the_bucket_and_no_local_directory(s3_url, tmp_path):
    A = _matrix(400)
    sp.save_npz(tmp_path / "T.npz", A)
    out = _cli("convert", tmp_path / "T.npz", "-o", f"{s3_url}/run/T.zarr", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert not (tmp_path / "s3:").exists()
    scene = _cli("scene", "dihedral4", "-o", f"{s3_url}/run/D.zarr", "-q", cwd=tmp_path)
    assert scene.returncode == 0, scene.stderr
    assert list(tmp_path.iterdir()) == [tmp_path / "T.npz"]  # nothing local was written
    assert bigT.scenes.load(f"{s3_url}/run/D.zarr").T.shape == (4, 4)
    assert (bigT.open(f"{s3_url}/run/T.zarr").to_scipy() != A).nnz == 0
    info = _cli("info", f"{s3_url}/run/T.zarr")
    assert info.returncode == 0 and "400" in info.stdout, info.stderr


def test_a_missing_store_in_the_bucket_is_one_line_exit_2(s3_url):
    out = _cli("info", f"{s3_url}/nothing.zarr")
    assert out.returncode == 2
    assert "Traceback" not in out.stderr and "nothing.zarr" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


def test_a_scene_built_into_the_bucket_opens_and_inverts_from_the_command_line(s3_url, tmp_path):
    out = _cli("scene", "corner", "--size", "24x32", "-o", f"{s3_url}/scene/T.zarr", "-q",
               env={"TMPDIR": str(tmp_path)})
    assert out.returncode == 0, out.stderr
    scene = bigT.scenes.load(f"{s3_url}/scene/T.zarr")
    assert scene.T.shape == (768, 768) and scene.A.nnz > 0
    assert (as_location(f"{s3_url}/scene") / "T-preview.png").is_file()
    scratch = tmp_path / f"bigT-scenes-{os.getuid()}"
    assert not any(scratch.iterdir()), "the local build is deleted"
    inv = _cli("invert", f"{s3_url}/scene/T.zarr", "-o", f"{s3_url}/scene/X.zarr", "--terms",
               "2", "-q")
    assert inv.returncode == 0, inv.stderr


def test_export_to_the_bucket_puts_one_object_scipy_reads(s3_url, tmp_path):
    import io

    A = _matrix(200)
    from_scipy(A, f"{s3_url}/T.zarr", tile_size=128)
    out = _cli("export", f"{s3_url}/T.zarr", "-o", f"{s3_url}/T.npz")
    assert out.returncode == 0, out.stderr
    back = sp.load_npz(io.BytesIO(as_location(f"{s3_url}/T.npz").read_bytes()))
    assert (back != A).nnz == 0


def test_a_lock_renewed_by_its_holder_stays_and_an_abandoned_one_is_taken_over(s3_url,
                                                                                 monkeypatch):
    """With a 2 s lease: a live holder renews its lock (a second writer is refused after
    more than one lease), a lock nobody renews (its host unknown here) is taken over
    once a lease has passed, by one conditional write."""
    import json
    import time

    from bigT import config
    from bigT.storage.locks import WriterLock

    monkeypatch.setattr(config, "OBJECT_LOCK_SECONDS", 2.0)
    root = as_location(f"{s3_url}/X.zarr")
    held = WriterLock(root).acquire()
    try:
        time.sleep(3.0)  # longer than a lease: only the renewals keep it
        with pytest.raises(StoreError, match="is being written by"):
            WriterLock(root).acquire()
    finally:
        held.release()
    lock = root / ".bigT-writer.lock"
    lock.write_bytes(json.dumps({"command": "bigT invert", "pid": 1,
                                 "host": "another-machine"}).encode())
    with pytest.raises(StoreError, match="another-machine"):
        WriterLock(root).acquire()  # renewed just now, as far as anyone can tell
    time.sleep(2.5)
    taker = WriterLock(root).acquire()
    assert json.loads(lock.read_bytes())["pid"] == os.getpid()
    taker.release()


def test_convert_over_its_own_input_under_another_spelling_is_refused(s3_url):
    A = _matrix(200)
    from_scipy(A, f"{s3_url}/T.zarr", tile_size=128)
    other = f"{s3_url.replace('s3://', 'S3A://', 1)}/T.zarr"
    out = _cli("convert", f"{s3_url}/T.zarr", "-o", other, "--overwrite")
    assert out.returncode == 2 and "input" in out.stderr, out.stderr
    assert (bigT.open(f"{s3_url}/T.zarr").to_scipy() != A).nnz == 0  # untouched


def test_a_store_being_inverted_is_not_replaced_under_its_writer(s3_url):
    from bigT.storage.locks import ReplaceLock, WriterLock

    from_scipy(_matrix(200), f"{s3_url}/X.zarr", tile_size=128)
    writer = WriterLock(as_location(f"{s3_url}/X.zarr")).acquire()
    try:
        with pytest.raises(StoreError, match="is being written by"):
            ReplaceLock(f"{s3_url}/X.zarr", "bigT convert").acquire()
    finally:
        writer.release()


def test_a_writer_that_lost_its_lock_publishes_nothing(s3_url, monkeypatch):
    import time

    from bigT import config
    from bigT.storage.locks import WriterLock

    # 2 s: S3's Last-Modified has whole seconds, a shorter lease would be noise
    monkeypatch.setattr(config, "OBJECT_LOCK_SECONDS", 2.0)
    root = as_location(f"{s3_url}/X.zarr")
    first = WriterLock(root).acquire()
    first._object._stop.set()  # frozen: it renews no more
    time.sleep(3.1)
    second = WriterLock(root).acquire()  # abandoned: taken over
    first._object._stop.clear()
    first._object._renew()  # wakes: its renewal is refused, it knows it lost
    with pytest.raises(StoreError, match="lost its writer lock"):
        first.check_held()
    first.release()  # never releases the other writer's lock
    with pytest.raises(StoreError, match="is being written by"):
        WriterLock(root).acquire()
    second.release()
