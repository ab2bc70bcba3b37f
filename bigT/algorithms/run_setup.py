"""Setting up one run of the engine, or resuming one: where the tasks read T, the first
bounce F, each process's memory plan, the inverse store opened under the run's
fingerprint, and the term stores' tile size (chosen by the run that made the store,
recorded, kept on resume so that a resumed run cuts the same row blocks).

What :func:`open_run` returns, a :class:`RunLayout`, is fixed for the whole run: every
other piece of the engine reads it. In memory, T is read once (:class:`TileRows`): its
diagonal, for F, comes from the same tile rows M is made from.
"""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass

import numpy as np

from .. import config
from ..kernels.threads import map_all, shared_pool
from ..schedule.memory import MemoryPlan
from ..schedule.runner import ClusterRunner, worker_path
from ..schedule.spec import MemoryPolicy
from ..storage import BlockCSR, InverseStore
from .fingerprint import inverse_fingerprint
from .engine_path import PathChoice, choose_path
from .first_bounce import FirstBounce, first_bounce_of_rows
from .methods import SeriesMethod
from .records import SeriesRecord
from .settings import SeriesSettings


class TileRows:
    """T's tile rows read whole, once, for the in-memory path: F's diagonal is taken
    from them (:func:`.first_bounce.first_bounce_of_rows`), then M is made from them
    (:class:`.resident.ResidentMatrices`), each row let go of as its rows of M are made
    (:meth:`take`), so that T is held whole only until M is.

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
    threads : int
        Tile rows read at once (a read decodes, checks and joins the row's tiles,
        mostly in numpy and numba, which let go of the interpreter).
    keep : bool
        Rows taken stay held (:meth:`take` is then :meth:`__getitem__`): the caller
        multiplies with T after the engine made M from them (the target-error search,
        :mod:`.target`, whose products and every attempt's M so read T once; M is
        made from them without changing them, :func:`bigT.schedule.blocks.m_rows`).
        :meth:`release` lets go of them.

    The rows are read on first use: an error found before (a ``first_bounce`` file
    that does not load) costs no read of T.
    """

    def __init__(self, T: BlockCSR, threads: int, keep: bool = False):
        self.T, self.threads, self.keep = T, max(1, int(threads)), bool(keep)
        self._rows: list | None = None
        self._reading = threading.Lock()  # M's threads may ask first: one read

    def __len__(self) -> int:
        return int(self.T.grid[0])

    def __getitem__(self, i: int):
        """Tile row ``i``, csr_array of shape (rows_i, n), global columns (as
        ``T.get_tile_row(i)``); read again if taken already."""
        row = self._read()[i]
        return self.T.get_tile_row(i) if row is None else row

    def take(self, i: int):
        """Tile row ``i``, no longer held here (unless ``keep``)."""
        row = self[i]
        if not self.keep:
            self._read()[i] = None
        return row

    def release(self) -> None:
        """Let go of every row held (read again on the next use)."""
        with self._reading:
            self._rows = None

    def _read(self) -> list:
        with self._reading:
            if self._rows is None:
                self._rows = map_all(shared_pool("T", self.threads), self.T.get_tile_row,
                                     range(len(self)))
        return self._rows


