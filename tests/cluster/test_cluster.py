"""bigT on a real dask cluster (conftest.Cluster: a ``dask scheduler`` and two ``dask
worker`` processes on 127.0.0.1): the inverse equals the local threaded run, the
scheduler really ran the tasks, a worker killed midway changes nothing, ``local:N``
works, compensation and relighting run there too, and failures are one line."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

import bigT
from bigT.cli import main


def _task_prefixes(address) -> set[str]:
    from distributed import Client

    with Client(address, timeout=30) as client:
        return set(client.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.task_prefixes)))


def test_invert_through_scheduler_equals_local(scene, local_inverse, cluster, tmp_path, capsys):
    out = tmp_path / "X.zarr"
    assert main(["invert", str(scene.path), "-o", str(out), "--terms", "3",
                 "--scheduler", cluster.address, "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert f"dask cluster {cluster.address}: 2 workers" in text
    assert text.count("memory limit 2048 MiB, 1 threads") == 2  # each worker's own plan
    np.testing.assert_allclose(bigT.open(out).to_scipy().toarray(), local_inverse,
                               rtol=1e-6, atol=1e-9)
    # the scheduler ran term 0, the products and the spectral radius and residual
    # mat-vecs (the power form's tasks report X's share of the residual probes, so X is
    # not read back; M's sign is known from the read of T's diagonal: no "largest-M")
    assert {"diag", "power", "matvec-M"} <= _task_prefixes(cluster.address)


def _first_row_of_term(out, k):
    rows = out / f"t{k:04d}" / "X" / "rows"
    return rows.is_dir() and any(p.name.isdigit() for p in rows.iterdir())


def test_worker_killed_midway(scene, local_inverse, fresh_cluster, tmp_path):
    cluster = fresh_cluster
    out = tmp_path / "X.zarr"
    result = {}

    def run():
        try:
            result["report"] = bigT.stratified_inverse(scene.T, out, terms=3, progress=False,
                                                       scheduler=cluster.address)
        except BaseException as exc:  # handed to the test thread
            result["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    deadline = time.monotonic() + 120
    while not _first_row_of_term(out, 2) and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert thread.is_alive(), "the run ended before a worker could be killed"
    os.kill(cluster.pid("worker1"), signal.SIGKILL)
    thread.join(timeout=300)
    assert "error" not in result, result.get("error")
    assert cluster.procs["worker1"].poll() is not None  # it really died
    assert result["report"].terms == 3
    np.testing.assert_allclose(bigT.open(out).to_scipy().toarray(), local_inverse,
                               rtol=1e-6, atol=1e-9)


def test_local_cluster_of_processes(scene, local_inverse, tmp_path, capsys):
    out = tmp_path / "X.zarr"
    assert main(["invert", str(scene.path), "-o", str(out), "--terms", "3",
                 "--scheduler", "local:2", "--no-progress"]) == 0
    assert ": 2 workers, 2 threads" in capsys.readouterr().out
    np.testing.assert_allclose(bigT.open(out).to_scipy().toarray(), local_inverse,
                               rtol=1e-6, atol=1e-9)


def test_compensate_and_relight_on_the_cluster(scene, cluster, tmp_path):
    X = tmp_path / "X.zarr"
    bigT.stratified_inverse(scene.T, X, terms=2, progress=False)
    desired = np.random.default_rng(0).uniform(0.3, 0.7, (3, 48, 64))
    np.save(tmp_path / "desired.npy", desired[0])
    local = bigT.compensate(X, desired, batch=2)
    remote = bigT.compensate(X, desired, batch=2, scheduler=cluster.address)
    np.testing.assert_allclose(remote, local, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(bigT.relight(scene.T, desired, scheduler=cluster.address),
                               bigT.relight(scene.T, desired), rtol=1e-6, atol=1e-7)
    assert main(["compensate", str(X), str(tmp_path / "desired.npy"), "-o",
                 str(tmp_path / "l_in.npy"), "--scheduler", cluster.address,
                 "--no-progress"]) == 0
    # the CLI multiplies at its own batch (64): a float32 X summed in float32 lanes in
    # another order than the library's batch of 2, so a few values differ by ~1e-6
    np.testing.assert_allclose(np.load(tmp_path / "l_in.npy"), local[0], rtol=1e-5, atol=1e-6)
    assert "X pass" in _task_prefixes(cluster.address)


def test_unreachable_scheduler_is_one_line(scene, tmp_path, capsys, monkeypatch):
    import socket

    from bigT import config

    monkeypatch.setattr(config, "SCHEDULER_CONNECT_SECONDS", 2)
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(["invert", str(scene.path), "-o", str(tmp_path / "X.zarr"),
                 "--scheduler", f"tcp://127.0.0.1:{port}", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("bigT invert: error: cannot reach the dask scheduler")
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "X.zarr").exists()  # refused before anything was written


def test_workers_that_cannot_see_a_path_are_refused(cluster):
    from bigT.schedule.runner import open_runner

    runner = open_runner(cluster.address)
    try:
        with pytest.raises(bigT.BigTError, match="cannot see /nonexistent.*shared filesystem"):
            runner.check_paths(["/nonexistent/T.zarr"])
    finally:
        runner.close()
