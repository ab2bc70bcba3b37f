"""Helpers for bigT's tests and benchmarks (as ``numpy.testing``): a dask cluster of
real processes on this machine, and an S3-compatible server.

:class:`ProcessCluster` starts one ``dask scheduler`` and N ``dask worker`` processes
(``--nthreads 1``, a memory limit each, no nanny, so the PIDs started are the processes
that run tasks) on 127.0.0.1 only, and stops every process it started, by PID.
:class:`S3Server` starts moto's S3 server on 127.0.0.1 with one bucket, and stops it
by PID.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

DASK = str(Path(sys.executable).with_name("dask"))


class ProcessCluster:
    """The processes of one cluster and the scheduler's address.

    Parameters
    ----------
    tmp : Path, a directory for the scheduler file and the processes' logs
    n_workers : int
    memory_limit : str, each worker's ``--memory-limit``
    """

    def __init__(self, tmp: Path, n_workers: int = 2, memory_limit: str = "2GiB", *,
                 worker_env: dict | None = None, separate_dirs: bool = False):
        self.tmp = tmp
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs = []
        # workers that share nothing but what they are given: each its own working
        # directory (and temporary directory), the environment ``worker_env`` adds
        self._worker_env = dict(worker_env or {})
        self._separate_dirs = separate_dirs
        try:
            self._launch(n_workers, memory_limit)
        except BaseException:
            self.stop()  # what started is stopped, whatever failed
            raise

    def _launch(self, n_workers: int, memory_limit: str) -> None:
        sched_file = self.tmp / "scheduler.json"
        self._start("scheduler", [DASK, "scheduler", "--host", "127.0.0.1", "--port", "0",
                                  "--no-dashboard", "--scheduler-file", str(sched_file)])
        self.address = self._wait_address(sched_file)
        for k in range(n_workers):
            cwd = None
            env = {**os.environ, **self._worker_env}
            if self._separate_dirs:
                cwd = self.tmp / f"w{k}-home"
                cwd.mkdir(exist_ok=True)
                env.update(TMPDIR=str(cwd), HOME=str(cwd))
            cmd = [DASK, "worker", self.address, "--host", "127.0.0.1", "--nthreads", "1",
                   "--memory-limit", memory_limit, "--no-nanny", "--no-dashboard",
                   "--name", f"w{k}"] + (["--local-directory", str(cwd)] if cwd else [])
            self._start(f"worker{k}", cmd, cwd=cwd, env=env)
        self.wait_for_workers(n_workers)

    def worker_dirs(self) -> list[Path]:
        """Each worker's own directory (with ``separate_dirs``)."""
        return sorted(self.tmp.glob("w*-home"))

    def _start(self, name, cmd, cwd=None, env=None):
        log = open(self.tmp / f"{name}.log", "w")
        self._logs.append(log)
        self.procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                            start_new_session=True, cwd=cwd, env=env)

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
        from distributed import Client  # distributed: ~0.5 s, only for a cluster test

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
        scheduler = [self.procs["scheduler"]] if "scheduler" in self.procs else []
        for group in (workers, scheduler):
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
        for log in self._logs:
            log.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
        return False


def clustered_spectrum(seed: int, top: float, blocks: int = 100, size: int = 20,
                       low: float = 0.9, high: float = 0.99):
    """A nonnegative block-diagonal N with zero diagonal whose spectrum crowds the top:
    every block's Perron root is drawn from [low, high] but one, which is ``top``.

    The spectrum that fools power iteration (its estimate creeps up from below): with
    the defaults, 30 steps read 0.99 for a radius of 1.02. ``T = I + N`` is then a
    transport with F = diag(T) = I and M = I - T F^-1 = -N.

    Returns
    -------
    N : scipy.sparse.csr_array, shape (blocks * size, blocks * size)
    rho : float, its spectral radius (max(top, the others))
    """

    rng = np.random.default_rng(seed)
    radii = rng.uniform(low, high, blocks)
    radii[rng.integers(blocks)] = top
    parts = []
    for r in radii:
        B = rng.uniform(0, 1, (size, size))
        np.fill_diagonal(B, 0)
        parts.append(B * (r / max(abs(np.linalg.eigvals(B)))))
    return sp.csr_array(sp.block_diag(parts)), float(radii.max())



class S3Server:
    """moto's S3-compatible server (``moto[server]``) as a process of its own on
    127.0.0.1, with one bucket; stopped by its PID.

    Parameters
    ----------
    tmp : Path, a directory for its log
    bucket : str

    Attributes
    ----------
    endpoint : str, ``http://127.0.0.1:PORT``
    env : dict, the environment a client (bigT, a dask worker) needs to reach it:
        ``AWS_ENDPOINT_URL``, test credentials, a region.
    """

    def __init__(self, tmp: Path, bucket: str = "bigt-test"):
        import socket

        self.bucket = bucket
        with socket.socket() as s:  # a free port on loopback, never another address
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        self.endpoint = f"http://127.0.0.1:{port}"
        self._log = open(Path(tmp) / "moto.log", "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1",
                                      "-p", str(port)], stdout=self._log,
                                     stderr=subprocess.STDOUT, start_new_session=True)
        try:
            self._wait(port)
            self.create_bucket(bucket)
        except BaseException:
            self.stop()
            raise
        # NO_PROXY: a proxy in the environment never carries the requests elsewhere
        self.env = {"AWS_ENDPOINT_URL": self.endpoint, "AWS_ACCESS_KEY_ID": "testing",
                    "AWS_SECRET_ACCESS_KEY": "testing", "AWS_REGION": "us-east-1",
                    "AWS_DEFAULT_REGION": "us-east-1", "NO_PROXY": "127.0.0.1,localhost",
                    "no_proxy": "127.0.0.1,localhost"}

    def _wait(self, port: int, timeout: float = 60) -> None:
        import socket

        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            if self.proc.poll() is not None:
                raise RuntimeError("moto server exited")
            try:
                socket.create_connection(("127.0.0.1", port), 0.2).close()
                return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError("moto server did not start")

    def create_bucket(self, name: str) -> None:
        import urllib.request

        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # no proxy
        opener.open(urllib.request.Request(f"{self.endpoint}/{name}", method="PUT"),
                    timeout=30).close()

    def url(self, key: str) -> str:
        """``s3://BUCKET/key``."""
        return f"s3://{self.bucket}/{key.lstrip('/')}"

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after a few seconds, by PID."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=10)
        self._log.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
