"""A worker lost at any moment of a cluster run changes nothing but the time.

Two kinds of kill on a real cluster (a ``dask scheduler`` and two ``dask worker``
processes on 127.0.0.1, :class:`bigT.testing.ProcessCluster`):

* at a chosen phase of a pass, in-process: while a pass's shared vectors are on their
  way to the workers (a value whose unpickling SIGKILLs worker1: the worker dies
  mid-delivery), and just before the per-worker calls (memory plans and path checks,
  the end of a pass);
* at a chosen moment of ``bigT invert --scheduler`` run as a separate process, a new
  worker started in the dead one's place: a loop over delays spread over the
  undisturbed run's time (ten delays, with ``-m slow``).

Every run must end as the undisturbed one does: exit 0 and the local threaded inverse.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import bigT
from bigT.schedule.runner import ClusterRunner
from bigT.testing import ProcessCluster

sys.path.insert(0, str(Path(__file__).parent))  # the helper next to this file
from worker_loss import invert_command, kill_worker, run_with_kill  # noqa: E402

TERMS = 3  # as the local inverse of conftest.py


def _assert_same_inverse(out, local_inverse):
    np.testing.assert_allclose(bigT.open(out).to_scipy().toarray(), local_inverse,
                               rtol=1e-6, atol=1e-9)


class _KillOnUnpickle:
    """A shared value whose unpickling SIGKILLs process ``pid`` (once: later
    unpickling finds no such process and does nothing). Unpickled where the pass's
    shared vectors arrive, it kills the worker while they are being delivered."""

    def __init__(self, pid: int):
        self.pid = pid

    def __reduce__(self):
        # subprocess.call: importable in every worker, unlike a function of this file
        return (subprocess.call, (["sh", "-c", f"kill -9 {self.pid} 2>/dev/null; true"],))


# the default suite keeps one of each kind; the others run with make test-all
@pytest.mark.parametrize("nth_pass", [1, pytest.param(4, marks=pytest.mark.slow)])
def test_worker_killed_while_shared_vectors_travel(scene, local_inverse, fresh_cluster,
                                                   tmp_path, monkeypatch, nth_pass):
    cluster, passes = fresh_cluster, []
    original = ClusterRunner.map

    def map_with_poison(self, spec, blocks, shared, **kwargs):
        passes.append(spec.op)
        if len(passes) == nth_pass:
            shared = {**shared, "poison": _KillOnUnpickle(cluster.pid("worker1"))}
        return original(self, spec, blocks, shared, **kwargs)

    monkeypatch.setattr(ClusterRunner, "map", map_with_poison)
    out = tmp_path / "X.zarr"
    report = bigT.stratified_inverse(scene.T, out, terms=TERMS, progress=False,
                                     scheduler=cluster.address)
    assert len(passes) > nth_pass
    assert cluster.procs["worker1"].wait(timeout=30) == -9  # it really died, by the kill
    assert report.terms == TERMS
    _assert_same_inverse(out, local_inverse)


@pytest.mark.parametrize("call", ["plans", pytest.param("check_paths", marks=pytest.mark.slow),
                                  pytest.param("end_pass", marks=pytest.mark.slow)])
def test_worker_killed_before_a_per_worker_call(scene, local_inverse, fresh_cluster,
                                                tmp_path, monkeypatch, call):
    cluster, calls = fresh_cluster, []
    original = getattr(ClusterRunner, call)

    def kill_first(self, *args, **kwargs):
        calls.append(call)
        if len(calls) == 1:
            kill_worker(cluster, "worker1")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(ClusterRunner, call, kill_first)
    out = tmp_path / "X.zarr"
    bigT.stratified_inverse(scene.T, out, terms=TERMS, progress=False,
                            scheduler=cluster.address)
    assert calls and cluster.procs["worker1"].poll() == -9
    _assert_same_inverse(out, local_inverse)


@pytest.fixture(scope="module")
def kill_cluster(tmp_path_factory):
    c = ProcessCluster(tmp_path_factory.mktemp("kill-cluster"))
    try:
        yield c
    finally:
        c.stop()


@pytest.fixture(scope="module")
def undisturbed_seconds(scene, local_inverse, kill_cluster, tmp_path_factory):
    """The wall time of the run left alone on warm workers (its result checked), which
    the delays are spread over. A replacement worker starts cold, so the disturbed
    runs take longer and every delay lands inside them."""
    seconds = []
    for k in range(2):  # the first run warms the workers (numba's cached kernels)
        out = tmp_path_factory.mktemp("undisturbed") / "X.zarr"
        run = run_with_kill(kill_cluster, invert_command(scene.path, out,
                                                         kill_cluster.address, TERMS), None)
        assert run.returncode == 0, run.output
        _assert_same_inverse(out, local_inverse)
        seconds.append(run.seconds)
    return seconds[-1]


#: where in the undisturbed run's time the kill lands: all with make test-all (about 20 s
#: even for one, its own cluster and two undisturbed runs included). The default suite
#: kills a worker mid-run in test_cluster.py::test_worker_killed_midway (mid-term, the
#: same inverse) and at the moments of the two tests above, on clusters of their own.
FRACTIONS = [0.05, 0.15, 0.25, 0.35, 0.45, 0.55, 0.65, 0.75, 0.85, 0.95]


@pytest.mark.slow
@pytest.mark.parametrize("fraction", FRACTIONS)
def test_worker_killed_at_a_moment_of_the_cli_run(scene, local_inverse, kill_cluster,
                                                  undisturbed_seconds, tmp_path, fraction):
    out = tmp_path / "X.zarr"
    delay = fraction * undisturbed_seconds
    run = run_with_kill(kill_cluster, invert_command(scene.path, out, kill_cluster.address,
                                                     TERMS), delay)
    # the outcome per delay, for the record (pytest -s, or -rA)
    print(f"kill at {delay:.1f} s of {undisturbed_seconds:.1f} s: killed={run.killed} "
          f"exit {run.returncode}, {run.seconds:.1f} s")
    if not run.killed:
        pytest.skip(f"the run ended in {run.seconds:.1f} s, before the kill at {delay:.1f} s")
    assert run.returncode == 0, run.output[-2000:]
    assert "Traceback" not in run.output
    _assert_same_inverse(out, local_inverse)
    kill_cluster.wait_for_workers(2)  # the replacement has joined before the next delay
