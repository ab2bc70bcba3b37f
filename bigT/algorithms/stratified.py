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

Residual: after every term, ||I - T X||_F is estimated from p = config.RESIDUAL_PROBES
Rademacher probes z (z_i = +-1 on the pixels kept): r = z - T (X z); since
E[z z^T] = D, E||r||^2 = ||(I - T X) D||_F^2, so (1/p) sum ||r||^2 is an unbiased
estimate of its square (with unit probes z/sqrt(n) this is the n/p sum ||r||^2 of
the issue). The report gives the relative value ||I - T X||_F / sqrt(n_kept) (the rms
of the columns of I - T X), which ``tol`` is compared with, and the absolute one.
T (X z) is computed as u - M u with u = F X z, the same T on the kept pixels.

Out of core and resumable: the inverse store ``out`` is a versioned bigT store. Term k
is written to a new subgroup ``tKKKK`` (X and, for the power form, P) with
``BlockCSRWriter``; only when it is complete (and its residual estimated and recorded
in its own metadata) does ``bigT.storage.set_redirect`` point the root at it (one atomic
rename), and then the previous subgroup is deleted. A crash or Ctrl-C leaves the
previous term readable; rerunning the same call resumes at the first incomplete tile
row of the next term (the writers' resume). The root's attribute ``bigT_inverse``
records the parameters (refused if they differ), the term held, the spectral radius
and the per-term history; ``bigT info`` shows the X store's ``metadata["inverse"]``.

Paper §5.1 note: the printed eqs. 35-41 are not consistent with the printed T of eq. 34
(eq. 37's diagonal is not the inverse of eq. 36's; eq. 38 is not symmetric where T is).
The tests compare with values computed independently (dense numpy) from eq. 34.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import threading
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .. import config
from ..errors import DivergenceError, NotSquareError, StoreError
from ..schedule import graph, tasks
from ..schedule._backend import BlockCSRWriter, open_store, set_redirect
from ..schedule.memory import MemoryPlan, plan_memory, warn_if_rows_outgrow
from ..schedule.operators import MOperand, StoreOperand, TileCache
from .first_bounce import FirstBounce, resolve_first_bounce

METHODS = ("power", "horner", "newton-schulz")
_FORMAT = 1


@dataclass
class TermRecord:
    """One row of the report: the state after term ``term``."""

    term: int
    seconds: float
    nnz_P: int
    nnz_X: int
    tiles_computed: int
    tiles_skipped: int
    rows_skipped: int
    residual: float | None
    residual_abs: float | None


@dataclass
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
    history: list[TermRecord] = field(default_factory=list)
    seconds_spectral_radius: float = 0.0
    memory: str = "no memory limit"

    def to_dict(self) -> dict:
        return asdict(self)

    def table(self) -> str:
        head = (f"{'term':>4} {'time s':>8} {'nnz(P)':>12} {'nnz(X)':>12} "
                f"{'tiles done':>10} {'skipped':>8} {'residual':>10}")
        lines = [head, "-" * len(head)]
        for r in self.history:
            res = "-" if r.residual is None else f"{r.residual:.3e}"
            lines.append(f"{r.term:>4} {r.seconds:>8.2f} {r.nnz_P:>12d} {r.nnz_X:>12d} "
                         f"{r.tiles_computed:>10d} {r.tiles_skipped:>8d} {res:>10}")
        rho = "-" if self.spectral_radius is None else f"{self.spectral_radius:.4f}"
        lines.append(f"spectral radius estimate {self.seconds_spectral_radius:.2f} s, "
                     f"total {self.seconds:.2f} s")
        lines.append(f"held term {self.terms} ({self.method}, prune {self.prune:g}, "
                     f"first bounce {self.first_bounce}), spectral radius of M {rho}, "
                     f"{self.excluded_pixels} pixels left out, stopped: {self.stopped}")
        lines.append(self.memory)
        return "\n".join(lines)


# --- the versioned inverse store -------------------------------------------------------

#: Attribute of the root group of ``out`` holding the engine's record (next to the
#: storage layer's ``bigT`` attribute, which holds the redirect).
INVERSE_ATTR = "bigT_inverse"


def _root_json(out):
    return os.path.join(out, "zarr.json")


def _read_root(out) -> dict | None:
    try:
        with open(_root_json(out)) as f:
            return json.load(f)
    except FileNotFoundError:
        return None


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def _write_json_atomic(path, obj):
    tmp = f"{path}.tmp-{os.getpid()}-{threading.get_ident()}"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1, allow_nan=False)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _write_inverse(out, inverse):
    """Replace the engine's record in the root's attributes (one atomic rename)."""
    root = _read_root(out) or {"zarr_format": 3, "node_type": "group", "attributes": {}}
    root.setdefault("attributes", {})[INVERSE_ATTR] = _jsonable(inverse)
    _write_json_atomic(_root_json(out), root)


