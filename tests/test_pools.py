"""bigT.pools: one pool per name and thread count for the process; ``started`` pools
have every thread running when they are handed out."""

import threading

from bigT.pools import named_pool


def _threads_named(prefix: str) -> int:
    return sum(t.name.startswith(prefix) for t in threading.enumerate())


def test_a_started_pool_has_all_its_threads_at_once_and_is_kept():
    pool = named_pool("test-started", 3, started=True)
    assert _threads_named("bigT-test-started") == 3
    assert named_pool("test-started", 3, started=True) is pool
    assert [pool.submit(pow, 2, k).result() for k in range(4)] == [1, 2, 4, 8]
    assert _threads_named("bigT-test-started") == 3  # no thread started for the tasks


def test_a_lazy_pool_starts_threads_as_tasks_come():
    pool = named_pool("test-lazy", 2)
    assert _threads_named("bigT-test-lazy") == 0
    assert pool.submit(abs, -1).result() == 1
    assert _threads_named("bigT-test-lazy") >= 1
    assert named_pool("test-lazy", 2) is pool and named_pool("test-lazy", 3) is not pool
