"""What a run's tasks cost, by kind of task (a pass's ``op``): the record a model of the
same run on more workers is built from (``benchmarks/cluster_model.py``).

Each task measures itself (:func:`~.worker.run_block`): its wall time, the bytes its
thread read and wrote (the kernel's per-thread I/O counters: bigT's stores are read and
written by the task's own thread, with plain file calls), how many read and write calls
that took, the part read once per process for every task of the pass (a right factor
held whole: what a cluster's workers each read again, the pass's broadcast), and the
process's resident set when it ended. A runner sums its passes into one
:class:`TaskCosts` per kind (:class:`CostLedger`); the engine keeps each term's in its
history record and the run's in its report. Reading the counters costs ~70 us a task.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass
from typing import Mapping

#: The kernel's I/O counters of the calling thread (Linux >= 3.17).
_THREAD_IO = "/proc/thread-self/io"


@dataclass(frozen=True)
class ThreadIO:
    """The calling thread's I/O so far: bytes and calls of read and write (sockets and
    pipes included, which a task's thread does not use: its results travel on another
    thread)."""

    read_bytes: int = 0
    written_bytes: int = 0
    read_calls: int = 0
    write_calls: int = 0

    def minus(self, earlier: "ThreadIO") -> "ThreadIO":
        return ThreadIO(self.read_bytes - earlier.read_bytes,
                        self.written_bytes - earlier.written_bytes,
                        self.read_calls - earlier.read_calls,
                        self.write_calls - earlier.write_calls)


def thread_io() -> ThreadIO:
    """:class:`ThreadIO` of the calling thread (``rchar``, ``wchar``, ``syscr``,
    ``syscw`` of /proc/thread-self/io); zeros where the kernel does not keep them."""
    try:
        with open(_THREAD_IO, "rb") as fh:
            fields = dict(line.split(b":") for line in fh.read().splitlines())
        return ThreadIO(int(fields[b"rchar"]), int(fields[b"wchar"]),
                        int(fields[b"syscr"]), int(fields[b"syscw"]))
    except (OSError, KeyError, ValueError):
        return ThreadIO()


_shared_reads = threading.local()


class SharedRead:
    """``with SharedRead():`` around a read done once per process for all the tasks of
    a pass (a right factor held whole): its bytes are counted as the task's
    ``bytes_read_shared`` too (:func:`shared_read_bytes`)."""

    def __enter__(self):
        self.before = thread_io()
        return self

    def __exit__(self, *exc):
        read = thread_io().minus(self.before).read_bytes
        _shared_reads.bytes = shared_read_bytes() + read
        return False


def shared_read_bytes() -> int:
    """Bytes the calling thread has read in :class:`SharedRead` blocks so far."""
    return getattr(_shared_reads, "bytes", 0)


@dataclass(frozen=True)
class TaskCosts:
    """The tasks of one kind in a stretch of a run (a term, or the whole run).

    Attributes
    ----------
    kind : str, the passes' ``op`` (``power``, ``diag``, ``matvec-M``, ``matvec-X``, ...)
    passes, tasks : int
    threads : int, threads that ran tasks at once (the most over the passes)
    wall_seconds : float, the passes' wall time, from submitting their tasks to the
        last result
    task_seconds : float, the tasks' own time, summed
    max_task_seconds : float, the slowest task
    kernel_seconds : float, inside the product kernel, summed over tasks
    bytes_read, bytes_written : int, by the tasks' threads (files: bigT's stores)
    read_calls, write_calls : int, the read and write calls that took (a stored
        array's chunk file is one open, an fstat and two reads: its bytes, then the
        end of the file)
    bytes_read_shared : int, the part of ``bytes_read`` read once per process and
        shared by its tasks (a right factor held whole): read by every worker of a
        cluster
    shared_bytes : int, the passes' shared vectors (F^-1, F, the kept mask, a
        mat-vec's V, the residual probes), summed over the passes: a cluster sends
        them to every worker, once a pass
    peak_resident : int, the largest resident set of a process seen at a task's end,
        bytes
    """

    kind: str
    passes: int = 0
    tasks: int = 0
    threads: int = 0
    wall_seconds: float = 0.0
    task_seconds: float = 0.0
    max_task_seconds: float = 0.0
    kernel_seconds: float = 0.0
    bytes_read: int = 0
    bytes_written: int = 0
    read_calls: int = 0
    write_calls: int = 0
    bytes_read_shared: int = 0
    shared_bytes: int = 0
    peak_resident: int = 0

    def plus(self, other: "TaskCosts") -> "TaskCosts":
        """These costs and ``other``'s (of the same kind): sums, the larger peaks."""
        largest = ("threads", "max_task_seconds", "peak_resident")
        return dataclasses.replace(self, **{
            f.name: (max if f.name in largest else _sum)(getattr(self, f.name),
                                                         getattr(other, f.name))
            for f in dataclasses.fields(self) if f.name != "kind"})

    @classmethod
    def of_pass(cls, kind: str, wall: float, stats, shared: Mapping, threads: int
                ) -> "TaskCosts":
        """One pass's costs from its tasks' :class:`~.spec.BlockStats`, its wall time,
        its shared vectors and the threads that ran it."""
        return cls(
            kind, passes=1, tasks=len(stats), threads=int(threads), wall_seconds=float(wall),
            task_seconds=float(sum(s.seconds for s in stats)),
            max_task_seconds=float(max((s.seconds for s in stats), default=0.0)),
            kernel_seconds=float(sum(s.kernel_seconds for s in stats)),
            bytes_read=int(sum(s.bytes_read for s in stats)),
            bytes_written=int(sum(s.bytes_written for s in stats)),
            read_calls=int(sum(s.read_calls for s in stats)),
            write_calls=int(sum(s.write_calls for s in stats)),
            bytes_read_shared=int(sum(s.bytes_read_shared for s in stats)),
            shared_bytes=int(sum(int(getattr(v, "nbytes", 0)) for v in shared.values())),
            peak_resident=int(max((s.resident_bytes for s in stats), default=0)))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping) -> "TaskCosts":
        """Raises TypeError/ValueError on a field of the wrong type (a damaged record)."""
        values = {}
        for f in dataclasses.fields(cls):
            v = d.get(f.name, f.default)
            if f.name == "kind":
                values[f.name] = str(v)
            elif f.type in ("float", float):
                values[f.name] = float(v)
            else:
                if isinstance(v, bool) or int(v) != v or v < 0:
                    raise ValueError(f"{f.name} must be a count, got {v!r}")
                values[f.name] = int(v)
        return cls(**values)


