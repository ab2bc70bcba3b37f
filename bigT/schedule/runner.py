"""One scheduler choice for every pass: dask's local threaded scheduler (default), or
a ``dask.distributed`` cluster (``Client``, a scheduler address, or ``local:N`` for a
``LocalCluster`` of N worker processes started and stopped here).

Both runners take a :class:`~.spec.PassSpec`, its row blocks and the pass's shared
vectors, run :func:`~.worker.run_block` once per block and return the
:class:`~.spec.BlockStats` in block order.

On a cluster a worker may die at any moment of a pass, and the run goes on:

* the shared vectors travel as the results of tasks (:func:`_shared_value`), not by
  ``Client.scatter``: the scheduler holds each task, so a vector lost with the worker
  that held it is made again elsewhere, and workers fetch it as their tasks need it.
  (A broadcast scatter to a worker that dies mid-transfer raised "Stream is closed" or
  left the scheduler retrying the dead worker's address for ever.)
* the tasks are submitted with ``Client.map``; a task lost with its worker, or a result
  lost before it was gathered, is rerun by the scheduler, which is harmless because
  row writes are idempotent;
* the per-worker calls (memory plans, path checks, the end of a pass) go to the
  workers alive at that moment (:meth:`ClusterRunner._on_live_workers`): a worker that
  dies before it answers is left out, and one that joins later plans on its first task.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import re
import time
import uuid
from concurrent.futures import ThreadPoolExecutor

from .. import config
from ..errors import BigTError, SchedulerError, StoreError
from ..progress import progress_bar
from ._backend import ObjectPath, as_location, is_url
from .costs import CostLedger
from .memory import MemoryPlan, peak_resident_bytes, plan_memory
from .spec import BlockStats, MemoryPolicy, PassSpec, RowBlock
from .worker import (STATE, end_pass, forget_tile_rows, plan_on_worker, run_block,
                     run_mapped_block, tile_row_keeper)


def _bar(progress: bool, total: int, desc: str):
    # delay: passes shorter than a second draw no bar
    return progress_bar(progress=progress, total=total, desc=desc, unit="block", delay=1.0)


class ThreadRunner:
    """Tasks on ``workers`` threads of this process (dask's threaded scheduler).
    ``costs`` records what each pass's tasks cost (:class:`~.costs.CostLedger`)."""

    def __init__(self, workers: int = 2):
        self.workers = max(1, int(workers))
        self.costs = CostLedger()

    @property
    def threads(self) -> int:
        return self.workers

    @property
    def idle_kernel_threads(self) -> int:
        """Threads one product may use when there are fewer row blocks than threads."""
        return self.workers

    def describe(self) -> str:
        return f"local threads ({self.workers})"

    def plans(self, policy: MemoryPolicy) -> dict[str, MemoryPlan]:
        """This process's plan, made now from what it holds now."""
        plan = plan_memory(policy.limit, self.workers, policy.n_cols, policy.max_row_nnz)
        STATE.install_plan(policy, plan)
        return {"local": plan}

    def check_paths(self, paths) -> None:
        """Nothing to check: the tasks run here."""

    def tile_row_keeper(self, T_path: str, policy: MemoryPolicy):
        """``keep(i, row)`` for T's tile rows read in this process before any pass,
        which the tasks, running here, then find (:func:`.worker.tile_row_keeper`)."""
        return tile_row_keeper(T_path, policy)

    def forget_kept_tile_rows(self, T_path: str) -> None:
        """Let go of what :meth:`tile_row_keeper` kept (:func:`.worker.forget_tile_rows`)."""
        forget_tile_rows(T_path)

    def map(self, spec: PassSpec, blocks: list[RowBlock], shared: dict, *,
            progress: bool = False, desc: str = "") -> list[BlockStats]:
        # dask: ~0.3 s of imports, paid only by a run that schedules a pass
        import dask
        import dask.threaded
        from dask.callbacks import Callback

        began = time.perf_counter()
        call = dask.delayed(run_block, pure=False)
        # the pass's spec and shared arrays as one node each, not traversed: dask would
        # walk the spec's fields and the dict again for every task (~0.2 ms a task, ~1 s
        # of a full-HD run's 20 passes of 254 blocks)
        named = f"{spec.op}-{spec.pass_id}"
        spec_node = dask.delayed(spec, name=f"spec-{named}", traverse=False)
        shared_node = dask.delayed(shared, name=f"shared-{named}", traverse=False)
        inputs = (spec_node.key, shared_node.key)  # not tasks: the bar counts blocks
        tasks = [call(spec_node, b, shared_node,
                      dask_key_name=f"{named}-{b.index}") for b in blocks]
        pool = ThreadPoolExecutor(self.workers, thread_name_prefix="bigT-task")
        try:
            with (_bar(progress, len(tasks), desc or spec.op) as bar,
                  Callback(posttask=lambda key, *_: bar.update(int(key not in inputs)))):
                # the threaded scheduler's own function: a scheduler named by string
                # makes dask import distributed (0.25 s) to look for a client first
                stats = list(dask.compute(*tasks, scheduler=dask.threaded.get, pool=pool))
        finally:
            # dask raises at a task's first failure while the others still run: they
            # finish (or are cancelled) before the caller goes on, so no thread of a
            # failed run writes into a store the caller may clean or resume
            pool.shutdown(wait=True, cancel_futures=True)
        self.costs.record(spec.op, began, stats, shared, self.workers)
        return stats

    def end_pass(self, pass_id: str | None = None, forget=()) -> None:
        """Let go of a pass's shared items (all when None) and of cached rows of the
        stores under ``forget`` (:func:`~.worker.end_pass`)."""
        end_pass(pass_id, tuple(str(p) for p in forget))

    def peak_memory(self) -> dict[str, int]:
        """Peak resident bytes of the process running the tasks (this one)."""
        return {"local": peak_resident_bytes()}

    def close(self) -> None:
        end_pass()


class ClusterRunner:
    """Tasks on the workers of a ``distributed.Client``.

    Parameters
    ----------
    client : distributed.Client
    owned : list
        Objects to close with the runner (a client and cluster made here).

    ``costs`` records what each pass's tasks cost (:class:`~.costs.CostLedger`).
    """

    def __init__(self, client, owned=()):
        self.client = client
        self.owned = list(owned)
        self.costs = CostLedger()

    def _workers(self) -> dict:
        return self.client.scheduler_info(n_workers=-1)["workers"]

    @property
    def threads(self) -> int:
        return max(1, sum(int(w.get("nthreads", 1)) for w in self._workers().values()))

    @property
    def idle_kernel_threads(self) -> int:
        return 1

    def describe(self) -> str:
        try:
            workers = self._workers()
        except Exception:  # gone at the end of a run: the report says what it can
            return f"dask cluster {self.client.scheduler.address}"
        text = (f"dask cluster {self.client.scheduler.address}: {len(workers)} workers, "
                f"{self.threads} threads")
        link = getattr(self.client, "dashboard_link", None)
        return text + (f", dashboard {link}" if link and self._has_dashboard() else "")

    def _has_dashboard(self) -> bool:
        try:
            return bool(self.client.run_on_scheduler(_serves_dashboard))
        except Exception:  # an old scheduler or no permission: say nothing
            return False

    def plans(self, policy: MemoryPolicy) -> dict[str, MemoryPlan]:
        """Each live worker's plan, made on the worker from its own limit and threads."""
        return self._on_live_workers(plan_on_worker, policy)

    def tile_row_keeper(self, T_path: str, policy: MemoryPolicy):
        """None: the workers are other processes, which read T themselves."""
        return None

    def forget_kept_tile_rows(self, T_path: str) -> None:
        """Nothing kept (:meth:`tile_row_keeper`)."""

    def check_paths(self, paths) -> None:
        """SchedulerError unless every live worker sees every path (a shared
        filesystem)."""
        paths = [as_location(p) if is_url(p) else os.fspath(p) for p in paths]
        for p in paths:
            if isinstance(p, ObjectPath) and p.base.startswith("memory"):
                raise SchedulerError(f"{p} lives in this process's memory: worker processes "
                                     "cannot reach it (use s3://, gs://, az:// or a shared "
                                     "directory)")
        seen = self._on_live_workers(_missing_paths, paths)
        for address, missing in sorted(seen.items()):
            if missing:
                where = ("the bucket (check its credentials and AWS_ENDPOINT_URL in the "
                         "workers' environment)" if is_url(missing[0]) else
                         "a directory at the same path on every worker (a shared "
                         "filesystem)")
                raise SchedulerError(f"worker {address} cannot see {missing[0]}: bigT's "
                                     f"workers open the stores themselves, from {where}")

    def map(self, spec: PassSpec, blocks: list[RowBlock], shared: dict, *,
            progress: bool = False, desc: str = "") -> list[BlockStats]:
        from distributed import as_completed  # distributed: ~0.5 s, only with a cluster

        began = time.perf_counter()
        keys = [f"{spec.op}-{spec.pass_id}-{b.index}" for b in blocks]
        futures, held, results = [], {}, []
        try:
            held = self._hold_shared(spec, shared)
            futures = self.client.map(run_mapped_block, blocks, spec=spec, shared=held,
                                      key=keys, pure=False, retries=0)
            with _bar(progress, len(futures), desc or spec.op) as bar:
                for fut in as_completed(futures):
                    results.append(fut.result())
                    bar.update(1)
        except BaseException as exc:
            self.client.cancel([*futures, *held.values()])
            raise _cluster_error(exc, spec) from None
        finally:
            del futures, held
        results.sort(key=lambda s: s.index)
        self.costs.record(spec.op, began, results, shared, self.threads)
        return results

    def _hold_shared(self, spec: PassSpec, shared: dict) -> dict:
        """The pass's shared vectors as futures of tasks that return them (see the
        module's docstring: a task is made again when its worker dies, scattered data
        is not)."""
        import dask  # loaded with distributed already: a cluster runner has a client

        with dask.config.set({"distributed.admin.large-graph-warning-threshold": "2GiB"}):
            # the vectors are the graph's payload by design (n floats each): no warning
            return {name: self.client.submit(_shared_value, value, key=f"shared-{name}-"
                                             f"{spec.pass_id}", pure=False, retries=0)
                    for name, value in shared.items()}

    def _on_live_workers(self, function, *args) -> dict:
        """``function(*args)`` on every worker alive now (``Client.run``): {address:
        answer}. A worker that dies before it answers is left out; SchedulerError when
        none answers within ``config.SCHEDULER_CONNECT_SECONDS``; what the function
        itself raises is raised."""
        deadline = time.monotonic() + config.SCHEDULER_CONNECT_SECONDS
        while True:
            answers = self.client.run(function, *args, on_error="return")
            alive = {addr: a for addr, a in answers.items() if not _worker_lost(a)}
            for answer in alive.values():
                if isinstance(answer, BaseException):
                    raise answer
            if alive:
                return alive
            if time.monotonic() > deadline:
                raise SchedulerError(f"no dask worker answered {function.__name__} "
                                     f"within {config.SCHEDULER_CONNECT_SECONDS} s (the "
                                     "cluster has no live worker)")
            time.sleep(0.5)  # a worker died and its replacement is on its way

    def end_pass(self, pass_id: str | None = None, forget=()) -> None:
        """As :meth:`ThreadRunner.end_pass`, on every worker alive (what a dead worker
        held went with it)."""
        self.client.run(end_pass, pass_id, tuple(str(p) for p in forget), on_error="ignore")

    def peak_memory(self) -> dict[str, int]:
        """Peak resident bytes of each worker process (empty when they cannot be
        asked any more: the figure is for the report, not worth failing a run)."""
        try:
            return self.client.run(peak_resident_bytes, on_error="ignore")
        except Exception:
            return {}

    def close(self) -> None:
        for obj in reversed(self.owned):
            obj.close()


def _serves_dashboard(dask_scheduler=None) -> bool:
    """Whether the scheduler serves distributed's dashboard (its HTTP server runs
    without bokeh too, but shows no dashboard then)."""
    return ("dashboard" in (getattr(dask_scheduler, "services", None) or {})
            and importlib.util.find_spec("bokeh") is not None)


def _shared_value(value):
    """A pass's shared vector, as a task's result (:meth:`ClusterRunner._hold_shared`)."""
    return value


def _worker_lost(answer) -> bool:
    """Whether ``Client.run``'s answer from a worker says the worker could not be
    reached (it died, or is dying): a connection error, not the function's own."""
    return isinstance(answer, OSError)  # distributed's CommClosedError is an OSError


def _missing_paths(paths) -> list[str]:
    """The paths (URLs) of ``paths`` this worker cannot see."""
    missing = []
    for p in paths:
        try:
            seen = p.exists() if isinstance(p, ObjectPath) else os.path.exists(p)
        except Exception:  # no credentials, no route to the server: not seen
            seen = False
        if not seen:
            missing.append(str(p))
    return missing


def _cluster_error(exc: BaseException, spec: PassSpec) -> BaseException:
    """bigT's errors and interrupts as they are; a task that killed its workers (the
    scheduler gave up on it) or any other failure as one line."""
    if isinstance(exc, (BigTError, KeyboardInterrupt)):
        return exc
    name = type(exc).__name__
    if name == "KilledWorker":
        return SchedulerError(f"{spec.op} (term {spec.term}): workers died running the same "
                              "task several times (out of memory? see the workers' logs); "
                              "finished rows are kept, rerun to resume")
    return SchedulerError(f"{spec.op} (term {spec.term}) failed on the cluster: {name}: {exc}")


_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


def worker_path(path, what: str = "store"):
    """The store ``path`` as the workers will open it: a local path made absolute
    (each worker resolves it against the same shared filesystem), a URL of object
    storage as its :class:`~bigT.storage.ObjectPath` (each worker opens the bucket
    with its own credentials). StoreError for an in-memory store or a URL scheme
    bigT does not serve."""
    if isinstance(path, ObjectPath):
        return path
    if not isinstance(path, (str, os.PathLike)):
        raise StoreError(f"the {what} must be a directory, or a URL of object storage, "
                         f"that every worker can reach, got a {type(path).__name__} "
                         "(in-memory stores cannot be shared between processes)")
    text = os.fspath(path)
    if _URL.match(text):
        return as_location(text)  # a scheme bigT does not serve is refused, by name
    return os.path.abspath(text)


def open_runner(scheduler=None, *, workers: int = 2, memory_limit: int | None = None):
    """The runner for ``scheduler``.

    Parameters
    ----------
    scheduler : None, "threads", "local:N", an address ("tcp://host:port") or a
        ``distributed.Client``
    workers : int, threads of the local threaded scheduler
    memory_limit : int, optional
        With ``local:N``: the memory of the N workers together (each gets 1/N).

    Raises
    ------
    SchedulerError
        Unreachable address, bad ``local:N``.
    """
    if scheduler is None or scheduler == "threads":
        return ThreadRunner(workers)
    if not isinstance(scheduler, str):
        return ClusterRunner(scheduler)
    m = re.fullmatch(r"local:(\d+)", scheduler.strip())
    if m:
        return _local_cluster(int(m.group(1)), memory_limit)
    return _connect(scheduler.strip())


def _local_cluster(n: int, memory_limit: int | None) -> ClusterRunner:
    if n < 1:
        raise SchedulerError("{option}: need at least one worker process",
                             option=("scheduler", f"local:{n}"))
    from distributed import Client, LocalCluster  # ~0.5 s, only for a cluster

    per_worker = "auto" if memory_limit is None else max(1, int(memory_limit) // n)
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           memory_limit=per_worker, dashboard_address=_dashboard(),
                           silence_logs=logging.ERROR, host="127.0.0.1")
    client = Client(cluster)
    return ClusterRunner(client, owned=[cluster, client])


def _dashboard() -> str:
    """A free port on 127.0.0.1 for the scheduler's HTTP server (and dashboard, with
    bokeh): never a fixed port another cluster may hold."""
    return "127.0.0.1:0"


def _connect(address: str) -> ClusterRunner:
    from distributed import Client  # ~0.5 s, only for a cluster

    try:
        client = Client(address, timeout=config.SCHEDULER_CONNECT_SECONDS)
    except (OSError, TimeoutError, ValueError) as exc:
        raise SchedulerError(f"cannot reach the dask scheduler at {address} "
                             f"({type(exc).__name__}: {exc})") from None
    return ClusterRunner(client, owned=[client])


def new_pass_id() -> str:
    return uuid.uuid4().hex[:12]
