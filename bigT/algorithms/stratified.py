"""The stratified inverse, out of core, term by term, resumable (paper §4.2, eq. 13).

Convention
----------
``terms=n`` yields T_n^-1 = F^-1 sum_{k=0..n} M^k with M = I - T F^-1 (paper eq. 13):
``terms=0`` is F^-1 alone, ``terms=1`` adds the first correction F^-1 M, and so on.
The paper counts bounces two ways: eq. 13's index n (used here), and "the n-bounce
inverse" of §5.1, where T_0^-1 is called the one-bounce and T_4^-1 the five-bounce
stratified inverse. In the power form n terms cost n sparse products (the first one,
M P_0 = M, is free: P_1 is M pruned).

Methods (all in the dimensionless variables P_k = M^k, S_n = sum_{k<=n} M^k, X = F^-1 S):

``"power"`` (default)
    P_0 = I, P_k = M P_{k-1} (pruned), X_k = X_{k-1} + F^-1 P_k, X_0 = F^-1.
``"horner"``
    X_n = F^-1 + (I - F^-1 T) X_{n-1}, i.e. S_n = I + M S_{n-1}: one product with the
    ever-growing S per term.
``"newton-schulz"``
    X <- X (2I - T X), as R = I - T X then X <- X + X R (two products per step). After
    j steps from X_0 = F^-1, X = T_{2^j-1}^-1 (exactly, without pruning). ``terms=n``
    runs the fewest steps j with 2^j - 1 >= n, so the store holds term 2^j - 1 >= n
    (reported as ``terms``).

Pruning: entries |v| < prune of each new P_k (power), of M S_{n-1} (horner), of R and of
S R (Newton-Schulz) are dropped inside the product, all dimensionless. Bound for the
power form: with E_k = P_k - M^k, E_k = M E_{k-1} + D_k where D_k (the dropped entries)
has at most r_k entries per row, each < prune in magnitude, so ||D_k||_inf < r_k prune
and ||E_k||_inf <= sum_{l<=k} ||M||_inf^(k-l) r_l prune. Hence
||X_n - T_n^-1||_inf <= ||F^-1||_inf prune sum_{k=1..n} sum_{l=1..k} ||M||_inf^(k-l) r_l,
with r_l the number of candidate entries dropped per row at term l (at most n).
``tests/algorithms/test_pruning.py`` checks it.

Power versus Horner under pruning: with D_k the entries dropped at term k, the power
form's residual is I - T X_n = M P_n - sum_k D_k. Every term's pruning stays in it,
and D_1, the small entries of M itself, is the largest. Horner's is
-D_n + M (S_n - S_{n-1}), because each step re-applies I + M S and so corrects the
earlier pruning. At the same prune, Horner is therefore more accurate. Its products
multiply by S, which is as wide as P_1, while the power form's later products shrink
with P_k. At four terms the first real product (M P_1, or M S_1) dominates both forms,
so the power form's advantage is bounded by (c_1 + 3c) / (c_1 + c) < 3x. That holds
even if the later products cost nothing. On the dense 384x512 corner, Horner wins at
equal error (README, "Measured").

Carrying (``prune_feed``): the power form may prune P_k, the factor of the next
product, at a higher threshold than the term Q_k = M P_{k-1} it adds to X. With
D_k = Q_k - P_k the entries carried in X but not fed on, X_n = F^-1 (I + sum_k Q_k)
and the residual is M P_n - sum_k D'_k + M sum_k D_k, where D'_k = Q_k - M P_{k-1}
(minus the entries below ``prune``, dropped from both): the fed-on pruning reaches the
residual multiplied by M (one more bounce, a factor ~rho(M)), not as itself, so P_k
can be pruned harder, and the next product costs less, for the same error. (The
infinity-norm bound above counts ``prune`` only; with a feed threshold, r_l prune
becomes r_l prune_feed in the terms after l.) The multiply-adds and the
error it buys are measured by ``benchmarks/bench_inverse.py --settings``.

The same holds on the left of the product (``prune_operator``): with M = M_o + D_o,
D_o the entries of M below ``prune_operator``, the terms k >= 2 compute
prune(M_o P_{k-1}) and miss D_o P_{k-1}, which is one bounce further down than D_o
(||P_{k-1}|| ~ rho^(k-1)), while term 1 still adds M down to ``prune``. Most of a dense
M's entries are small (on the dense 384x512 corner, 309 a row, 117 of them >= 1e-5),
and every one of them costs a row of P_{k-1} in the product: dropping them from the
left factor cuts term 2's multiply-adds 2.3x there for a 0.8 % larger error.

Residual: after every term, ||I - T X||_F is estimated from p = config.RESIDUAL_PROBES
Rademacher probes z (z_i = +-1 on the pixels kept): r = z - T (X z); since
E[z z^T] = D, E||r||^2 = ||(I - T X) D||_F^2, so (1/p) sum ||r||^2 is an unbiased
estimate of its square (with unit probes z/sqrt(n) this is the n/p sum ||r||^2 of
the issue). The report gives the relative value ||I - T X||_F / sqrt(n_kept) (the rms
of the columns of I - T X), which ``tol`` is compared with, and the absolute one.
T (X z) is computed as u - M u with u = F X z, the same T on the kept pixels.

Divergence: before term 0, rho(M) is computed by :func:`bigT.spectral.spectral_radius`
(a Collatz-Wielandt bracket where M = -|M|, as for any transport without negative
entries; else Arnoldi, with the Ritz residual as its uncertainty) and the run is
refused unless rho + uncertainty < 1. As a second line, the residuals are estimated
with the same probes at every term, and a term whose residual grew and exceeds the
smallest so far ``config.RESIDUAL_GROWTH`` (2) times is not published: the run stops
with the last good term held. (Not any growth: with a non-normal M, rho < 1 <= ||M||, or at the pruning
floor, a convergent series may grow for a term.)
``force`` skips both checks.

Out of core and resumable: the inverse store ``out`` is a versioned bigT store
(:class:`bigT.storage.InverseStore`). Term k is written to a new subgroup ``tKKKK``
(X and, for the power form, P) by the tasks of its passes, each task writing its own
tile rows; only when the term is complete (and its residual estimated and recorded in
its own metadata) does the root's redirect flip to it (one atomic rename), and then
the previous subgroup is deleted. A crash or Ctrl-C leaves the previous term readable;
rerunning the same call resumes at the first incomplete row block of the next term.
The root's attribute ``bigT_inverse`` records the parameters (refused if they differ),
the term held, the spectral radius and the per-term history; ``bigT info`` shows the X
store's ``metadata["inverse"]``.

Where the tasks run: :mod:`bigT.schedule.runner` (local threads, or the workers of a
dask cluster). The term stores take T's tile size, halved while that gives fewer than
``config.TASKS_PER_THREAD`` row blocks per thread (down to ``config.MIN_BLOCK_ROWS``
rows), so every thread of a cluster has work; the tile size is recorded and kept on
resume.

Paper §5.1 note: the printed eqs. 35-41 are not consistent with the printed T of eq. 34
(eq. 37's diagonal is not the inverse of eq. 36's; eq. 38 is not symmetric where T is).
The tests compare with values computed independently (dense numpy) from eq. 34.
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from .. import config
from ..errors import BigTError, DivergenceError, NotSquareError
from ..schedule.matvec import matvec, matvec_spec
from ..schedule.memory import human_bytes, warn_if_rows_outgrow
from ..schedule.operators import StoreOperand
from ..schedule.runner import ClusterRunner, local_path, new_pass_id, open_runner
from ..schedule.spec import BlockStats, MemoryPolicy, PassSpec, row_blocks
from ..spectral import SpectralRadius, spectral_radius
from ..sizes import parse_size
from ..storage import InverseStore, StoreAttrs, TermRecord
from ..storage import open as open_store
from ..storage.inverse_store import InverseRecord, term_dir
from ..storage import completed_rows
from .first_bounce import FirstBounce, resolve_first_bounce
from .methods import METHODS as SERIES_METHODS
from .methods import TERM_ZERO, Pass, SeriesMethod

METHODS = tuple(SERIES_METHODS)
_FORMAT = 1


@dataclass(frozen=True)
class InverseReport:
    """What :func:`stratified_inverse` did.

    ``terms`` is the term the store holds (T_terms^-1, eq. 13); ``history`` one
    :class:`TermRecord` per term computed (this run or an earlier, resumed one).
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

    def to_dict(self) -> dict:
        return asdict(self)

    def table(self) -> str:
        """The per-term table: time (its residual estimate's share), entries, tiles,
        residual, and the products' multiply-adds with two rates per core: over the
        term's wall time (everything the user waits for) and inside the kernel only."""
        head = (f"{'term':>4} {'time s':>8} {'resid s':>7} {'nnz(P)':>12} {'nnz(X)':>12} "
                f"{'tiles done':>10} {'skipped':>8} {'residual':>10} {'mult-adds':>10} "
                f"{'rate/core':>9} {'kernel/core':>11}")
        lines = [head, "-" * len(head)]
        for r in self.history:
            res = "-" if r.residual is None else f"{r.residual:.3e}"
            lines.append(f"{r.term:>4} {r.seconds:>8.2f} {r.residual_seconds:>7.2f} "
                         f"{r.nnz_P:>12d} {r.nnz_X:>12d} {r.tiles_computed:>10d} "
                         f"{r.tiles_skipped:>8d} {res:>10} {_count(r.multiply_adds):>10} "
                         f"{_rate(r.multiply_adds, r.seconds * self.threads):>9} "
                         f"{_rate(r.multiply_adds, r.kernel_seconds):>11}")
        rho = "-" if self.spectral_radius is None else f"{self.spectral_radius:.4f}"
        if self.spectral_radius is not None and self.spectral_uncertainty is not None:
            rho += f" +- {self.spectral_uncertainty:.1e}"
        lines.append(f"spectral radius estimate {self.seconds_spectral_radius:.2f} s, "
                     f"total {self.seconds:.2f} s")
        feed = "" if self.prune_feed is None else f", P_k pruned at {self.prune_feed:g}"
        if self.prune_operator is not None:
            feed += f", M pruned at {self.prune_operator:g} in the products"
        lines.append(f"held term {self.terms} ({self.method}, prune {self.prune:g}{feed}, "
                     f"first bounce {self.first_bounce}), spectral radius of M {rho}, "
                     f"{self.excluded_pixels} pixels left out, stopped: {self.stopped}")
        lines.append(f"ran on {self.scheduler}, row blocks of {self.tile_size} rows, "
                     f"{self.tasks} tasks, {self.task_overhead_ms:.1f} ms scheduling "
                     "overhead per task")
        lines.append(self.memory)
        if self.peak_memory:
            lines.append("peak resident memory: " + ", ".join(
                f"{who} {human_bytes(b)}" for who, b in self.peak_memory))
        return "\n".join(lines)