def _reconcile(out, inv):
    """Adopt the term the redirect points at when the root's record lags behind it
    (a crash between the flip and the record)."""
    try:
        cur = open_store(out)
    except StoreError:
        return
    rec = (cur.metadata or {}).get("inverse") or {}
    d = rec.get("dir")
    if d is not None and (inv.get("dir") is None or d > inv["dir"]):
        inv.update(term=d, dir=d, residual=rec.get("residual"))
        if rec.get("record"):
            inv.setdefault("history", []).append(rec["record"])
        _write_inverse(out, inv)


def _term_dir(k: int) -> str:
    return f"t{k:04d}"


class _Versioned:
    """The inverse store ``out``: its root attributes and term subgroups."""

    def __init__(self, out: str):
        self.out = os.fspath(out)

    def sub(self, k: int, name: str) -> str:
        return os.path.join(self.out, _term_dir(k), name)

    def store_if_complete(self, k, name):
        path = self.sub(k, name)
        if not os.path.exists(path):
            return None
        try:
            return open_store(path)
        except StoreError:
            return None

    def writer(self, k, name, T, metadata):
        path = self.sub(k, name)
        resume = os.path.exists(path)
        return BlockCSRWriter(path, T.shape, tile_size=T.tile_size, dtype=np.dtype(T.dtype).name,
                              pixel_order=getattr(T, "pixel_order", None),
                              metadata=_jsonable(metadata), resume=resume)

    def clean(self, keep: set[int]):
        """Delete term subgroups other than ``keep`` (left by a crash after a flip)."""
        for name in os.listdir(self.out):
            m = re.fullmatch(r"t(\d{4})", name)
            if m and int(m.group(1)) not in keep:
                shutil.rmtree(os.path.join(self.out, name), ignore_errors=True)


# --- helpers ------------------------------------------------------------------------------

def parse_bytes(value) -> int | None:
    """``2GiB``, ``500MB``, ``1e9`` or an int -> bytes."""
    if value is None or isinstance(value, int):
        return value
    s = str(value).strip()
    m = re.fullmatch(r"([0-9.eE+]+)\s*([KMGT]?i?B?)?", s, flags=re.I)
    if not m:
        raise ValueError(f"memory_limit: cannot read {value!r} (try 2GiB)")
    num = float(m.group(1))
    unit = (m.group(2) or "").upper().rstrip("B")
    mult = {"": 1, "K": 1e3, "M": 1e6, "G": 1e9, "T": 1e12,
            "KI": 1024, "MI": 1024**2, "GI": 1024**3, "TI": 1024**4}[unit]
    return int(num * mult)


def _fingerprint(T, fb: FirstBounce, prune: float, method: str) -> dict:
    import hashlib

    h = hashlib.sha1()
    h.update(np.asarray(T.tile_indptr, dtype=np.int64).tobytes())
    h.update(np.asarray(T.tile_indices, dtype=np.int64).tobytes())
    h.update(np.asarray(T.tile_nnz, dtype=np.int64).tobytes())
    return {
        "format": _FORMAT,
        "T": {"path": os.path.abspath(T.path), "shape": list(T.shape), "nnz": int(T.nnz),
              "tile_size": int(T.tile_size), "dtype": str(np.dtype(T.dtype)),
              "tiles": h.hexdigest()[:16]},
        "prune": float(prune),
        "method": method,
        "first_bounce": {"kind": fb.kind, "digest": fb.digest},
    }


def _memory_plan(T, memory_limit, workers) -> MemoryPlan:
    """The run's memory plan (:mod:`bigT.schedule.memory`) for T's largest tile row."""
    indptr = np.asarray(T.tile_indptr)
    tile_nnz = np.append(np.asarray(T.tile_nnz, dtype=np.int64), 0)
    row_nnz = np.add.reduceat(tile_nnz, indptr[:-1]) * (np.diff(indptr) > 0)
    return plan_memory(memory_limit, workers, T.shape[1], int(row_nnz.max(initial=0)))