def _sum(a, b):
    return a + b


def by_kind(costs) -> tuple[TaskCosts, ...]:
    """``costs`` (any number per kind) summed into one per kind, in the order the kinds
    first appear."""
    out: dict[str, TaskCosts] = {}
    for c in costs:
        out[c.kind] = out[c.kind].plus(c) if c.kind in out else c
    return tuple(out.values())


class CostLedger:
    """A runner's passes, each as a :class:`TaskCosts` stamped with the time
    (``time.perf_counter()``) it began: :meth:`since` gives one stretch's (a term's),
    :meth:`total` the whole run's. Only the thread that runs the passes writes it."""

    def __init__(self):
        self._passes: list[tuple[float, TaskCosts]] = []

    def add(self, began: float, costs: TaskCosts) -> None:
        self._passes.append((float(began), costs))

    def since(self, t0: float) -> tuple[TaskCosts, ...]:
        """The passes begun at or after ``t0``, one :class:`TaskCosts` per kind."""
        return by_kind(c for began, c in self._passes if began >= t0)

    def total(self) -> tuple[TaskCosts, ...]:
        """Every pass, one :class:`TaskCosts` per kind."""
        return by_kind(c for _, c in self._passes)

    def record(self, kind: str, began: float, stats, shared: Mapping, threads: int) -> None:
        """Add the pass of ``kind`` that began at ``began`` and ended now."""
        self.add(began, TaskCosts.of_pass(kind, time.perf_counter() - began, stats, shared,
                                          threads))
