"""Thread pools kept for the life of the process, one per name and thread count.

A pool's threads start once per process, not once per call: a small run would
otherwise start a handful of threads each time (issue #30, ~3 ms a thread under
load). The kernels' pools (:func:`bigT.kernels.threads.shared_pool`) and the fsync
pool of :mod:`bigT.atomic` come from here. A forked child has none of its parent's
threads: its pools are made anew.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

_NAMED: dict[tuple[str, int], ThreadPoolExecutor] = {}
_LOCK = threading.Lock()


def _forget_pools() -> None:
    # a forked child has none of its parent's threads: its pools are made anew
    global _LOCK
    _NAMED.clear()
    _LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools)


def named_pool(name: str, n: int, *, started: bool = False) -> ThreadPoolExecutor:
    """The process's pool ``name`` of ``n`` threads (threads ``bigT-{name}_i``), made on
    first use and kept.

    Parameters
    ----------
    name : str
    n : int, threads (at least 1)
    started : bool
        Start all ``n`` threads when the pool is made (each held at a barrier until
        the last one starts). A pool otherwise starts a thread when a task finds none
        idle, so one started lazily might start another in a later run, which a run
        of the same size should not (tests/algorithms: a second small run starts no
        thread).
    """
    n = max(1, int(n))
    with _LOCK:
        pool = _NAMED.get((name, n))
        if pool is None:
            pool = _NAMED[(name, n)] = ThreadPoolExecutor(n, thread_name_prefix=f"bigT-{name}")
            if started:
                _start_all(pool, n)
        return pool


def _start_all(pool: ThreadPoolExecutor, n: int) -> None:
    barrier = threading.Barrier(n + 1)
    for _ in range(n):
        pool.submit(barrier.wait)
    barrier.wait()
