"""A real dask cluster for the tests: one ``dask scheduler`` and two ``dask worker``
processes (``--nthreads 1``, a memory limit each, no nanny, so the PIDs started are the
processes that run tasks) on 127.0.0.1 only. Every process started is stopped by its
PID when the test ends, whatever happened."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

DASK = str(Path(sys.executable).with_name("dask"))


class Cluster:
    """The processes of one test cluster and the scheduler's address."""

    def __init__(self, tmp: Path, n_workers: int = 2, memory_limit: str = "2GiB"):
        self.tmp = tmp
        self.procs: dict[str, subprocess.Popen] = {}
        sched_file = tmp / "scheduler.json"
        self._start("scheduler", [DASK, "scheduler", "--host", "127.0.0.1", "--port", "0",
                                  "--no-dashboard", "--scheduler-file", str(sched_file)])
        self.address = self._wait_address(sched_file)
        for k in range(n_workers):
            self._start(f"worker{k}", [DASK, "worker", self.address, "--host", "127.0.0.1",
                                       "--nthreads", "1", "--memory-limit", memory_limit,
                                       "--no-nanny", "--no-dashboard", "--name", f"w{k}"])
        self.wait_for_workers(n_workers)

    def _start(self, name, cmd):
        log = open(self.tmp / f"{name}.log", "w")
        self.procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                            start_new_session=True)

    def _wait_address(self, sched_file: Path, timeout: float = 60) -> str:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            if sched_file.exists():
                try:
                    return json.loads(sched_file.read_text())["address"]
                except (ValueError, KeyError):
                    pass
            time.sleep(0.2)
        raise RuntimeError("dask scheduler did not start: " + self.log("scheduler"))

    def wait_for_workers(self, n: int, timeout: float = 90) -> None:
        from distributed import Client

        with Client(self.address, timeout=30) as client:
            client.wait_for_workers(n, timeout=timeout)

    def pid(self, name: str) -> int:
        return self.procs[name].pid

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text()[-3000:]

    def stop(self) -> None:
        """Workers first (a worker whose scheduler is gone keeps trying to reconnect),
        then the scheduler; SIGTERM, then SIGKILL after a few seconds."""
        workers = [p for name, p in self.procs.items() if name != "scheduler"]
        for group in (workers, [self.procs["scheduler"]]):
            for proc in group:
                if proc.poll() is None:
                    os.kill(proc.pid, signal.SIGTERM)
            deadline = time.monotonic() + 5
            for proc in group:
                try:
                    proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    os.kill(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=10)


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