def _whole_limit(plan: MemoryPlan, cache: TileCache, right) -> int:
    """Bytes the pass's right factor may take when held whole and shared.

    Its own share, or, when it needs more, the tile cache's share too (the cache is
    shrunk for the pass): a factor read in batches is re-read for every chunk of output
    rows, which costs far more than rebuilding M's tile rows from T.
    """
    if right is None or right.nbytes <= plan.whole_bytes:
        return plan.whole_bytes
    if right.nbytes <= plan.whole_bytes + plan.cache_bytes:
        cache.resize(plan.whole_bytes + plan.cache_bytes - right.nbytes)
        return right.nbytes
    return plan.whole_bytes


def _check_row_width(plan, Xprev, history, term, out):
    """Warn before a term whose output tile rows may not fit the memory plan."""
    Xop = StoreOperand(Xprev)
    widest = max((Xop.row_bytes(j) for j in range(Xprev.grid[0])), default=0)
    growth = 1.0
    # X_0 = F^-1 is a diagonal: its growth to X_1 (T's width) predicts nothing
    if len(history) >= 2 and history[-2].term >= 1 and history[-2].nnz_X:
        growth = history[-1].nnz_X / history[-2].nnz_X
    warn_if_rows_outgrow(plan, widest, growth, term, out)


class _Progress:
    def __init__(self, enabled, total, desc):
        self.bar = None
        if enabled and total:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="tile row", leave=False)

    def __call__(self, k):
        if self.bar is not None:
            self.bar.update(k)

    def close(self):
        if self.bar is not None:
            self.bar.close()


# --- the estimates -----------------------------------------------------------------------

def _m_matvec(M: MOperand, V, client, workers, tag):
    return graph.matvec(f"matvec-M-{tag}", M.row_matvec(V), M.grid[0], M.row_range, V,
                        token_parts=(M.T.path,), client=client, workers=workers)


