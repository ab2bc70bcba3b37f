"""A model of ``bigT invert`` on N dask workers, built from what one real run records.

Why here and not in ``bigT``: the model reads a finished run's report and predicts other
runs; nothing in bigT's own runs needs it (the CLI does not choose a cluster size), so
it stays with the benchmarks that check it (``bench_scale.py --cluster-model``).

What one run records (``InverseReport.task_costs`` and each term's ``TermRecord.tasks``,
one :class:`bigT.schedule.costs.TaskCosts` per kind of task): per kind and term the
tasks, their time (summed, and the slowest), the bytes their threads read and wrote and
the calls that took, the right factor read once per process (the pass's broadcast), the
shared vectors sent once a pass, and the largest resident set seen. From it, per row of
T (the scene keeps ~84 entries per row at every size, so work, bytes and requests grow
with the rows: :func:`RecordedRun.from_report`):

* ``c`` compute seconds per row of a pass (the tasks' time, less the recording storage's
  share: their bytes over its bandwidth, their requests times its latency);
* ``r``, ``w``, ``q`` bytes read, bytes written and requests per row (a chunk file read
  takes two read calls, a written one one write call);
* ``H`` bytes of the right factor per row, read whole by every worker once a pass;
* ``V`` bytes of the shared vectors per row, sent to every worker once a pass.

The run at n rows on N workers of ``t`` threads (``m = N t`` task slots), storage S
(bandwidth ``b`` per worker, ``B_all`` for all workers together, latency ``l`` per
request, ``k`` requests in flight per task) and scheduler D (``o`` seconds per task,
serial on the scheduler; ``L`` seconds per pass; ``bw_net`` for the vectors)::

    tiles     = ceil(n / ts), ts = bigT's own choice (choose_tile_size(n, 8192, m))
    b_eff(N)  = min(b, B_all / N)                     # storage shared by N readers
    io(x, y)  = x / b_eff(N) + y * l / k              # x bytes in y requests
    t_task    = c ts + io((r + w) ts, q ts) + e(p) c_M ts + o
    e(p)      = (1 - 1/N)^p                           # M's rows not yet built on this
                                                      # worker at the run's p-th pass
    pass      = L + io(H n, q_H n) + N V n / bw_net
                + max(ceil(tiles / m) t_task, imbalance t_task, tiles o)
    term      = sum of its passes + its publication (measured, per tile row)
    inverse   = spectral radius's passes + sum of the terms

Terms are sequential, and so are a term's passes; the row blocks (tile rows) of a pass
are its parallelism; the scheduler hands out one task at a time (``tiles o``). Every
worker reads the right factor whole at the start of each pass (``H n``): the broadcast,
which does not shrink with N. M's rows are made from T's by the first task of a worker
that needs them and cached there; dask does not send a row block back to the worker
that cached its rows, so at pass p a task finds them cached with probability
1 - (1 - 1/N)^p (random placement) and rebuilds them otherwise (``c_M``: the first
pass's time per row, which built them all).

Memory per worker::

    base + t * task + min(cache budget, M (1 - (1 - 1/N)^P)) + max_k H_k n

``base`` the worker process before its tasks, ``task`` what one task holds beyond the
shared parts (the recorded peak less base, cache and factor, per thread; at the same
tile size), ``M`` M's rows in memory (8 bytes an entry), ``P`` the run's passes, ``H_k``
term k's right factor in memory. Where the factor does not fit the plan's share the
products read it in batches instead, and the model says so (``batched``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

#: Tile size of T's store at full HD and 4K (the scene builder's default).
T_TILE = 8192
#: Bytes of a CSR entry in memory (float32 value, int32 column), as bigT's plan counts.
ENTRY_BYTES = 8
#: Read calls per chunk file read (its bytes, then the end of the file: measured on
#: format-2 stores, where every read of ``_read_at`` is two calls).
READ_CALLS_PER_FILE = 2


@dataclass(frozen=True)
class Storage:
    """Where the stores live, as a reader sees it.

    Attributes
    ----------
    name : str
    bandwidth : float, bytes/s one worker reads or writes
    aggregate : float, bytes/s all workers together (math.inf: no shared limit)
    latency : float, seconds per request (a chunk file: an open and a read, or a GET)
    in_flight : int, requests a task keeps in flight
    source : str, where the numbers come from
    """

    name: str
    bandwidth: float
    aggregate: float
    latency: float
    in_flight: int = 1
    source: str = ""

    def io_seconds(self, nbytes: float, requests: float, readers: int) -> float:
        """Seconds to move ``nbytes`` in ``requests`` while ``readers`` workers do."""
        per_reader = min(self.bandwidth, self.aggregate / max(1, readers))
        return nbytes / per_reader + requests * self.latency / self.in_flight


#: A cluster's shared filesystem (NFS or Lustre over 10 GbE): a client's stream is
#: bounded by its 10 GbE link (~1.1 GB/s), a mid-size server or a few Lustre OSTs give
#: ~10 GB/s in all, and a small file's open and read are ~0.5 ms of round trips.
SHARED_FS = Storage("shared filesystem", 1.1e9, 10e9, 0.5e-3, 1,
                    "10 GbE client link; ~10 GB/s server (a few Lustre OSTs); 0.5 ms "
                    "per file (NFS open + read round trips)")
#: An object store (S3 in the same region): ~90 MB/s per connection, 16 requests in
#: flight per task (what an async client keeps open) bounded by a 25 Gb/s instance
#: link (~3 GB/s); the service scales out (no shared limit at these rates) but each GET
#: waits ~30 ms for its first byte (AWS's guide quotes 100-200 ms tail latency for
#: small objects; 20-40 ms is typical in-region).
OBJECT_STORE = Storage("object store", min(16 * 90e6, 3e9), math.inf, 30e-3, 16,
                       "S3 in-region: ~90 MB/s and ~30 ms first byte per GET, 16 in "
                       "flight per task, 25 Gb/s instance link")


@dataclass(frozen=True)
class Scheduler:
    """What scheduling costs.

    Attributes
    ----------
    per_task : float, seconds per task, on its worker and (serially) on the scheduler
    per_pass : float, seconds per pass (submitting, the per-worker calls at its end)
    network : float, bytes/s of the link that sends the shared vectors (math.inf: none
        sent, the threads of one process)
    source : str
    """

    name: str
    per_task: float
    per_pass: float
    network: float
    source: str = ""


#: dask.distributed: "about 1 ms of overhead per task" (dask's best-practices page), a
#: pass's round trips (submit, gather, ``Client.run`` at its end) ~30 ms, vectors over
#: 10 GbE.
DASK_DISTRIBUTED = Scheduler("dask.distributed", 1e-3, 30e-3, 1.1e9,
                             "dask docs: ~1 ms per task; ~30 ms per pass of round trips; "
                             "10 GbE for the vectors")
#: dask's threaded scheduler: ~50 us per task (dask docs), nothing sent.
DASK_THREADS = Scheduler("dask threads", 50e-6, 2e-3, math.inf,
                         "dask docs: ~50 us per task in the threaded scheduler")


@dataclass(frozen=True)
class PassKind:
    """One kind of pass, as recorded, per row of T.

    Attributes
    ----------
    term : int or None, the term (None: the spectral radius's passes, before term 0)
    kind : str
    passes : int
    compute_per_row : float, seconds per row of one pass, storage time taken out
    read_per_row, write_per_row, requests_per_row : float, per row of one pass
    shared_read_per_row : float, the right factor's bytes per row (read whole per worker)
    shared_requests_per_row : float
    vectors_per_row : float, shared vectors' bytes per row of one pass
    imbalance : float, slowest task over the mean task
    """

    term: int | None
    kind: str
    passes: int
    compute_per_row: float
    read_per_row: float
    write_per_row: float
    requests_per_row: float
    shared_read_per_row: float
    shared_requests_per_row: float
    vectors_per_row: float
    imbalance: float


@dataclass(frozen=True)
class RecordedRun:
    """What the model takes from one run (:meth:`from_report`).

    Attributes
    ----------
    n, nnz_T, tile_size, slots : the recorded run's rows, T's entries, row block, task
        slots (threads, or workers x threads)
    passes : tuple of PassKind, in the run's order
    publish_per_tile_row : dict of term -> seconds per tile row outside the passes
        (publication, finalizing stores, the residual's arithmetic)
    m_build_per_row : float, seconds per row to make M's rows from T's (the first pass)
    base_resident : int, bytes a process holds before its heavy passes
    task_resident : int, bytes one task holds beyond the shared parts
    max_factor_per_row : float, bytes per row of the largest right factor in memory
    seconds_terms, seconds_spectral : measured
    """

    n: int
    nnz_T: int
    tile_size: int
    slots: int
    passes: tuple[PassKind, ...]
    publish_per_tile_row: dict
    m_build_per_row: float
    base_resident: int
    task_resident: int
    max_factor_per_row: float
    seconds_terms: float
    seconds_spectral: float
    term_seconds: tuple[float, ...] = ()

    @classmethod
    def from_report(cls, report: dict, storage: Storage, processes: int = 1) -> "RecordedRun":
        """From ``bigT invert --json``'s report of an out-of-core run; ``storage`` is
        where it read and wrote (its time is taken out of the tasks'), ``processes``
        how many processes ran tasks (each read the right factor once a pass)."""
        n, ts = int(report["n"]), int(report["tile_size"])
        tiles = -(-n // ts)
        history = [h for h in report["history"] if h.get("tasks")]
        if not history:
            raise ValueError("the report holds no task costs (an in-memory run, or one "
                             "made before they were recorded)")
        per_term = [(h["term"], t) for h in history for t in h["tasks"]]
        spectral = _spectral_costs(report["task_costs"], [t for _, t in per_term])
        passes = tuple(_pass_kind(None, t, n, storage, processes) for t in spectral)
        passes += tuple(_pass_kind(k, t, n, storage, processes) for k, t in per_term)
        first = passes[0]
        publish = {h["term"]: max(0.0, h["seconds"] - sum(t["wall_seconds"] for t in h["tasks"]))
                   / tiles for h in history}
        peak = max(t["peak_resident"] for t in report["task_costs"])
        base = min(t["peak_resident"] for t in report["task_costs"])
        factor_mem = max((_factor_entries(report, h) * ENTRY_BYTES / n for h in history),
                         default=0.0)
        m_bytes = min(report["nnz_T"] * ENTRY_BYTES, _cache_share(report))
        slots = int(report["threads"])
        task = max(0, int((peak - base - m_bytes - factor_mem * n) / slots))
        return cls(n, int(report["nnz_T"]), ts, slots, passes, publish,
                   first.compute_per_row, int(base), task, factor_mem,
                   sum(h["seconds"] for h in history),
                   float(report["seconds_spectral_radius"]),
                   tuple(h["seconds"] for h in history))


def _spectral_costs(total: list[dict], in_terms: list[dict]) -> list[dict]:
    """The run's costs by kind less the terms': the spectral radius's passes."""
    out = []
    for t in total:
        rest = dict(t)
        for s in in_terms:
            if s["kind"] == t["kind"]:
                for key in ("passes", "tasks", "wall_seconds", "task_seconds", "bytes_read",
                            "bytes_written", "read_calls", "write_calls",
                            "bytes_read_shared", "shared_bytes"):
                    rest[key] -= s[key]
        if rest["passes"] > 0:
            out.append(rest)
    return out


def _pass_kind(term, t: dict, n: int, storage: Storage, processes: int) -> PassKind:
    passes = max(1, t["passes"])
    requests = t["read_calls"] / READ_CALLS_PER_FILE + t["write_calls"]
    shared = t["bytes_read_shared"]
    rows_read = t["bytes_read"] - shared
    shared_requests = requests * shared / t["bytes_read"] if t["bytes_read"] else 0.0
    storage_s = storage.io_seconds(t["bytes_read"] + t["bytes_written"], requests, 1)
    compute = max(0.0, t["task_seconds"] - storage_s)
    mean = t["task_seconds"] / t["tasks"] if t["tasks"] else 0.0
    return PassKind(
        term, t["kind"], passes, compute / passes / n,
        rows_read / passes / n, t["bytes_written"] / passes / n,
        (requests - shared_requests) / passes / n,
        shared / processes / passes / n, shared_requests / processes / passes / n,
        t["shared_bytes"] / passes / n,
        t["max_task_seconds"] / mean if mean else 1.0)


def _factor_entries(report: dict, h: dict) -> int:
    """Entries of the right factor term ``h`` multiplied by: the held term's P."""
    previous = [p for p in report["history"] if p["term"] == h["term"] - 1]
    return int(previous[0]["nnz_P"]) if previous and h["term"] >= 2 else 0


def _cache_share(report: dict) -> int:
    """The recorded plan's tile cache, bytes (from its description)."""
    import re

    found = re.search(r"tile cache (\d+)", report.get("memory", ""))
    return int(found[1]) << 20 if found else 1 << 62


@dataclass(frozen=True)
class Prediction:
    """One configuration's predicted run.

    Attributes
    ----------
    n, workers, threads : the run
    storage, scheduler : names
    seconds : float, the inverse (spectral radius and terms; set-up left out)
    seconds_terms : tuple of float, per term
    seconds_spectral : float
    memory_per_worker : int, bytes
    batched : bool, a right factor exceeds the plan's share (read in batches: the
        broadcast term then under-counts the reads)
    """

    n: int
    workers: int
    threads: int
    storage: str
    scheduler: str
    seconds: float
    seconds_terms: tuple[float, ...]
    seconds_spectral: float
    memory_per_worker: int
    batched: bool = False


def tile_size_for(n: int, slots: int, t_tile: int = T_TILE) -> int:
    """The row block bigT cuts at n rows for ``slots`` task slots."""
    from bigT.algorithms.run_setup import choose_tile_size  # the engine's own rule

    return choose_tile_size(n, t_tile, slots)


def predict(run: RecordedRun, n: int, workers: int, storage: Storage,
            scheduler: Scheduler, *, threads: int = 1, tile_size: int | None = None,
            memory_limit: int = 8 << 30) -> Prediction:
    """The run at ``n`` rows on ``workers`` processes of ``threads`` threads each
    (the module's equations); ``memory_limit`` per worker."""
    slots = workers * threads
    ts = tile_size or tile_size_for(n, slots)
    tiles = -(-n // ts)
    rows = n / tiles
    by_term: dict = {}
    done = 0  # passes before this kind's first: M's rows built on a worker so far
    for p in run.passes:
        # the chance a task finds its M rows unbuilt on its worker, averaged over the
        # kind's passes (the run's first pass built them all: in its compute)
        unbuilt = sum((1 - 1 / workers) ** j for j in range(max(done, 1), done + p.passes)
                      ) / p.passes
        done += p.passes
        task = (p.compute_per_row * rows
                + storage.io_seconds((p.read_per_row + p.write_per_row) * rows,
                                     p.requests_per_row * rows, min(workers, tiles))
                + unbuilt * run.m_build_per_row * rows + scheduler.per_task)
        broadcast = (storage.io_seconds(p.shared_read_per_row * n,
                                        p.shared_requests_per_row * n, workers)
                     if p.shared_read_per_row else 0.0)
        vectors = workers * p.vectors_per_row * n / scheduler.network
        one = (scheduler.per_pass + broadcast + vectors
               + max(math.ceil(tiles / slots) * task, p.imbalance * task,
                     tiles * scheduler.per_task))
        by_term[p.term] = by_term.get(p.term, 0.0) + one * p.passes
    terms = tuple(by_term[k] + run.publish_per_tile_row.get(k, 0.0) * tiles
                  for k in sorted(k for k in by_term if k is not None))
    spectral = by_term.get(None, 0.0)
    memory, batched = _memory(run, n, workers, threads, memory_limit, len(run.passes))
    return Prediction(n, workers, threads, storage.name, scheduler.name,
                      spectral + sum(terms), terms, spectral, memory, batched)


def _memory(run: RecordedRun, n: int, workers: int, threads: int, limit: int,
            passes: int) -> tuple[int, bool]:
    """Bytes per worker, and whether a right factor exceeds the plan's shares."""
    from bigT.config import MEMORY_CACHE_SHARE, MEMORY_HEADROOM_BYTES, MEMORY_WHOLE_SHARE

    rest = max(0, limit - run.base_resident - MEMORY_HEADROOM_BYTES)
    cache_budget = MEMORY_CACHE_SHARE * rest
    seen = 1 - (1 - 1 / workers) ** passes if workers > 1 else 1.0
    m_bytes = run.nnz_T / run.n * n * ENTRY_BYTES * seen
    factor = run.max_factor_per_row * n
    batched = factor > (MEMORY_CACHE_SHARE + MEMORY_WHOLE_SHARE) * rest
    held = (run.base_resident + threads * run.task_resident + min(cache_budget, m_bytes)
            + (0 if batched else factor))
    return int(min(held, limit) if batched else held), batched


@dataclass(frozen=True)
class Measured:
    """A measured configuration beside its prediction."""

    label: str
    workers: int
    seconds_terms: float
    seconds_spectral: float
    peak_per_worker: int
    predicted: Prediction = field(compare=False, default=None)

    @property
    def error(self) -> float:
        """(predicted - measured) / measured of the terms' time plus the spectral
        radius's (what :class:`Prediction` ``seconds`` counts)."""
        measured = self.seconds_terms + self.seconds_spectral
        return (self.predicted.seconds - measured) / measured

    @property
    def memory_error(self) -> float:
        return (self.predicted.memory_per_worker - self.peak_per_worker) / self.peak_per_worker


def measured_from_report(label: str, workers: int, report: dict) -> Measured:
    history = [h for h in report["history"]]
    peaks = [b for _, b in report["peak_memory"]]
    return Measured(label, workers, sum(h["seconds"] for h in history),
                    float(report["seconds_spectral_radius"]), max(peaks) if peaks else 0)


def local_storage(bandwidth: float, latency: float) -> Storage:
    """This machine's store (the page cache, as the recorded run met it)."""
    return Storage("local disk", bandwidth, bandwidth, latency, 1,
                   "measured here: the run's store files read back")


def with_scheduler_from(run_report: dict, base: Scheduler) -> Scheduler:
    """``base`` with the per-task cost the report measured (its scheduling overhead
    per task)."""
    return replace(base, per_task=float(run_report["task_overhead_ms"]) / 1e3)


#: Projector sizes the cluster table predicts.
FULL_HD, UHD_4K = 1080 * 1920, 2160 * 3840
#: Worker counts of the table.
WORKERS = (1, 2, 4, 8, 16, 32, 64, 128)


def prediction_table(run: RecordedRun, scheduler: Scheduler = DASK_DISTRIBUTED,
                     sizes=(FULL_HD, UHD_4K), storages=(SHARED_FS, OBJECT_STORE),
                     workers=WORKERS, memory_limit: int = 8 << 30) -> list[Prediction]:
    """Every (size, storage, N) of the cluster table."""
    return [predict(run, n, N, st, scheduler, memory_limit=memory_limit)
            for n in sizes for st in storages for N in workers]
