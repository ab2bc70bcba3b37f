"""What :func:`~bigT.algorithms.stratified_inverse` did: the :class:`InverseReport` and
its per-term table (what ``bigT invert`` prints)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from ..schedule.costs import TaskCosts
from ..schedule.memory import human_bytes
from ..spectral import ABS_BOUND, spectral_meaning
from .records import TermRecord
from .settings import Thresholds


@dataclass(frozen=True)
class InverseReport:
    """What :func:`stratified_inverse` did.

    ``terms`` is the term the store holds (T_terms^-1, eq. 13); ``history`` one
    :class:`TermRecord` per term computed, by this run or by an earlier one that it
    resumed (the terms up to ``resumed_from``: their times are that run's). ``seconds``
    is this run's wall time, ``seconds_spectral_radius`` the part of it spent on the
    spectral radius (read from the store when ``spectral_computed`` is False).
    ``spectral_method`` says what kind of number ``spectral_radius`` +-
    ``spectral_uncertainty`` is (:meth:`bigT.spectral.SpectralRadius.meaning`).
    ``engine_path`` is ``"in-memory"`` or ``"out-of-core"`` (the path the run's last
    term took; each term's is in ``history``), ``engine_path_reason`` why.
    ``task_costs`` is what this run's tasks cost, one
    :class:`~bigT.schedule.costs.TaskCosts` per kind (the spectral radius's mat-vecs
    included; each term's are in ``history``).
    """

    path: str
    terms: int
    requested_terms: int
    method: str
    prune: float
    first_bounce: str
    spectral_radius: float | None
    excluded_pixels: int
    residual: float | None
    stopped: str
    resumed_from: int | None
    products: int
    seconds: float
    n: int
    nnz_T: int
    history: tuple[TermRecord, ...] = ()
    seconds_spectral_radius: float = 0.0
    memory: str = "no memory limit"
    scheduler: str = "local threads"
    tile_size: int = 0
    tasks: int = 0
    task_overhead_ms: float = 0.0
    peak_memory: tuple[tuple[str, int], ...] = ()
    spectral_uncertainty: float | None = None
    threads: int = 1
    prune_feed: float | None = None
    prune_operator: float | None = None
    spectral_method: str | None = None
    spectral_computed: bool = True
    engine_path: str = "out-of-core"
    engine_path_reason: str = ""
    task_costs: tuple[TaskCosts, ...] = ()

    def to_dict(self) -> dict:
        return asdict(self)

    def earlier(self, record: TermRecord) -> bool:
        """Whether ``record``'s term was computed by an earlier run this one resumed."""
        return self.resumed_from is not None and record.term <= self.resumed_from

    def table(self) -> str:
        """The per-term table: time (its residual estimate's share), entries, tiles,
        residual, and the products' multiply-adds with two rates per core: over the
        term's wall time (everything the user waits for) and inside the kernel only;
        then where the time went, the spectral radius, the settings and the run."""
        head = (f"{'term':>4} {'time s':>8} {'resid s':>7} {'nnz(P)':>12} {'nnz(X)':>12} "
                f"{'tiles done':>10} {'skipped':>8} {'residual':>10} {'mult-adds':>10} "
                f"{'rate/core':>9} {'kernel/core':>11}")
        lines = [head, "-" * len(head)]
        lines += [self._row(r) for r in self.history]
        if any(self.earlier(r) for r in self.history):
            lines.append(f"* computed by an earlier run (this one resumed from term "
                         f"{self.resumed_from}): the times are that run's")
        lines += [self._time_line(), self._spectral_line(),
                  f"held term {self.terms} ({self.method}, {self._thresholds()}, "
                  f"first bounce {self.first_bounce}), {self.excluded_pixels} pixels "
                  f"left out, stopped: {self.stopped}",
                  self._ran_line(),
                  self.memory]
        if self.peak_memory:
            lines.append("peak resident memory: " + ", ".join(
                f"{who} {human_bytes(b)}" for who, b in self.peak_memory))
        if self.task_costs:
            lines.append(self._costs_line())
        return "\n".join(lines)

    def _costs_line(self) -> str:
        """What the tasks cost by kind: tasks, time in them, bytes read (once per
        process of it) and written."""
        parts = [f"{c.kind} {c.tasks} in {c.task_seconds:.2f} s, read "
                 f"{human_bytes(c.bytes_read)}"
                 + (f" ({human_bytes(c.bytes_read_shared)} once per process)"
                    if c.bytes_read_shared else "")
                 + f", wrote {human_bytes(c.bytes_written)}" for c in self.task_costs]
        return "tasks by kind: " + "; ".join(parts)

    def _ran_line(self) -> str:
        """Where the run ran: in memory (and why), or its tasks on the scheduler."""
        if self.engine_path == "in-memory":
            return (f"ran {self.engine_path_reason or 'in memory'}, {self.threads} threads, "
                    f"each term written in tile rows of {self.tile_size} rows")
        why = f" ({self.engine_path_reason})" if self.engine_path_reason else ""
        return (f"ran on {self.scheduler}{why}, row blocks of {self.tile_size} rows, "
                f"{self.tasks} tasks, {self.task_overhead_ms:.1f} ms scheduling "
                "overhead per task")

    def _row(self, r: TermRecord) -> str:
        res = "-" if r.residual is None else f"{r.residual:.3e}"
        mark = "*" if self.earlier(r) else " "
        return (f"{r.term:>4}{mark}{r.seconds:>8.2f} {r.residual_seconds:>7.2f} "
                f"{r.nnz_P:>12d} {r.nnz_X:>12d} {r.tiles_computed:>10d} "
                f"{r.tiles_skipped:>8d} {res:>10} {_count(r.multiply_adds):>10} "
                f"{_rate(r.multiply_adds, r.seconds * self.threads):>9} "
                f"{_rate(r.multiply_adds, r.kernel_seconds):>11}")

    def _time_line(self) -> str:
        """This run's wall time and what it counts (the table's rows of this run, the
        spectral radius, the set-up), then the earlier run's terms apart."""
        new = [r for r in self.history if not self.earlier(r)]
        rho = (f"{self.seconds_spectral_radius:.2f} s on the spectral radius"
               if self.spectral_computed else "the spectral radius read from the store")
        terms = (f"{sum(r.seconds for r in new):.2f} s on {_terms(new)}" if new
                 else "no term computed")
        line = f"this run: {self.seconds:.2f} s in all ({rho}, {terms}, the rest set-up)"
        old = [r for r in self.history if self.earlier(r)]
        if old:
            line += (f"; the earlier run's {_terms(old)} took "
                     f"{sum(r.seconds for r in old):.2f} s")
        return line

    def _spectral_line(self) -> str:
        if self.spectral_radius is None:
            return "spectral radius of M = I - T F^-1: -"
        value = f"{self.spectral_radius:.4f}"
        if self.spectral_method == ABS_BOUND and self.spectral_uncertainty is not None:
            value = f"at most {self.spectral_radius + self.spectral_uncertainty:.4f}"
        elif self.spectral_uncertainty is not None:
            value += f" +- {self.spectral_uncertainty:.1e}"
        return (f"spectral radius of M = I - T F^-1: {value}, "
                + spectral_meaning(self.spectral_method, self.spectral_radius,
                                   self.spectral_uncertainty))

    def _thresholds(self) -> str:
        return Thresholds(self.prune, self.prune_feed, self.prune_operator).describe()


def _terms(records: list[TermRecord]) -> str:
    """``term 3`` or ``terms 0-2``."""
    first, last = records[0].term, records[-1].term
    return f"term {first}" if first == last else f"terms {first}-{last}"


def _count(n: int) -> str:
    """1.23e9 style for a table cell; '-' for none."""
    return f"{n:.3g}" if n else "-"


def _rate(multiply_adds: int, seconds: float) -> str:
    """Multiply-adds per second (per core when ``seconds`` are core-seconds)."""
    if not multiply_adds or seconds <= 0:
        return "-"
    return f"{multiply_adds / seconds:.3g}"