# --- helpers ------------------------------------------------------------------------------

def _count(n: int) -> str:
    """1.23e9 style for a table cell; '-' for none."""
    return f"{n:.3g}" if n else "-"


def _rate(multiply_adds: int, seconds: float) -> str:
    """Multiply-adds per second (per core when ``seconds`` are core-seconds)."""
    if not multiply_adds or seconds <= 0:
        return "-"
    return f"{multiply_adds / seconds:.3g}"


def _fingerprint(T, fb: FirstBounce, prune: float, method: str,
                 prune_feed: float | None = None,
                 prune_operator: float | None = None) -> dict:
    """What the inverse depends on: a run whose fingerprint differs is refused."""
    h = hashlib.sha1()
    h.update(np.asarray(T.tile_indptr, dtype=np.int64).tobytes())
    h.update(np.asarray(T.tile_indices, dtype=np.int64).tobytes())
    h.update(np.asarray(T.tile_nnz, dtype=np.int64).tobytes())
    # the feed and operator thresholds are recorded only when set, so stores made
    # before them resume
    extra = {name: float(value) for name, value in
             (("prune_feed", prune_feed), ("prune_operator", prune_operator))
             if value is not None}
    return {
        "format": _FORMAT,
        "T": {"path": os.path.abspath(T.path), "shape": list(T.shape), "nnz": int(T.nnz),
              "tile_size": int(T.tile_size), "dtype": str(np.dtype(T.dtype)),
              "tiles": h.hexdigest()[:16]},
        "prune": float(prune),
        "method": method,
        "first_bounce": {"kind": fb.kind, "digest": fb.digest},
        **extra,
    }


