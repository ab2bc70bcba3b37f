"""The process's one pool of worker threads for nogil kernels.

Every numba kernel releases the GIL, so bigT splits a product's rows over threads. All
of them (the CSR kernels, the resident products of compensation, the pixel
reordering) share this pool instead of each keeping its own: one set of threads per
process for each thread count asked for (a call asking for n threads never runs more
than n of its tasks at once, however many it submits). Tasks submitted here must not
wait on other tasks of the pool (they are kernels, not drivers), so sharing it cannot
deadlock. The schedule layer's runner keeps a pool per pass for a different
reason: shutting it down is how a failed pass waits for its running tasks.

The in-memory engine's few other threads (reading T's tile rows, making M, writing a
term's stores, the term computed ahead) come from :func:`shared_pool`, one pool per
name and thread count, kept for the process like the kernels' pool: a small run would
otherwise start a handful of threads each time (issue #30, ~3 ms a thread under load).
The same rule holds per name: a task of pool ``name`` never waits on another task of
pool ``name`` (it may wait on another pool's). :func:`map_all` waits for every task it
submitted, as leaving a ``with ThreadPoolExecutor`` block did.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor, wait

from .. import config
from ..errors import BigTError
from ..pools import named_pool


def thread_count(n_threads: int | None = None) -> int:
    """Threads a kernel call uses: ``n_threads``, else ``config.KERNEL_THREADS``, else
    one per core. BigTError below 1."""
    if n_threads is None:
        n_threads = config.KERNEL_THREADS
    if n_threads is None:
        n_threads = os.cpu_count() or 1
    n_threads = int(n_threads)
    if n_threads < 1:
        raise BigTError(f"n_threads must be >= 1, got {n_threads}")
    return n_threads


def thread_pool(n: int) -> ThreadPoolExecutor:
    """The kernels' shared pool of ``n`` threads (:func:`shared_pool` ``"kernel"``)."""
    return shared_pool("kernel", n)


def shared_pool(name: str, n: int) -> ThreadPoolExecutor:
    """The process's pool ``name`` of ``n`` threads (threads ``bigT-{name}_i``), made on
    first use and kept (:func:`bigT.pools.named_pool`): its threads start once per
    process, not once per call. A task submitted to it must not wait on another task
    of the same pool."""
    return named_pool(name, n)


def map_all(pool: ThreadPoolExecutor, func, items) -> list:
    """``func(item)`` for each item on ``pool``, the results in order. Every task has
    finished when it returns or raises (the first error in item order): a caller
    that fails cleans up after no task still running, as when it left a pool of its
    own, ``with ThreadPoolExecutor(...)``, which waited for them."""
    futures = [pool.submit(func, item) for item in items]
    wait(futures)
    return [f.result() for f in futures]


def run_on_threads(func, ranges, n_threads: int) -> list:
    """``func(a, b)`` for each range ``(a, b)``, at most ``n_threads`` at once on the
    shared pool (in the calling thread when one suffices); the results in range order.
    """
    if n_threads == 1 or len(ranges) <= 1:
        return [func(a, b) for a, b in ranges]
    futures = [thread_pool(n_threads).submit(func, a, b) for a, b in ranges]
    return [f.result() for f in futures]
