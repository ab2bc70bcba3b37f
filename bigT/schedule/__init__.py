"""bigT.schedule: where and how the engine's tasks run.

* :mod:`.spec` — the frozen records a task receives and returns (``PassSpec``,
  ``RowBlock``, ``BlockStats``, ``MemoryPolicy``);
* :mod:`.worker` — what runs in any process that executes tasks (open stores, the
  tile cache, memory plans, ``TaskContext``, ``run_block``);
* :mod:`.runner` — the scheduler choice (local threads, a dask cluster);
* :mod:`.stream` — a store streamed against dense batches (compensation, probes);
* :mod:`.operators`, :mod:`.blocks`, :mod:`.matvec` — the row-block products and
  mat-vecs; :mod:`.memory` — the memory plan; :mod:`.cache` — the tile cache.

The contract is in docs/CONTRACTS.md ("schedule").
"""