def estimate_spectral_radius(M: MOperand, active, iterations=None, seed=0, client=None,
                             workers=2) -> float:
    """rho(M) by power iteration (at most ``config.SPECTRAL_RADIUS_ITERATIONS`` mat-vecs,
    each streaming the tiles of M): the geometric mean of the growth ||M v|| / ||v|| over
    the second half of the iterations (robust to a two-cycle from a +-rho pair).

    Stops early, after at least ``config.SPECTRAL_RADIUS_MIN_ITERATIONS``, once two
    estimates two iterations apart (both over an even window, so a two-cycle averages
    out) agree to ``config.SPECTRAL_RADIUS_RTOL``: each mat-vec re-reads T from disk when
    the tile cache cannot hold it."""
    iterations = iterations or config.SPECTRAL_RADIUS_ITERATIONS
    rng = np.random.default_rng(seed)
    v = rng.standard_normal((M.shape[0], 1)) * active[:, None]
    nv = np.linalg.norm(v)
    if nv == 0:
        return 0.0
    v /= nv
    logs = []
    previous = None
    for it in range(iterations):
        w = _m_matvec(M, v, client, workers, f"rho{it}")
        nw = float(np.linalg.norm(w))
        if nw == 0 or not np.isfinite(nw):
            return 0.0 if nw == 0 else float("inf")
        logs.append(math.log(nw))
        v = w / nw
        if len(logs) >= config.SPECTRAL_RADIUS_MIN_ITERATIONS and len(logs) % 2 == 0:
            estimate = math.exp(np.mean(logs[len(logs) // 2:]))
            if previous is not None and abs(estimate - previous) <= \
                    config.SPECTRAL_RADIUS_RTOL * estimate:
                return float(estimate)
            previous = estimate
    h = len(logs) // 2
    return float(math.exp(np.mean(logs[h:])))


def estimate_residual(M: MOperand, X, fb: FirstBounce, probes=None, seed=0, client=None,
                      workers=2) -> tuple[float, float]:
    """(relative, absolute) estimate of ||I - T X||_F from Rademacher probes (module
    docstring). Relative is absolute / sqrt(number of kept pixels)."""
    p = probes or config.RESIDUAL_PROBES
    n_act = int(fb.active.sum())
    if n_act == 0:
        return 0.0, 0.0
    rng = np.random.default_rng(seed + 7919)
    Z = rng.choice(np.array([-1.0, 1.0]), size=(X.shape[0], p)) * fb.active[:, None]
    Xz = graph.matvec("matvec-X", StoreOperand(X).matvec_row, X.grid[0],
                      X.tile_row_range, Z, token_parts=(X.path,), client=client,
                      workers=workers)
    U = Xz * fb.f[:, None]
    TU = U - _m_matvec(M, U, client, workers, "res")
    R = Z - TU
    abs_ = math.sqrt(float(np.sum(R * R)) / p)
    return abs_ / math.sqrt(n_act), abs_


# --- the engine ---------------------------------------------------------------------------

def stratified_inverse(T, out, terms=4, prune=config.DEFAULT_PRUNE, tol=None,
                       first_bounce="diag", method="power", client=None, memory_limit=None,
                       progress=True, force=False, *, workers=2, seed=0) -> InverseReport:
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
    tol : float, optional
        Stop once the estimated relative residual ||I - T X||_F / sqrt(n) <= tol.
    first_bounce : "diag", "identity", (n,) array or path of a .npy
        F: diag(T) (Jacobi, paper §4.4), I (the naive choice, often divergent), or a
        known F, e.g. from :func:`recover_first_bounce`.
    method : "power", "horner" or "newton-schulz" (module docstring)
    client : distributed.Client or str, optional
        Run the tasks on this client (an address string connects to a scheduler);
        default: dask's local threaded scheduler with ``workers`` threads.
    memory_limit : int or str, optional
        Bytes ("2GiB") for the resident memory of the whole process. What the process
        already holds is measured, the rest is shared out by
        :func:`bigT.schedule.memory.plan_memory` (tile cache, shared right factor,
        per-task batches and partial sums); a limit too small for the fixed parts
        raises ``MemoryLimitError`` before anything is written.
    progress : bool
        tqdm progress bars.
    force : bool
        Go on although the estimated spectral radius of M is >= 1.

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
    """
    t_start = time.perf_counter()
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if int(terms) != terms or terms < 0:
        raise ValueError(f"terms must be an integer >= 0, got {terms!r}")
    terms = int(terms)
    if not prune >= 0:
        raise ValueError(f"prune must be >= 0, got {prune!r}")
    if isinstance(T, (str, os.PathLike)):
        T = open_store(T)
    if T.shape[0] != T.shape[1]:
        raise NotSquareError(f"T is {T.shape[0]} x {T.shape[1]}; the inverse needs a square "
                             "T (apply the pixel correspondence first)", T.path)
    out = os.fspath(out)
    memory_limit = parse_bytes(memory_limit)
    own_client = None
    if isinstance(client, str):
        from distributed import Client

        client = own_client = Client(client)
    try:
        return _run(T, out, terms, float(prune), tol, first_bounce, method, client,
                    memory_limit, progress, force, workers, seed, t_start)
    finally:
        if own_client is not None:
            own_client.close()


def _run(T, out, terms, prune, tol, first_bounce, method, client, memory_limit, progress,
         force, workers, seed, t_start):
    fb = resolve_first_bounce(T, first_bounce)
    plan = _memory_plan(T, memory_limit, workers)
    params = _fingerprint(T, fb, prune, method)
    vs = _Versioned(out)
    inv = None
    if os.path.exists(out):
        root = _read_root(out)
        inv = None if root is None else root.get("attributes", {}).get(INVERSE_ATTR)
        if inv is None or "params" not in inv:
            raise StoreError("exists and is not a bigT inverse store; choose another path "
                             "or delete it", out)
        if inv["params"] != params:
            diff = [k for k in params if inv["params"].get(k) != params[k]]
            held_desc = ", ".join(f"{k}={inv['params'].get(k)}" for k in diff)
            raise StoreError(
                "holds an inverse with different " + ", ".join(diff) + " than asked "
                f"(it holds {held_desc}); "
                "rerun with the same parameters to resume, or choose another path", out)
        _reconcile(out, inv)
    else:
        os.makedirs(out)
        inv = {"params": params, "term": None, "dir": None, "history": []}
        _write_inverse(out, inv)

    # dask runs tile rows on `workers` threads; with fewer tile rows than threads the
    # kernel splits each product over the threads instead.
    kernel_threads = 1 if T.grid[0] >= workers else workers
    cache = TileCache(plan.cache_bytes)
    M = MOperand(T, fb.finv.astype(T.dtype), fb.active, fb.zero_diagonal, cache)
    held = inv.get("term")
    resumed_from = held
    history = [TermRecord(**h) for h in inv.get("history", [])]

    rho = inv.get("spectral_radius")
    t_rho = time.perf_counter()
    if rho is None:
        # Nothing else is in memory yet: the power iterations may cache all of M they
        # can (each iteration is one pass over M), the rest is given back after.
        if plan.limit is not None:
            cache.resize(plan.cache_bytes + plan.whole_bytes
                         + workers * plan.work_bytes_per_task // 2)
        rho = estimate_spectral_radius(M, fb.active, seed=seed, client=client,
                                       workers=workers)
        cache.resize(plan.cache_bytes)
        inv["spectral_radius"] = rho
        _write_inverse(out, inv)
    if rho >= 1 and not force:
        raise DivergenceError(
            f"the spectral radius of M = I - T F^-1 is about {rho:.4f} >= 1 "
            f"(first_bounce={fb.kind!r}): the series diverges. Try first_bounce='diag', "
            "a higher threshold on T's small entries (or denoising it), fixing "
            "negative or zero diagonal entries, or force=True (bigT invert --force) to run "
            "anyway", T.path)
    t_rho = time.perf_counter() - t_rho

    base_meta = {"method": method, "prune": prune, "first_bounce": fb.kind,
                 "spectral_radius": rho, "excluded_pixels": fb.excluded}
    n = T.shape[0]
    common = dict(M=M, finv=fb.finv, f=fb.f, active=fb.active, threshold=prune,
                  dtype=np.dtype(T.dtype), n=n, plan=plan)
    products = 0
    stopped = "terms reached"

    def run_pass(op, fn, writers, k, right=None, **extra):
        nonlocal products
        done = {name: set(w.completed_tile_rows) for name, w in writers.items()}
        rows = [i for i in range(T.grid[0]) if any(i not in d for d in done.values())]
        bar = _Progress(progress, len(rows), f"term {k} {op}")
        ctx = graph.Context(writers=writers, done=done,
                            kernel_threads=kernel_threads,
                            whole_limit=_whole_limit(plan, cache, right),
                            **common, **extra)
        ctx.progress = bar
        try:
            stats = graph.run_rows(op, fn, rows, ctx,
                                   token_parts=(out, k, prune, method, fb.digest),
                                   client=client, workers=workers)
        finally:
            bar.close()
            if right is not None:
                right.release()
            cache.resize(plan.cache_bytes)
        stores = {name: w.finalize() for name, w in writers.items()}
        products += sum(s["computed"] for s in stats)
        return stats, stores

    def finish_term(k, X, stats, t0):
        res_rel, res_abs = estimate_residual(M, X, fb, seed=seed + k, client=client,
                                             workers=workers)
        rec = TermRecord(
            term=k, seconds=time.perf_counter() - t0,
            nnz_P=int(sum(s["nnz_P"] for s in stats)),
            nnz_X=int(X.nnz),
            tiles_computed=int(sum(s["computed"] for s in stats)),
            tiles_skipped=int(sum(s["skipped"] for s in stats)),
            rows_skipped=int(sum(1 for s in stats if s.get("row_skipped"))),
            residual=res_rel, residual_abs=res_abs)
        # The X store records its own term first, so a crash between the flip and the
        # root's record is repaired on resume (_reconcile).
        X.update_metadata(inverse=_jsonable({**base_meta, "term": k, "dir": k,
                                             "residual": res_rel, "residual_abs": res_abs,
                                             "record": asdict(rec)}))
        set_redirect(out, f"{_term_dir(k)}/X")  # the atomic flip
        history.append(rec)
        inv.update(term=k, dir=k, residual=res_rel, history=[asdict(h) for h in history],
                   **base_meta)
        _write_inverse(out, inv)
        return rec

    def meta(k):
        return {"inverse": {**base_meta, "term": k, "complete": False}}

    # term 0: X_0 = F^-1
    if held is None:
        vs.clean(keep={0})
        t0 = time.perf_counter()
        stats, stores = run_pass("diag", tasks.diag_row, {"X": vs.writer(0, "X", T, meta(0))}, 0)
        finish_term(0, stores["X"], stats, t0)
        held = 0

    def check_tol():
        return tol is not None and history and history[-1].residual is not None \
            and history[-1].residual <= tol

    if inv.get("exhausted_at") is not None and held < terms:
        # every term after the exhausted one is exactly zero: nothing to compute
        inv.update(term=terms)
        _write_inverse(out, inv)
        held = terms
        stopped = f"series exhausted at term {inv['exhausted_at']}"
    computed_any = False
    while held < terms:
        if check_tol():
            stopped = f"tol {tol:g} reached"
            break
        prev = held
        Xprev = open_store(vs.sub(prev, "X"))
        computed_any = True
        _check_row_width(plan, Xprev, history, prev + 1, out)
        if method == "power":
            k = prev + 1
            Pprev = None if prev == 0 else open_store(vs.sub(prev, "P"))
            if Pprev is not None and Pprev.nnz == 0:
                # P_prev = 0 (M^prev pruned to nothing): every later term is exactly 0.
                stopped = f"series exhausted at term {prev} (P_{prev} = 0)"
                inv.update(term=terms, exhausted_at=prev)
                _write_inverse(out, inv)
                held = terms
                break
            vs.clean(keep={prev, k})
            t0 = time.perf_counter()
            writers = {"P": vs.writer(k, "P", T, meta(k)), "X": vs.writer(k, "X", T, meta(k))}
            P_op = None if Pprev is None else StoreOperand(Pprev, cache=cache)
            stats, stores = run_pass("power", tasks.power_row, writers, k, right=P_op,
                                     P_prev=P_op, X_prev=StoreOperand(Xprev))
        elif method == "horner":
            k = prev + 1
            vs.clean(keep={prev, k})
            t0 = time.perf_counter()
            S_op = StoreOperand(Xprev, row_scale=fb.f.astype(T.dtype), cache=cache)
            stats, stores = run_pass("horner", tasks.horner_row,
                                     {"X": vs.writer(k, "X", T, meta(k))}, k, right=S_op,
                                     S_prev=S_op)
        else:
            k = 2 * prev + 1
            vs.clean(keep={prev, k})
            t0 = time.perf_counter()
            S = StoreOperand(Xprev, row_scale=fb.f.astype(T.dtype), cache=cache)
            Rstore = vs.store_if_complete(k, "R")
            st1 = []
            if Rstore is None:
                st1, st = run_pass("ns-residual", tasks.ns_residual_row,
                                   {"R": vs.writer(k, "R", T, meta(k))}, k, right=S, S=S)
                Rstore = st["R"]
            if Rstore.nnz == 0:
                stopped = f"series exhausted at term {prev} (I - T X pruned to 0)"
                inv.update(term=terms, exhausted_at=prev)
                _write_inverse(out, inv)
                held = terms
                break
            R_op = StoreOperand(Rstore, cache=cache)
            stats, stores = run_pass("ns-update", tasks.ns_update_row,
                                     {"X": vs.writer(k, "X", T, meta(k))}, k, right=R_op,
                                     S=S, R=R_op)
            stats = [{**s, "nnz_P": 0} for s in stats] + st1
        # only M's tile rows serve the next term; the previous term's are stale
        cache.drop_where(lambda path: path != T.path)
        finish_term(k, stores["X"], stats, t0)
        shutil.rmtree(os.path.join(out, _term_dir(prev)), ignore_errors=True)
        held = k
    else:
        if check_tol():
            stopped = f"tol {tol:g} reached"

    if resumed_from is not None and not computed_any and stopped == "terms reached":
        stopped = f"already held term {held}"
    last = history[-1] if history else None
    return InverseReport(
        path=out, terms=held, requested_terms=terms, method=method, prune=prune,
        first_bounce=fb.kind, spectral_radius=rho, excluded_pixels=fb.excluded,
        residual=None if last is None else last.residual, stopped=stopped,
        resumed_from=resumed_from, products=products,
        seconds=time.perf_counter() - t_start, n=T.shape[0], nnz_T=int(T.nnz),
        history=history, seconds_spectral_radius=t_rho, memory=plan.describe())