def _max_row_nnz(T) -> int:
    """Entries of T's widest tile row."""
    indptr = np.asarray(T.tile_indptr)
    tile_nnz = np.append(np.asarray(T.tile_nnz, dtype=np.int64), 0)
    row_nnz = np.add.reduceat(tile_nnz, indptr[:-1]) * (np.diff(indptr) > 0)
    return int(row_nnz.max(initial=0))


def choose_tile_size(n: int, tile_size: int, threads: int) -> int:
    """T's tile size, halved while it gives fewer than ``config.TASKS_PER_THREAD`` row
    blocks per thread, halving adds blocks, and blocks keep at least
    ``config.MIN_BLOCK_ROWS`` rows."""
    ts = int(tile_size)
    while (-(-n // ts) < config.TASKS_PER_THREAD * threads and ts // 2 >= config.MIN_BLOCK_ROWS
           and -(-n // (ts // 2)) > -(-n // ts)):
        ts //= 2
    return ts


# --- the estimates -----------------------------------------------------------------------

def residual_probes(fb: FirstBounce, probes=None, seed=0) -> np.ndarray:
    """The Rademacher probes Z of :func:`estimate_residual`, shape (n, p): +-1 on the
    kept pixels, 0 elsewhere; the same for the same ``seed``."""
    p = probes or config.RESIDUAL_PROBES
    rng = np.random.default_rng(seed + 7919)
    return rng.choice(np.array([-1.0, 1.0]), size=(len(fb.active), p)) * fb.active[:, None]


def estimate_residual(apply_M, apply_X, fb: FirstBounce, probes=None,
                      seed=0) -> tuple[float, float]:
    """(relative, absolute) estimate of ||I - T X||_F from Rademacher probes (module
    docstring); ``apply_M``/``apply_X`` multiply (n, p) blocks (``apply_X`` is called
    once, with :func:`residual_probes` of the same ``probes`` and ``seed``). Relative
    is absolute / sqrt(number of kept pixels)."""
    n_act = int(fb.active.sum())
    if n_act == 0:
        return 0.0, 0.0
    Z = residual_probes(fb, probes, seed)
    p = Z.shape[1]
    U = apply_X(Z) * fb.f[:, None]
    R = Z - (U - apply_M(U))  # T (X z) = u - M u with u = F X z, on the kept pixels
    abs_ = math.sqrt(float(np.sum(R * R)) / p)
    return abs_ / math.sqrt(n_act), abs_


# --- the engine ---------------------------------------------------------------------------

@dataclass(frozen=True)
class _Options:
    terms: int
    prune: float
    tol: float | None
    progress: bool
    force: bool
    seed: int
    overwrite: bool = False
    prune_feed: float | None = None
    prune_operator: float | None = None
    on_term: Callable[[InverseRecord], str | None] | None = None


def _check_arguments(method, terms, prune, tol, prune_feed=None,
                     prune_operator=None) -> SeriesMethod:
    if method not in SERIES_METHODS:
        raise BigTError(f"method must be one of {', '.join(SERIES_METHODS)}, got {method!r}")
    if isinstance(terms, bool) or int(terms) != terms or terms < 0:
        raise BigTError(f"terms must be an integer >= 0, got {terms!r}")
    if not prune >= 0:
        raise BigTError(f"prune must be >= 0, got {prune!r}")
    if tol is not None and not tol >= 0:
        raise BigTError(f"tol must be >= 0, got {tol!r}")
    for name, value, what in (("prune_feed", prune_feed, "P_k"),
                              ("prune_operator", prune_operator, "products M P_{k-1}")):
        if value is None:
            continue
        if method != "power":
            # Horner's S_{n-1} holds I: M pruned there would miss D_o itself
            raise BigTError(f"{name} is a threshold of the power form's {what}; the "
                            f"{method} method has none")
        if not value >= prune:
            raise BigTError(f"{name} must be >= prune ({prune:g}), got {value!r}")
    return SERIES_METHODS[method]


def stratified_inverse(T, out, terms=4, prune=config.DEFAULT_PRUNE, tol=None,
                       first_bounce="diag", method="power", client=None, memory_limit=None,
                       progress=True, force=False, *, workers=2, seed=0,
                       scheduler=None, overwrite=False, prune_feed=None,
                       prune_operator=None, on_term=None) -> InverseReport:
    """Compute the stratified inverse T_n^-1 = F^-1 sum_{k=0..n} (I - T F^-1)^k
    (paper eq. 13) out of core, term by term, into the store ``out``.

    ``terms=n`` follows eq. 13's index: ``terms=0`` is F^-1, and each term adds one
    power of M = I - T F^-1 (one sparse product in the power form). The paper's §5.1
    calls T_n^-1 the "(n+1)-bounce" stratified inverse: the same matrix, counted from 1.

    Parameters
    ----------
    T : BlockCSR or str/PathLike, shape (n, n)
        The light transport, square (after the pixel correspondence).
    out : str or PathLike
        The inverse store. Created; or, when it holds an inverse of the same T with
        the same prune, method and first bounce, resumed (a held term >= ``terms``
        returns at once). Any other existing ``out`` is refused (StoreError).
    terms : int >= 0
    prune : float >= 0
        Entries of each new (dimensionless) term below this are dropped in the product.
    prune_feed : float >= prune, optional
        Power form only: P_k, the factor of the next product, is pruned at this
        instead, while X keeps the term's entries down to ``prune`` ("Carrying" in
        the module docstring: less work for the same error). Default: ``prune``.
    prune_operator : float >= prune, optional
        Power form only: M's entries below this are left out of the products of the
        terms k >= 2, M P_{k-1}; term 1 still adds M down to ``prune`` (module
        docstring, after "Carrying": what they would add is one bounce further
        down). Default: none left out.
    tol : float, optional
        Stop once the estimated relative residual ||I - T X||_F / sqrt(n) <= tol.
    first_bounce : "diag", "identity", (n,) array or path of a .npy
        F: diag(T) (Jacobi, paper §4.4), I (the naive choice, often divergent), or a
        known F, e.g. from :func:`recover_first_bounce`.
    method : "power", "horner" or "newton-schulz" (:mod:`bigT.algorithms.methods`)
    scheduler : None, "local:N", an address or a distributed.Client
        Where the tasks run (:func:`bigT.schedule.runner.open_runner`): dask's local
        threaded scheduler with ``workers`` threads by default; ``local:N`` starts N
        worker processes for the run; an address ("tcp://host:port") or a Client uses
        that cluster, whose workers must see ``T`` and ``out`` at the same paths.
    client : distributed.Client or str, optional
        The same as ``scheduler`` (kept for callers of bigT 0.1).
    memory_limit : int or str, optional
        Bytes ("2GiB") for the resident memory of the process running the tasks (with
        ``local:N``, of the N workers together; on a cluster each worker also keeps
        its own limit). Each process measures what it holds and shares out the rest
        (:func:`bigT.schedule.memory.plan_memory`); a limit too small for the fixed
        parts raises ``MemoryLimitError`` before anything is written.
    progress : bool
        Progress bars (shown only when stderr is a terminal).
    force : bool
        Go on although the estimated spectral radius of M is >= 1.
    overwrite : bool
        Delete an inverse ``out`` holds (whatever its parameters) and start anew;
        never anything that is not a bigT inverse store.
    on_term : callable, optional
        ``on_term(record)`` is called after each term this run computes is published
        (``record`` the store's :class:`InverseRecord`; ``out`` then holds that term),
        and first for the term held when the run resumes a store short of ``terms``;
        a string returned stops the run there, as its ``stopped`` reason. One run
        with it costs less than a run per term (one set-up, one spectral radius
        read): :func:`bigT.algorithms.target.invert_to_target` measures each term so.

    Returns
    -------
    InverseReport

    Raises
    ------
    MemoryLimitError
        ``memory_limit`` cannot hold what the run needs at the least.
    DivergenceError
        rho(M) >= 1 (and not ``force``).
    InvalidMatrixError
        Negative or zero diagonal on lit pixels with ``first_bounce="diag"``.
    StoreError
        ``out`` exists and holds something else.
    SchedulerError
        The scheduler cannot be reached, or its workers cannot see the stores.
    """
    t_start = time.perf_counter()
    prune_feed = None if prune_feed is None else float(prune_feed)
    prune_operator = None if prune_operator is None else float(prune_operator)
    series = _check_arguments(method, terms, prune, tol, prune_feed, prune_operator)
    if prune_feed == prune:  # the plain power form, and resumes its stores
        prune_feed = None
    scheduler = client if scheduler is None else scheduler
    if isinstance(T, (str, os.PathLike)):
        T = open_store(local_path(T, "transport T"))
    if T.shape[0] != T.shape[1]:
        raise NotSquareError(f"T is {T.shape[0]} x {T.shape[1]}; the inverse needs a square "
                             "T (apply the pixel correspondence first)", T.path)
    out = local_path(out, "inverse store")
    opts = _Options(int(terms), float(prune), tol, progress, force, seed, overwrite,
                    prune_feed, prune_operator, on_term)
    memory_limit = None if memory_limit is None else parse_size(memory_limit, "memory_limit")
    runner = open_runner(scheduler, workers=workers, memory_limit=memory_limit)
    store = InverseStore(out)
    try:
        engine = _Engine(T, store, series, runner, opts, first_bounce, memory_limit)
        return engine.run(t_start)
    finally:
        _let_go(runner, T, out)
        store.close()  # the writer lock, whatever failed


def _let_go(runner, T, out) -> None:
    """End of a run: every process forgets the cached rows of T's M and of the
    inverse's terms (a caller's later work starts with an empty cache), then the
    runner closes what it started."""
    try:
        runner.end_pass(None, forget=(local_path(T.path), out))
    except Exception:  # a cluster gone with the run: nothing left to free
        pass
    runner.close()


@dataclass
class _PassTiming:
    """Tasks of the product passes and the threads' time not spent inside them:
    (wall time x threads - time in tasks) / tasks is what scheduling a task costs
    (submission, scattering, results, idle threads at the end of a pass)."""

    tasks: int = 0
    thread_seconds: float = 0.0
    task_seconds: float = 0.0

    def add(self, wall: float, stats: list[BlockStats], threads: int) -> None:
        self.tasks += len(stats)
        self.thread_seconds += wall * threads
        self.task_seconds += sum(s.seconds for s in stats)

    def overhead_ms(self) -> float:
        if not self.tasks:
            return 0.0
        return 1e3 * max(0.0, self.thread_seconds - self.task_seconds) / self.tasks


class _Engine:
    """One run of :func:`stratified_inverse`: the loop over terms, each term's passes
    handed to the runner, each finished term published in the inverse store."""

    def __init__(self, T, store: InverseStore, series: SeriesMethod, runner, opts: _Options,
                 first_bounce, memory_limit):
        self.T, self.series, self.runner, self.opts = T, series, runner, opts
        self.T_path = local_path(T.path, "transport T")  # as the workers will open it
        runner.check_paths([self.T_path])
        if opts.progress and isinstance(runner, ClusterRunner):
            # a cluster run may be long: where to watch it (the dashboard) comes first
            print(f"bigT: running on {runner.describe()}", file=sys.stderr)
        self.fb = resolve_first_bounce(T, first_bounce)
        self.policy = MemoryPolicy(memory_limit, runner.threads, T.shape[1], _max_row_nnz(T))
        self.plans = runner.plans(self.policy)
        self.store = store
        self.created = not store.path.exists() or opts.overwrite
        self.record = self.store.open_or_create(
            _fingerprint(T, self.fb, opts.prune, series.name, opts.prune_feed,
                         opts.prune_operator),
            overwrite=opts.overwrite)
        runner.check_paths([str(store.path)])
        if self.record.tile_size is None:
            ts = choose_tile_size(T.shape[0], T.tile_size, runner.threads)
            self._save(self.record.replace(tile_size=ts, excluded_pixels=self.fb.excluded))
        self.tile_size = self.record.tile_size
        n_blocks = -(-T.shape[0] // self.tile_size)
        self.kernel_threads = 1 if n_blocks >= runner.threads else runner.idle_kernel_threads
        self.shared = {"finv": self.fb.finv, "f": self.fb.f, "active": self.fb.active}
        self.products = 0
        self.timing = _PassTiming()
        # the residual probes and X Z for the term held (None: unknown, X is read)
        self.probes = residual_probes(self.fb, seed=opts.seed)
        self.XZ: np.ndarray | None = None

    def _save(self, record) -> None:
        self.store.save(record)
        self.record = record

    # --- the run --------------------------------------------------------------------

    def run(self, t_start: float) -> InverseReport:
        resumed_from = self.record.term
        try:
            t0 = time.perf_counter()
            rho = self._spectral_radius()
            t_rho = time.perf_counter() - t0
            if self.record.term is None:
                self._term_zero()
        except BaseException:
            # refused (a diverging series) or stopped before any term was finished: an
            # output this run created holds nothing worth keeping
            if self.created and self.record.term is None:
                self.store.discard()
            raise
        try:
            stopped = self._extend(resumed_from)
        finally:
            self.store.settle()
        if self.record.dir is not None:
            self.store.clean(keep={self.record.dir})  # terms readers held when dropped
        return self._report(stopped, resumed_from, t_rho, time.perf_counter() - t_start, rho)

    def _spectral_radius(self) -> SpectralRadius:
        """rho(M), estimated once per store (kept in the record); a series that may
        diverge (rho + its uncertainty >= 1) is refused unless forced."""
        rec = self.record
        # a record without an uncertainty was made by the older power iteration, which
        # reads low on crowded spectra: estimated again
        if rec.spectral_radius is None or rec.spectral_uncertainty is None:
            rho = spectral_radius(self._apply_M, self.T.shape[0], self.fb.active,
                                  seed=self.opts.seed, nonpositive=self._m_nonpositive())
            if rho.converged:  # else estimated anew on the next run
                self._save(rec.replace(spectral_radius=rho.value,
                                       spectral_uncertainty=rho.uncertainty,
                                       spectral_products=rho.products))
        else:
            rho = SpectralRadius(rec.spectral_radius, rec.spectral_uncertainty,
                                 rec.spectral_products or 0, "recorded")
        if not rho.upper < 1 and not self.opts.force:
            raise DivergenceError(
                f"the spectral radius of M = I - T F^-1 is {rho.describe()}, so it may be "
                f">= 1 (first bounce {self.fb.kind}): the series diverges. Try the "
                "diagonal first bounce, a higher threshold on T's small entries (or "
                "denoising it), fixing negative or zero diagonal entries, or {option} "
                "to run anyway", self.T.path, option=("force", True))
        return rho

    def _extend(self, resumed_from) -> str:
        """Compute terms until ``terms`` is held, ``tol`` is reached or the series is
        exhausted; returns why it stopped."""
        terms, rec = self.opts.terms, self.record
        if rec.exhausted_at is not None and rec.term < terms:
            self._save(rec.replace(term=terms))
            return f"series exhausted at term {rec.exhausted_at}"
        computed = False
        if resumed_from is not None and self.opts.on_term and self.record.term < terms:
            # the term held may already be enough: the callback sees it before any work
            reason = self.opts.on_term(self.record)
            if reason:
                return reason
        while self.record.term < terms:
            if self._tol_reached():
                return f"tol {self.opts.tol:g} reached"
            computed = True
            reason = self._next_term()
            if reason:
                return reason
            reason = self.opts.on_term(self.record) if self.opts.on_term else None
            if reason:
                return reason
        if self._tol_reached():
            return f"tol {self.opts.tol:g} reached"
        if resumed_from is not None and not computed:
            return f"already held term {self.record.term}"
        return "terms reached"

    def _tol_reached(self) -> bool:
        h = self.record.history
        return (self.opts.tol is not None and bool(h) and h[-1].residual is not None
                and h[-1].residual <= self.opts.tol)

    def _term_zero(self) -> None:
        self.store.clean(keep={0})
        t0 = time.perf_counter()
        stats = self._run_pass(TERM_ZERO, 0)
        self._finish_term(0, stats, t0, XZ=self.fb.finv[:, None] * self.probes)

    def _next_term(self) -> str | None:
        """Compute the term after the one held and publish it; a reason when the series
        turns out exhausted instead."""
        held = self.record.term
        k = self.series.next_term(held)
        self._warn_row_width(held, k)
        self.store.clean(keep={held, k})
        t0 = time.perf_counter()
        stats = []
        for p in self.series.passes(held, k):
            reason = self._exhausted(p, held)
            if reason:
                self._save(self.record.replace(term=self.opts.terms, exhausted_at=held))
                return reason
            stats += self._run_pass(p, k)
        self._finish_term(k, stats, t0, XZ=self._updated_XZ(stats))
        # the caches let go of the held term first: their open stores hold its lease
        self.runner.end_pass(None, forget=(str(self.store.path / term_dir(held)),))
        # deleted while the next term computes; the run waits for it before it returns
        self.store.drop_term(held, background=True)
        return None

    def _updated_XZ(self, stats: list[BlockStats]) -> np.ndarray | None:
        """X_k Z, shape (n, p), from X_{k-1} Z and every row block's
        (X_k - X_{k-1}) Z, when the term's tasks all reported theirs (the power form's
        do); else None."""
        n_blocks = -(-self.T.shape[0] // self.tile_size)
        if self.XZ is None or len(stats) != n_blocks or any(s.y is None for s in stats):
            return None
        XZ = self.XZ.copy()
        for s in stats:
            start = s.index * self.tile_size
            XZ[start:start + s.y.shape[0]] += s.y
        return XZ

    def _exhausted(self, p: Pass, held: int) -> str | None:
        for _alias, name, term in p.inputs:
            reason = self.series.exhausted(held, name, open_store(self.store.term_path(term, name)))
            if reason:
                return reason
        return None

    # --- passes ---------------------------------------------------------------------

    def _run_pass(self, p: Pass, k: int) -> list[BlockStats]:
        """Create (or resume) the pass's output stores, run a task per row block not yet
        complete in all of them, finalize them from their row markers."""
        paths = {name: self.store.prepare_term_store(k, name, self._term_attrs(k))
                 for name in p.outputs}
        n_blocks = -(-self.T.shape[0] // self.tile_size)
        done = [set(completed_rows(path, n_blocks)) for path in paths.values()]
        todo = [i for i in range(n_blocks) if any(i not in d for d in done)]
        stats = []
        if todo:
            t0 = time.perf_counter()
            spec = self._spec(p, k, paths)
            try:
                shared = {**self.shared, "Z": self.probes} if p.probed else self.shared
                stats = self.runner.map(spec, row_blocks(self.T.shape[0], self.tile_size, todo),
                                        shared, progress=self.opts.progress,
                                        desc=f"term {k} {p.op}")
            finally:
                self.runner.end_pass(spec.pass_id)
            self.timing.add(time.perf_counter() - t0, stats, self.runner.threads)
        for name in p.outputs:
            self.store.finalize_term_store(k, name)
        self.products += sum(s.computed for s in stats)
        return stats

    def _spec(self, p: Pass, k: int, paths: dict) -> PassSpec:
        inputs = tuple((alias, str(self.store.term_path(term, name)))
                       for alias, name, term in p.inputs)
        return PassSpec(
            op=p.op, term=k, task=p.task, T=self.T_path, first_bounce=self.fb.digest,
            zero_diagonal=self.fb.zero_diagonal, n=self.T.shape[0],
            block_rows=self.tile_size, dtype=np.dtype(self.T.dtype).name, memory=self.policy,
            inputs=inputs, scaled=p.scaled,
            outputs=tuple((name, str(path)) for name, path in paths.items()),
            right=p.right, threshold=self.opts.prune, feed_threshold=self.opts.prune_feed,
            operator_threshold=self.opts.prune_operator,
            kernel_threads=self.kernel_threads,
            pass_id=new_pass_id())

    def _term_attrs(self, k: int) -> StoreAttrs:
        meta = {"inverse": {**self._term_metadata(), "term": k, "complete": False}}
        return StoreAttrs(self.T.shape, self.tile_size, self.T.dtype, metadata=meta,
                          pixel_order=self.T.pixel_order)

    def _term_metadata(self) -> dict:
        meta = {"method": self.series.name, "prune": self.opts.prune,
                "first_bounce": self.fb.kind, "spectral_radius": self.record.spectral_radius,
                "excluded_pixels": self.fb.excluded}
        for name in ("prune_feed", "prune_operator"):  # when set (bigT info shows them)
            if getattr(self.opts, name) is not None:
                meta[name] = getattr(self.opts, name)
        return meta

    def _finish_term(self, k: int, stats: list[BlockStats], t0: float,
                     XZ: np.ndarray | None = None) -> None:
        """Estimate term k's residual, then publish it (redirect and record). ``XZ``
        is X_k Z for the probes when known; else X_k is read to compute it."""
        X = open_store(self.store.term_path(k, "X"))
        t_res = time.perf_counter()

        def apply_X(Z: np.ndarray) -> np.ndarray:
            nonlocal XZ
            if XZ is None:
                XZ = self._apply_X(X, Z)
            return XZ

        # the same probes at every term, so that two terms' residuals compare exactly
        res_rel, res_abs = estimate_residual(self._apply_M, apply_X, self.fb,
                                             seed=self.opts.seed)
        self._check_residual_falls(k, res_rel)
        now = time.perf_counter()
        rec = TermRecord(
            term=k, seconds=now - t0,
            nnz_P=int(sum(s.nnz_P for s in stats)), nnz_X=int(X.nnz),
            tiles_computed=int(sum(s.computed for s in stats)),
            tiles_skipped=int(sum(s.skipped for s in stats)),
            rows_skipped=int(sum(1 for s in stats if s.row_skipped)),
            residual=res_rel, residual_abs=res_abs,
            multiply_adds=int(sum(s.multiply_adds for s in stats)),
            kernel_seconds=float(sum(s.kernel_seconds for s in stats)),
            residual_seconds=now - t_res)
        record = self.record.replace(term=k, dir=k, residual=res_rel,
                                     history=self.record.history + (rec,))
        meta = {**self._term_metadata(), "term": k, "dir": k, "residual": res_rel,
                "residual_abs": res_abs, "record": rec.to_dict()}
        self.store.publish(record, X, meta)
        self.record = record
        self.XZ = XZ

    def _check_residual_falls(self, k: int, residual: float) -> None:
        """Refuse term k (unless forced) when its residual grew from the held term's and
        exceeds the smallest so far ``config.RESIDUAL_GROWTH`` times: the series
        diverges, whatever the spectral radius estimate said. The held term stays
        published."""
        h = [r for r in self.record.history if r.residual is not None]
        if self.opts.force or not h:
            return
        before = h[-1].residual
        if residual > before and residual > config.RESIDUAL_GROWTH * min(r.residual for r in h):
            raise DivergenceError(
                f"the residual grew from {before:.3e} at term {h[-1].term} to {residual:.3e} "
                f"at term {k}: the series diverges (spectral radius estimate "
                f"{self.record.spectral_radius}). The inverse keeps term {h[-1].term}; "
                "{option} goes on anyway", self.store.path, option=("force", True))

    # --- mat-vecs -------------------------------------------------------------------

    def _apply_M(self, V: np.ndarray, largest: bool = False) -> np.ndarray:
        spec = matvec_spec("largest-M" if largest else "matvec-M", self.T_path,
                           self.T.shape[0], self.tile_size, self.T.dtype, memory=self.policy,
                           T=self.T_path, first_bounce=self.fb.digest,
                           zero_diagonal=self.fb.zero_diagonal, largest=largest)
        return matvec(self.runner, spec, V, self.shared)

    def _m_nonpositive(self) -> bool:
        """Whether M = I - T F^-1 has no positive entry (a transport with no negative
        entry and F = diag T): one pass over M's rows, which the spectral radius's
        products then find in the tile cache."""
        largest = self._apply_M(np.zeros((self.T.shape[0], 1)), largest=True)
        return bool(largest.max(initial=0.0) <= 0.0)

    def _apply_X(self, X, V: np.ndarray) -> np.ndarray:
        spec = matvec_spec("matvec-X", str(X.path), X.shape[0], X.tile_size, X.dtype,
                           memory=self.policy, cache_tiles=False)
        return matvec(self.runner, spec, V)

    # --- reporting ------------------------------------------------------------------

    def _warn_row_width(self, held: int, k: int) -> None:
        """Warn before a term whose output tile rows may not fit the memory plan."""
        X = StoreOperand(open_store(self.store.term_path(held, "X")))
        widest = max((X.row_bytes(j) for j in range(X.grid[0])), default=0)
        h = self.record.history
        growth = 1.0
        # X_0 = F^-1 is a diagonal: its growth to X_1 (T's width) predicts nothing
        if len(h) >= 2 and h[-2].term >= 1 and h[-2].nnz_X:
            growth = h[-1].nnz_X / h[-2].nnz_X
        tightest = min(self.plans.values(), key=lambda p: p.work_bytes_per_task)
        warn_if_rows_outgrow(tightest, widest, growth, k, self.store.path)

    def _memory_text(self) -> str:
        if len(self.plans) == 1:
            return next(iter(self.plans.values())).describe()
        return "; ".join(f"{addr}: {plan.describe()}" for addr, plan in sorted(self.plans.items()))

    def _report(self, stopped, resumed_from, t_rho, seconds, rho) -> InverseReport:
        rec = self.record
        return InverseReport(
            path=str(self.store.path), terms=rec.term, requested_terms=self.opts.terms,
            method=self.series.name, prune=self.opts.prune, prune_feed=self.opts.prune_feed,
            prune_operator=self.opts.prune_operator, first_bounce=self.fb.kind,
            spectral_radius=rho.value, spectral_uncertainty=rho.uncertainty,
            excluded_pixels=self.fb.excluded, residual=rec.residual,
            stopped=stopped, resumed_from=resumed_from, products=self.products,
            seconds=seconds, n=self.T.shape[0], nnz_T=int(self.T.nnz), history=rec.history,
            seconds_spectral_radius=t_rho, memory=self._memory_text(),
            scheduler=self.runner.describe(), threads=self.runner.threads,
            tile_size=self.tile_size,
            tasks=self.timing.tasks, task_overhead_ms=self.timing.overhead_ms(),
            peak_memory=tuple(sorted(self.runner.peak_memory().items())))