@dataclass(frozen=True, eq=False)
class RunLayout:
    """What one run fixes before its first product.

    Attributes
    ----------
    T : BlockCSR, shape (n, n)
    T_path : str
        T's path as the workers open it.
    fb : FirstBounce
    policy : MemoryPolicy
        The memory limit and T's widths, from which each process plans.
    plans : dict of str to MemoryPlan
        Each process's plan, by worker address (``"local"`` for a local run).
    tile_size : int
        Tile size of the term stores; their row blocks are the tasks.
    kernel_threads : int
        Threads each task's product kernel may use (1 when the row blocks alone keep
        every runner thread busy).
    created : bool
        This run creates (or overwrites) the store: stopped before its first term is
        finished, the run discards it.
    path : PathChoice
        In memory or out of core (:mod:`.engine_path`), and why.
    T_rows : TileRows or None
        In memory, T's tile rows F was taken from, for M to be made from (then let
        go of); None out of core.
    """

    T: BlockCSR
    T_path: str
    fb: FirstBounce
    policy: MemoryPolicy
    plans: dict[str, MemoryPlan]
    tile_size: int
    kernel_threads: int
    created: bool
    path: PathChoice = PathChoice(False, "out of core")
    T_rows: TileRows | None = None

    @property
    def n(self) -> int:
        return self.T.shape[0]

    @property
    def n_blocks(self) -> int:
        return -(-self.n // self.tile_size)

    @property
    def shared(self) -> dict[str, np.ndarray]:
        """What every task of the series reads beside its stores: F^-1, F (each shape
        (n,), or (n/3, 3, 3) blocks for colour) and the kept values (shape (n,))."""
        return {"finv": self.fb.finv, "f": self.fb.f, "active": self.fb.active}

    def memory_text(self) -> str:
        """The memory plans, one line (the report's ``memory``)."""
        if len(self.plans) == 1:
            return next(iter(self.plans.values())).describe()
        return "; ".join(f"{addr}: {plan.describe()}" for addr, plan in sorted(self.plans.items()))


def open_run(T: BlockCSR, store: InverseStore, series: SeriesMethod, runner, settings: SeriesSettings,
             first_bounce, memory_limit: int | None,
             in_memory: bool | None = False,
             T_rows: TileRows | None = None) -> tuple[RunLayout, SeriesRecord]:
    """The run's layout and the store's record, the store opened (created, or resumed
    when it holds the same fingerprint; its writer lock taken); ``in_memory`` as
    :func:`.engine_path.choose_path`'s; ``T_rows``, T's tile rows a caller holds
    (read or to be read), F's diagonal and, in memory, M are taken from instead of
    reading T again.

    Raises what :func:`.first_bounce.resolve_first_bounce`,
    :meth:`InverseStore.open_or_create` and the runner's path check raise (before
    anything is written where they can).
    """
    T_path = _tasks_path(T, runner, settings.progress)
    channels = int(getattr(T, "channels", 1))  # F's block size (FirstBounce.channels)
    policy = MemoryPolicy(memory_limit, runner.threads, T.shape[1],
                          max_row_nnz(T) * channels)
    plans = runner.plans(policy)
    path = choose_path(in_memory, runner, T, channels, next(iter(plans.values())))
    # in memory, T is read whole for M: F's diagonal is taken from the same rows
    # (a caller's, when it holds them: then out of core too, as they are read anyway)
    if T_rows is None and path.in_memory:
        T_rows = TileRows(T, runner.threads)
    # out of core, the tile rows read for the diagonal are kept for M's rows to be made
    # from (where the tasks run in this process): T is then decoded once before term 1
    keep = runner.tile_row_keeper(T_path, policy) if T_rows is None else None
    fb = first_bounce_of_rows(T, first_bounce, T_rows, keep)
    if not path.in_memory:
        T_rows = None  # the out-of-core tasks read T themselves
    created = not store.path.exists() or settings.overwrite
    params = inverse_fingerprint(T, fb, settings.thresholds, series.name)
    # in memory, the row blocks are only the units written: T's tiles, the fewest files
    # (a resumed run keeps the tile size recorded, on either path)
    ts = (int(T.tile_size) if path.in_memory
          else choose_tile_size(T.shape[0], T.tile_size, runner.threads, fb.channels))

    def chosen(stored):  # a new store: its tile size recorded in its first record
        return SeriesRecord.from_stored(stored, store.path).replace(
            tile_size=ts, excluded_pixels=fb.excluded).to_stored()

    record = SeriesRecord.from_stored(
        store.open_or_create(params, overwrite=settings.overwrite, fresh=chosen),
        store.path)
    runner.check_paths([str(store.path)])
    if record.tile_size is None:  # a record saved without one (a run killed before)
        record = record.replace(tile_size=ts, excluded_pixels=fb.excluded)
        store.save(record.to_stored())
    if keep is not None and record.tile_size != T.tile_size:
        # the row blocks are not T's tile rows: no pass would take the rows kept
        runner.forget_kept_tile_rows(T_path)
    n_blocks = -(-T.shape[0] // record.tile_size)
    kernel_threads = 1 if n_blocks >= runner.threads else runner.idle_kernel_threads
    return RunLayout(T, T_path, fb, policy, plans, record.tile_size, kernel_threads,
                     created, path, T_rows), record


def _tasks_path(T, runner, progress: bool) -> str:
    """T's path as the workers will open it, checked on every worker."""
    T_path = worker_path(T.path, "transport T")
    runner.check_paths([T_path])
    if progress and isinstance(runner, ClusterRunner):
        # a cluster run may be long: where to watch it (the dashboard) comes first
        print(f"bigT: running on {runner.describe()}", file=sys.stderr)
    return T_path


def choose_tile_size(n: int, tile_size: int, threads: int, channels: int = 1) -> int:
    """T's tile size, halved while it gives fewer than ``config.TASKS_PER_THREAD`` row
    blocks per thread, halving adds blocks, and blocks keep at least
    ``config.MIN_BLOCK_ROWS`` rows and a multiple of ``channels`` (a colour pixel's 3
    rows in one row block, where its 3x3 block of F^-1 mixes them)."""
    ts = int(tile_size)
    while (-(-n // ts) < config.TASKS_PER_THREAD * threads and ts // 2 >= config.MIN_BLOCK_ROWS
           and (ts // 2) % channels == 0 and -(-n // (ts // 2)) > -(-n // ts)):
        ts //= 2
    return ts


def max_row_nnz(T) -> int:
    """Entries of T's widest tile row (a tile row of M holds up to ``channels`` times
    as many: the caller scales it)."""
    indptr = np.asarray(T.tile_indptr)
    tile_nnz = np.append(np.asarray(T.tile_nnz, dtype=np.int64), 0)
    row_nnz = np.add.reduceat(tile_nnz, indptr[:-1]) * (np.diff(indptr) > 0)
    return int(row_nnz.max(initial=0))
