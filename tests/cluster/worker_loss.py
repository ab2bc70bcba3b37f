"""Kill a worker of a :class:`bigT.testing.ProcessCluster` at a chosen moment of a
``bigT invert --scheduler`` run, and put a new worker in its place.

The run is a separate process (the CLI, as a user starts it), so a kill lands at a
moment of the run's own clock, whatever phase it is in: a pass's shared vectors on
their way to the workers, its tasks, their results coming back, or the per-worker
memory plan and path checks between passes.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from bigT.testing import DASK, ProcessCluster


@dataclass(frozen=True)
class KilledRun:
    """One run with a worker killed ``delay`` seconds after it started.

    Attributes
    ----------
    delay : float, seconds from the run's start to the kill
    killed : bool, whether the run was still going when the kill came
    returncode : int, the CLI's exit status
    seconds : float, the run's wall time
    output : str, what the CLI printed (stdout and stderr together)
    """

    delay: float
    killed: bool
    returncode: int
    seconds: float
    output: str


def invert_command(scene_path: Path, out: Path, address: str, terms: int) -> list[str]:
    return [sys.executable, "-m", "bigT.cli", "invert", str(scene_path), "-o", str(out),
            "--terms", str(terms), "--scheduler", address, "--no-progress"]


def run_with_kill(cluster: ProcessCluster, command: list[str], delay: float | None,
                  victim: str = "worker1", timeout: float = 600) -> KilledRun:
    """Run ``command``; ``delay`` seconds after its start SIGKILL ``victim`` (None: no
    kill) and start a new worker under the same name at once, so the cluster has its
    two workers again while the run goes on."""
    env = {**os.environ, "PYTHONPATH": _repo_root()}
    t0 = time.monotonic()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env)
    killed = False
    try:
        if delay is not None:
            try:
                proc.wait(timeout=delay)
            except subprocess.TimeoutExpired:
                kill_worker(cluster, victim)
                killed = True
                replace_worker(cluster, victim)
        output, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:  # a hang: the run is stopped, by its PID
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
    return KilledRun(delay or 0.0, killed, proc.returncode, time.monotonic() - t0, output)


def kill_worker(cluster: ProcessCluster, name: str) -> None:
    proc = cluster.procs[name]
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)  # reaped: no zombie left behind


def replace_worker(cluster: ProcessCluster, name: str) -> None:
    """A new ``dask worker`` named as the dead one, started as the cluster starts its
    own and recorded in ``cluster.procs``, so ``cluster.stop()`` stops it by PID."""
    log_path = cluster.tmp / f"{name}.log"
    with open(log_path, "a") as log:  # the child keeps its own copy of the descriptor
        cluster.procs[name] = subprocess.Popen(
            [DASK, "worker", cluster.address, "--host", "127.0.0.1", "--nthreads", "1",
             "--memory-limit", "2GiB", "--no-nanny", "--no-dashboard", "--name",
             f"{name}-{time.monotonic_ns()}"],
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def _repo_root() -> str:
    return str(Path(__file__).resolve().parents[2])
