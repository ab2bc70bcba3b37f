"""One scheduler choice for every pass: dask's local threaded scheduler (default), or
a ``dask.distributed`` cluster (``Client``, a scheduler address, or ``local:N`` for a
``LocalCluster`` of N worker processes started and stopped here).

Both runners take a :class:`~.spec.PassSpec`, its row blocks and the pass's shared
vectors, run :func:`~.worker.run_block` once per block and return the
:class:`~.spec.BlockStats` in block order. On a cluster the shared vectors are
scattered to every worker once per pass, tasks are submitted with ``Client.map`` and a
progress bar in the caller follows ``as_completed``; a task lost with its worker is
rerun by the scheduler, which is harmless because row writes are idempotent.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import re
import uuid
from concurrent.futures import ThreadPoolExecutor

from .. import config
from ..errors import BigTError, SchedulerError, StoreError
from ..progress import progress_bar
from .memory import MemoryPlan, peak_resident_bytes, plan_memory
from .spec import BlockStats, MemoryPolicy, PassSpec, RowBlock
from .worker import STATE, end_pass, plan_on_worker, run_block, run_mapped_block


def _bar(progress: bool, total: int, desc: str):
    # delay: passes shorter than a second draw no bar
    return progress_bar(progress=progress, total=total, desc=desc, unit="block", delay=1.0)


class ThreadRunner:
    """Tasks on ``workers`` threads of this process (dask's threaded scheduler)."""

    def __init__(self, workers: int = 2):
        self.workers = max(1, int(workers))

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

    def map(self, spec: PassSpec, blocks: list[RowBlock], shared: dict, *,
            progress: bool = False, desc: str = "") -> list[BlockStats]:
        # dask: ~0.3 s of imports, paid only by a run that schedules a pass
        import dask
        import dask.threaded
        from dask.callbacks import Callback

        call = dask.delayed(run_block, pure=False)
        tasks = [call(spec, b, shared, dask_key_name=f"{spec.op}-{spec.pass_id}-{b.index}")
                 for b in blocks]
        pool = ThreadPoolExecutor(self.workers, thread_name_prefix="bigT-task")
        try:
            with (_bar(progress, len(tasks), desc or spec.op) as bar,
                  Callback(posttask=lambda *_: bar.update(1))):  # a task finished
                # the threaded scheduler's own function: a scheduler named by string
                # makes dask import distributed (0.25 s) to look for a client first
                return list(dask.compute(*tasks, scheduler=dask.threaded.get, pool=pool))
        finally:
            # dask raises at a task's first failure while the others still run: they
            # finish (or are cancelled) before the caller goes on, so no thread of a
            # failed run writes into a store the caller may clean or resume
            pool.shutdown(wait=True, cancel_futures=True)

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
    """

    def __init__(self, client, owned=()):
        self.client = client
        self.owned = list(owned)

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
        """Each worker's plan, made on the worker from its own limit and threads."""
        return self.client.run(plan_on_worker, policy)

    def check_paths(self, paths) -> None:
        """SchedulerError unless every worker sees every path (a shared filesystem)."""
        seen = self.client.run(_missing_paths, [os.fspath(p) for p in paths])
        for address, missing in sorted(seen.items()):
            if missing:
                raise SchedulerError(
                    f"worker {address} cannot see {missing[0]}: bigT's workers open the "
                    "stores by path, which must be the same on every worker (a shared "
                    "filesystem)")

    def map(self, spec: PassSpec, blocks: list[RowBlock], shared: dict, *,
            progress: bool = False, desc: str = "") -> list[BlockStats]:
        from distributed import as_completed  # distributed: ~0.5 s, only with a cluster

        keys = [f"{spec.op}-{spec.pass_id}-{b.index}" for b in blocks]
        futures, scattered, results = [], {}, []
        try:
            scattered = {k: self.client.scatter(v, broadcast=True, hash=False)
                         for k, v in shared.items()}
            futures = self.client.map(run_mapped_block, blocks, spec=spec, shared=scattered,
                                      key=keys, pure=False, retries=0)
            with _bar(progress, len(futures), desc or spec.op) as bar:
                for fut in as_completed(futures):
                    results.append(fut.result())
                    bar.update(1)
        except BaseException as exc:
            self.client.cancel(futures)
            raise _cluster_error(exc, spec) from None
        finally:
            del futures, scattered
        return sorted(results, key=lambda s: s.index)

    def end_pass(self, pass_id: str | None = None, forget=()) -> None:
        """As :meth:`ThreadRunner.end_pass`, on every worker."""
        self.client.run(end_pass, pass_id, tuple(str(p) for p in forget))

    def peak_memory(self) -> dict[str, int]:
        """Peak resident bytes of each worker process (empty when they cannot be
        asked any more: the figure is for the report, not worth failing a run)."""
        try:
            return self.client.run(peak_resident_bytes)
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


def _missing_paths(paths) -> list[str]:
    return [p for p in paths if not os.path.exists(p)]


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


def local_path(path, what: str = "store") -> str:
    """``path`` made absolute (workers resolve it themselves); StoreError for a URL
    or an in-memory store, which worker processes cannot open."""
    if not isinstance(path, (str, os.PathLike)):
        raise StoreError(f"the {what} must be a directory on a filesystem every worker can "
                         f"reach, got a {type(path).__name__} (in-memory stores cannot be "
                         "shared between processes)")
    text = os.fspath(path)
    if _URL.match(text):
        raise StoreError(f"the {what} must be a local directory (bigT's workers open it "
                         "by path); URLs and in-memory stores are not supported", text)
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
