"""The stratified inverse chosen from a target error of the compensated image.

``invert_to_target(T, out, target)`` runs :func:`~bigT.algorithms.stratified_inverse`
term by term (each call resumes the store at the next term) and chooses the method,
the prune threshold and the number of terms that bring the compensation error of a
few probe images below ``target``, at the least cost it can predict. It is a layer
over the engine: the engine's store, record and report are those of a fixed-setting
run with the chosen values.

What is measured
----------------
The compensated error of a desired image d is e(d) = ||T clip(X d) - d|| / ||d||. The
inverse controls the unclipped part, ||(I - T X) d|| / ||d||: clipping depends on the
scene's gamut (a dark wall cannot show 0.8 whatever X is), and the unclipped error is
scale-free, so it equals the clipped error of d scaled down until X d fits the
projector's [0, 1] (when X d >= 0). The decisions use the unclipped error; the report
also gives the clipped error of each probe scaled so (``clipped_errors``).

Probes (:func:`probe_images`): a constant image, a smooth gradient and low-pass
filtered noise, all in [0.2, 0.8], zero on pixels the inverse leaves out. A term
measured costs two streamed products for all probes together: Y = X D, then
T [Y, clip(s Y)] (clip(s Y) only for the probes whose X d leaves [0, 1]). The engine
runs once per (method, prune) and hands each term over as it is published
(``on_term``); a term is measured where the target may be met (the truncation part
within MEASURE_WITHIN of it), at terms 4, 8, 16, ... and at every Newton-Schulz step.

Decomposing the error
---------------------
Without pruning, I - T T_k^-1 = M^(k+1) (M = I - T F^-1), so the truncation part of
the error of T_k^-1 on the probes, ||M^(k+1) d|| / ||d||, is computed before any term
by k+1 products with T (matrix-free, a pass over T each, far cheaper than a sparse
product): it gives the number of terms the series needs (:func:`predicted_curve`:
the last point, which the curve's last ratio puts under the goal, is counted before
it is computed, and computed only if a term measured needs it). With no memory limit
(and T within the tile cache's budget, a store of format 2) T's tile rows are read once and held through
the search (:func:`held_rows`): F, the curve, the measurements and every attempt's M
in the engine are taken from them; else T is streamed from its store. The engine
estimates no residual of its own (``on_term.needs_residual``): the probes' errors
decide, and the terms' records hold none. After each term the measured residual
r_k = (I - T X_k) d minus M^(k+1) d is exactly what pruning added (M P_n - sum_k D_k
for the power form: docs/DESIGN.md, "Methods, pruning and carrying"), so a prune too large for the target
is seen at the first term measured (by term 4 in a long series) and the run restarts
with a smaller one instead of running into the floor.

Rules (constants below, measured by ``benchmarks/bench_target.py``)
-------------------------------------------------------------------
* stop at the first term whose worst probe's unclipped error is <= SAFETY * target.
  The probes are dominated by the slowest mode of M and agree within a few per cent;
  the 20 % margin covers a fresh image (tests/algorithms/test_target_error.py checks
  random low-pass images against the exact inverse).
* thresholds: the power form prunes P_k, the next product's factor, at
  config.TARGET_FEED_RATIO times the prune, and M in the products after the first term
  at config.TARGET_OPERATOR_RATIO times it (:func:`first_thresholds`; on the dense
  384x512 corner, 4 terms, prune 3e-6 so fed and pruned does 5x fewer multiply-adds
  than prune 1e-5 alone, at a fraction of its image error: the measurements are
  config's comments); a restart scales the three together. A store ``out``
  already holding an inverse of T starts from the setting it records.
* prune: the largest step of PRUNE_GRID (1, 3 times a power of ten) <= target (1 - r)
  / PRUNE_RATIO, with r the rate at which the truncation curve falls per term (about
  rho(M)): pruned entries are carried by every later bounce, so their error adds up
  like 1 / (1 - r). Restart with a smaller
  step (the pruning part measured, scaled to PRUNE_SHARE of the target) when the pruning
  part exceeds PRUNE_SHARE * SAFETY * target, or the series is exhausted or stalls
  above the target; at most MAX_RESTARTS restarts.
* terms: at most the truncation curve's count + EXTRA_TERMS (a pruned series may need
  one or two more), and at most MAX_TERMS; past it the run stops best-effort
  (``met`` False, the store holds the last term).
* method (unless given): "newton-schulz" when its products (two per step, 2^j - 1
  terms after j steps) are at most NS_PRODUCT_SHARE of the power form's (n - 1 for n
  terms, the first one free), else "power". Measured on the 48x64 Cornell box at
  rho = 0.89, prune 1e-5: term 31 after 51 s by Newton-Schulz, 146 s by the power
  form. Horner is not chosen: every product multiplies by the whole S, so it loses
  where the products dominate (dense 192x256 corner, 4 terms to 1e-4: Horner 21 s,
  power fed on P_k pruned at 1e-4 6.7 s, benchmarks/RESULTS.md), and it was no more
  accurate at the same prune on the Cornell box (floor at prune 1e-5, rho = 0.52:
  2.3e-3 against power's 1.6e-3; at 6 terms, 3.7e-3 against 3.0e-3: the error of
  either is not monotone in the terms). On tiny scenes, where each term's store
  writes and X's merge dominate, it is up to ~1.5x quicker per term (one store a
  term against power's two), which the sweep's ratios at rho 0.19-0.52 show.
* a target below TARGET_FLOOR_EPS machine epsilons of T's dtype is refused: the
  rounding of T X d in that precision alone is of that order.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import BigTError
from ..kernels import spmm_dense
from ..kernels.threads import run_on_threads
from ..schedule.runner import ThreadRunner
from ..schedule.stream import compute_dtype, forget_tiles, stream_matmul
from ..storage import as_store
from ..storage import open as open_store
from ..storage.frames import pixel_order_of, to_vectors
from . import defaults
from .fingerprint import recorded_setting
from .first_bounce import first_bounce_of_rows, resolve_first_bounce
from .run_setup import TileRows
from .settings import Thresholds
from .stratified import stratified_inverse

#: Stop when the worst probe's error is below SAFETY * target.
SAFETY = 0.8
#: The first prune tried: the largest step of PRUNE_GRID <= target (1 - rate) /
#: PRUNE_RATIO.
PRUNE_RATIO = 50.0
#: The prune's steps in each decade: 1 and 3 (a step of ~3x, not 10x: on the dense
#: 384x512 corner at 5e-4, 7.5e-6 became 1e-6 by decades; by 1-3 steps, 3e-6, whose
#: inverse holds fewer entries at no larger error: benchmarks/bench_defaults.py).
PRUNE_GRID = (1, 3)
#: The pruning part must exceed the truncation part this many times to be a floor.
FLOOR_DOMINANCE = 2.0
#: The pruning part may take this share of the (safe) target before a restart.
PRUNE_SHARE = 0.5
#: Terms allowed beyond the unpruned series' count.
EXTRA_TERMS = 3
MAX_TERMS = 200
MAX_RESTARTS = 3
TARGET_FLOOR_EPS = 64
#: Newton-Schulz is chosen when its products are at most this share of power's.
NS_PRODUCT_SHARE = 0.5
#: A term is measured once the truncation part alone is within this factor of the
#: safe target: the pruning part may cancel much of it (M = -|M| alternates in sign;
#: on the rho = 0.52 Cornell box, term 6 of prune 1e-5 measured 2.97e-3 against a
#: truncation part of 7.5e-3, a factor 2.5). Not more: each term measured costs two
#: streamed products and, in memory, the term's write (on the dense 384x512 corner at
#: the default target, term 3's truncation part 9.3e-4 against 3 x 2.4e-4: not
#: measured; measured, it erred 4.5e-4, above the target, ~2.5 s for nothing).
MEASURE_WITHIN = 3.0


@dataclass(frozen=True)
class TermErrors:
    """The probes' errors after one term.

    Attributes
    ----------
    term : int
    seconds : float, wall time of the run up to and including this term and its check
    errors : tuple of float, unclipped ||(I - T X) d|| / ||d|| per probe
    truncation : float, worst probe's ||M^(term+1) d|| / ||d|| (the unpruned series)
    pruning : float, worst probe's ||(I - T X) d - M^(term+1) d|| / ||d||
    clipped_errors : tuple of float, ||T clip(s X d) - s d|| / ||s d|| per probe, with s
        the scale that brings max(X d) to 1 (1 when it is already below)
    """

    term: int
    seconds: float
    errors: tuple[float, ...]
    truncation: float
    pruning: float
    clipped_errors: tuple[float, ...]

    @property
    def worst(self) -> float:
        return max(self.errors)


@dataclass(frozen=True)
class Attempt:
    """One run at a fixed (method, thresholds): its terms' errors and why it ended;
    ``feed`` and ``operator`` are the power form's ``prune_feed`` and
    ``prune_operator`` (None: not set)."""

    method: str
    prune: float
    terms: tuple[TermErrors, ...]
    ended: str
    feed: float | None = None
    operator: float | None = None

    @property
    def thresholds(self) -> Thresholds:
        return Thresholds(self.prune, self.feed, self.operator)


@dataclass(frozen=True)
class TargetReport:
    """What :func:`invert_to_target` chose and measured.

    Attributes
    ----------
    target : float, the relative error asked for
    met : bool, the worst probe's unclipped error <= target at the held term
    method, prune, terms : the setting the store holds (as a fixed run would)
    prune_feed, prune_operator : the power form's thresholds on P_k and on M in the
        products, as the store records them (None: not set)
    why : str, one sentence: why this setting
    error : float, the worst probe's unclipped error at the held term
    clipped_error : float, the worst probe's clipped error at the held term
    probes : tuple of str, the probe images' names
    predicted_terms : int, terms the unpruned series needs (truncation curve)
    spectral_radius : float or None, the engine's estimate of rho(M)
    seconds : float, the whole run
    restarts : tuple of str, one line per restart
    attempts : tuple of Attempt, every (method, prune) tried, the last one held
    inverse : dict, the engine's last :class:`InverseReport` as a dict
    """

    target: float
    met: bool
    method: str
    prune: float
    terms: int
    why: str
    error: float
    clipped_error: float
    probes: tuple[str, ...]
    predicted_terms: int
    spectral_radius: float | None
    seconds: float
    restarts: tuple[str, ...] = ()
    attempts: tuple[Attempt, ...] = ()
    inverse: dict = field(default_factory=dict)
    prune_feed: float | None = None
    prune_operator: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        """A readable account: the choice, why, the per-term errors, the restarts."""
        head = f"{'term':>4} {'time s':>8} {'worst err':>10} {'truncation':>10} {'pruning':>10}"
        lines = [f"target error {self.target:.3g}: "
                 + ("met" if self.met else "NOT met (best effort)")
                 + f", worst probe {self.error:.3e} (clipped into the projector's range "
                 f"{self.clipped_error:.3e}) on {len(self.probes)} probes "
                 f"({', '.join(self.probes)})",
                 f"chosen: {self.method}, "
                 f"{Thresholds(self.prune, self.prune_feed, self.prune_operator).describe()}, "
                 f"{self.terms} terms, "
                 f"{self.seconds:.1f} s",
                 f"why: {self.why}"]
        for line in self.restarts:
            lines.append(f"restart: {line}")
        lines += [head, "-" * len(head)]
        for t in self.attempts[-1].terms if self.attempts else ():
            lines.append(f"{t.term:>4} {t.seconds:>8.2f} {t.worst:>10.3e} "
                         f"{t.truncation:>10.3e} {t.pruning:>10.3e}")
        return "\n".join(lines)


# --- probes ------------------------------------------------------------------------

PROBE_NAMES = ("constant", "gradient", "low-pass noise")


def probe_images(shape: tuple[int, int], seed: int = 0, channels: int = 1) -> np.ndarray:
    """The probe images, shape (3, H, W) (grey) or (3, H, W, 3) (colour), float64 in
    [0.2, 0.8]: a constant 0.5, a diagonal gradient, and Gaussian-filtered noise
    (sigma ~ 1/16 of the smaller side, a natural-looking image's spectrum), stretched
    to [0.2, 0.8]. In colour the gradient runs another way in each channel and the
    noise is drawn per channel, so that the probes are coloured images (the colour
    mixing, not only the grey axis, is measured); the constant stays grey."""
    from scipy.ndimage import gaussian_filter  # ~0.3 s: only the probes' images need it

    H, W = shape
    yy, xx = np.mgrid[0:H, 0:W]
    u, v = yy / max(H - 1, 1), xx / max(W - 1, 1)
    ramps = [(u + v) / 2, (1 - u + v) / 2, (u + 1 - v) / 2][:channels]
    rng = np.random.default_rng(seed)
    noises = []
    for _ in range(channels):
        noise = gaussian_filter(rng.standard_normal((H, W)), max(1.0, min(H, W) / 16),
                                mode="wrap")
        span = np.ptp(noise)
        noises.append((noise - noise.min()) / span if span > 0 else np.full((H, W), 0.5))
    images = np.stack([np.full((channels, H, W), 0.5), 0.2 + 0.6 * np.stack(ramps),
                       0.2 + 0.6 * np.stack(noises)])  # (3, channels, H, W)
    return images[:, 0] if channels == 1 else np.moveaxis(images, 1, -1)


def probe_vectors(T, active: np.ndarray, seed: int = 0) -> np.ndarray:
    """The probes in T's pixel order, shape (n, 3), zero on pixels left out (no inverse
    can light them, so they would only add a constant to every error); colour images
    for a colour T."""
    n = T.shape[0]
    order = pixel_order_of(T, (n, 1))  # the store's own order when it records one
    D = to_vectors(probe_images(order.image_shape, seed, order.channels), order,
                   np.float64)
    return D * active[:, None]


# --- streamed products -----------------------------------------------------------------

class _Products:
    """Products with T and X, sharing one thread runner: streamed from the stores
    (T's tiles in the tile cache: the truncation curve passes over T once per term),
    or, with T's tile rows held (``rows``, :func:`held_rows`), T's from them."""

    def __init__(self, T, fb, workers: int, keep_tiles: bool = False,
                 rows: TileRows | None = None):
        self.T, self.fb, self.rows = T, fb, rows
        self.threads = max(1, int(workers))
        self.runner = ThreadRunner(self.threads)
        self.keep_tiles = keep_tiles

    def times(self, A, V: np.ndarray, cache: bool = False) -> np.ndarray:
        """A V, shape (n, k) float64: A a store, streamed; or a matrix held in memory
        (the engine's X, ``on_term``'s ``X=``), in the streamed product's precision
        (float32 for float32 entries), the same numbers."""
        if sp.issparse(A):
            dtype = np.result_type(A.dtype, np.float32)
            return spmm_dense(A, np.ascontiguousarray(V, dtype=dtype),
                              n_threads=self.threads).astype(np.float64, copy=False)
        budget = config.COMPENSATE_CACHE_BYTES if cache else 0
        return np.asarray(stream_matmul(A, V, runner=self.runner, cache_bytes=budget),
                          dtype=np.float64)

    def times_T(self, V: np.ndarray, cache: bool = True) -> np.ndarray:
        """T V, shape (n, k): from the rows held, else streamed, T's tiles kept in the
        tile cache when ``cache`` or ``keep_tiles``."""
        if self.rows is not None:
            return self._rows_times(V)
        return self.times(self.T, V, cache=cache or self.keep_tiles)

    def _rows_times(self, V: np.ndarray) -> np.ndarray:
        """T V from the tile rows held, shape (n, k) float64, a tile row per task; in
        the streamed product's precision (``compute_dtype(T)``: float32 for a float32
        T), so that the two give the same numbers and the search the same choices."""
        dtype = compute_dtype(self.T)
        V = np.ascontiguousarray(V, dtype=dtype)
        out = np.zeros((self.T.shape[0], V.shape[1]), dtype)

        def tile_rows(first: int, end: int) -> None:
            for i in range(first, end):
                start, stop = self.T.tile_row_range(i)
                spmm_dense(self.rows[i], V, out=out[start:stop], n_threads=1)

        # the kernels' shared pool, a tile row per task (not a pool made per product)
        run_on_threads(tile_rows, [(i, i + 1) for i in range(len(self.rows))], self.threads)
        return out.astype(np.float64, copy=False)

    def M(self, V: np.ndarray, cache: bool = True) -> np.ndarray:
        """M V = V - T F^-1 V on the kept pixels, shape (n, k); T's tiles kept in the
        tile cache unless ``cache`` and ``keep_tiles`` are False (between the engine's
        terms, whose M rows the cache holds under the engine's memory plan)."""
        return (V - self.times_T(self.fb.apply_inverse(V), cache=cache)) \
            * self.fb.active[:, None]

    def close(self) -> None:
        forget_tiles(self.runner, self.T)
        if self.rows is not None:
            self.rows.release()


def keeps_tiles(T, memory_limit) -> bool:
    """Whether T stays in memory during the engine's run too: with no memory limit
    (whose plan is the engine's) and T's CSR arrays within the tile cache's budget.
    Else each measurement's products with T re-read T from the store: on the dense
    384x512 corner (700 MiB of CSR), ~2 s more per term measured."""
    return memory_limit is None and T.csr_bytes() <= config.COMPENSATE_CACHE_BYTES


def held_rows(T, memory_limit, workers: int) -> TileRows | None:
    """T's tile rows, read once and held through the search (None where
    :func:`keeps_tiles` says T is not kept): F's diagonal, the truncation curve's and
    the measurements' products with T, and every attempt's M in the engine
    (``stratified_inverse(T_rows=...)``) are taken from them. Streamed instead, T was
    read three times on the dense 384x512 corner: its diagonal tiles for F (0.8 s),
    all of it into the tile cache (1.2 s), and again by the engine for M (1.0 s).

    None too for a store of format 1 (a group per tile, docs/FORMAT.md): its streamed
    product sums each row tile by tile, a held row's sums it whole, and in float32 the
    two round apart (~1e-5 measured): the measured errors, and so the search's choices,
    would no longer be the streamed search's."""
    if not keeps_tiles(T, memory_limit) or not getattr(T, "row_layout", True):
        return None
    return TileRows(T, workers, keep=True)


def _rel(R: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Column-wise ||R|| / ||D||, shape (k,)."""
    return np.linalg.norm(R, axis=0) / np.maximum(np.linalg.norm(D, axis=0), 1e-300)


def truncation_curve(products: _Products, D: np.ndarray, goal: float,
                     max_terms: int) -> list[np.ndarray]:
    """M^(k+1) D for k = 0, 1, ... until its worst relative column is <= ``goal``,
    stalls (rho >= 1, or float rounding) or ``max_terms`` is reached.

    Returns
    -------
    list of ndarray, each (n, k): element k is M^(k+1) D.
    """
    return _curve(products, D, goal, max_terms)[0]


def predicted_curve(products: _Products, D: np.ndarray, goal: float,
                    max_terms: int) -> tuple[list[np.ndarray], int]:
    """(:func:`truncation_curve` short of its last point, the terms the unpruned
    series needs): the point that its last step's ratio puts below ``goal`` is
    counted, not computed (one streamed product with T fewer; a term measured
    computes it when it needs it, :func:`_power`)."""
    return _curve(products, D, goal, max_terms, extrapolate=True)


def _curve(products, D, goal, max_terms, extrapolate=False):
    powers = [products.M(D)]
    worst = [float(_rel(powers[-1], D).max())]
    while len(powers) <= max_terms and worst[-1] > goal:
        if extrapolate and len(worst) >= 2 and worst[-1] ** 2 / worst[-2] <= goal:
            return powers, len(powers)  # M^(len+1) D predicted below the goal
        powers.append(products.M(powers[-1]))
        now = float(_rel(powers[-1], D).max())
        if now >= worst[-1]:
            break  # stalled: the engine's divergence check decides
        worst.append(now)
    return powers, len(powers) - 1


def _power(products: _Products, powers: list[np.ndarray], k: int,
           cache: bool = True) -> np.ndarray:
    """M^(k+1) D, extending ``powers`` (M^(j+1) D for j < len) where the curve stopped
    short (Newton-Schulz holds 2^j - 1 terms, past the count asked); ``cache`` as
    :meth:`_Products.M`'s."""
    while len(powers) <= k:
        powers.append(products.M(powers[-1], cache=cache))
    return powers[k]


def measure_term(products: _Products, X, D: np.ndarray, truncation: np.ndarray,
                 term: int, seconds: float) -> TermErrors:
    """The probes' errors of the inverse ``X`` (held term ``term``); ``truncation`` is
    M^(term+1) D, shape (n, k)."""
    Y = products.times(X, D)
    scale = 1.0 / np.maximum(Y.max(axis=0), 1.0)  # X d brought into [.., 1]
    Yc = np.clip(Y * scale, 0.0, 1.0)
    # a probe whose X d already lies in [0, 1] is its own clipped image: its clipped
    # error is its unclipped one, and T is multiplied by its column once, not twice
    # (on the dense 384x512 corner every probe: half of the measurement's T product)
    clips = np.flatnonzero((scale < 1.0) | (Y.min(axis=0) < 0.0))
    TY = products.times_T(np.hstack([Y, Yc[:, clips]]), cache=False)
    k = D.shape[1]
    active = products.fb.active[:, None]
    R = (D - TY[:, :k]) * active
    errors = _rel(R, D)
    clipped = errors.copy()
    clipped[clips] = _rel((D[:, clips] * scale[clips] - TY[:, k:]) * active,
                          D[:, clips] * scale[clips])
    return TermErrors(term=term, seconds=seconds, errors=tuple(map(float, errors)),
                      truncation=float(_rel(truncation, D).max()),
                      pruning=float(_rel(R - truncation, D).max()),
                      clipped_errors=tuple(map(float, clipped)))


# --- the choice ------------------------------------------------------------------------

def first_prune(target: float, rate: float = 0.0) -> float:
    """The largest step of PRUNE_GRID <= target (1 - rate) / PRUNE_RATIO (module
    docstring); ``rate`` is :func:`decay_rate`'s, in [0, 1)."""
    slack = 1.0 - min(max(rate, 0.0), 0.99)
    return grid_floor(target * slack / PRUNE_RATIO)


def grid_floor(value: float) -> float:
    """The largest m 10^e <= ``value`` with m in PRUNE_GRID (1, 3: 7.4e-6 -> 3e-06,
    2.9e-6 -> 1e-06), as a float that prints as written (3e-06, not
    3.0000000000000004e-06)."""
    exponent = math.floor(math.log10(value) + 1e-9)
    ratio = value / 10.0 ** exponent * (1 + 1e-9)
    if ratio < PRUNE_GRID[0]:  # the log's tolerance rounded up across a power of ten
        exponent, ratio = exponent - 1, ratio * 10.0
    mantissa = max(m for m in PRUNE_GRID if m <= ratio)
    return float(f"{mantissa:g}e{exponent}")


def first_thresholds(method: str, prune: float) -> Thresholds:
    """The threshold triple tried first at ``prune``: the power form feeds on P_k
    pruned at config.TARGET_FEED_RATIO times it and leaves M's entries below
    config.TARGET_OPERATOR_RATIO times it out of the products after the first term
    (the ratios of the README's recommendation, measured by
    benchmarks/bench_defaults.py to cost no visible error); the other methods have
    neither."""
    if method != "power":
        return Thresholds(float(prune))
    return Thresholds(float(prune), float(f"{prune * config.TARGET_FEED_RATIO:.3g}"),
                      float(f"{prune * config.TARGET_OPERATOR_RATIO:.3g}"))


def decay_rate(powers: list[np.ndarray], D: np.ndarray) -> float:
    """The rate at which the truncation curve falls per term (about rho(M)): the last
    step's ratio of the worst probe's ||M^(k+1) d|| / ||d||; for a curve of one point,
    that point (||M d|| / ||d||, at most rho(M)'s order). In [0, 1) when the series
    converges."""
    worst = [float(_rel(P, D).max()) for P in powers[-2:]]
    if len(worst) == 1:
        return min(worst[0], 0.99)
    return min(worst[1] / worst[0], 0.99) if worst[0] > 0 else 0.0


def floored(m: TermErrors, target: float) -> bool:
    """The pruning part will keep the error above the target: it exceeds its share of
    the safe target and dominates the truncation part. (Early on the pruning part also
    holds earlier terms' pruning carried by M, which decays like the truncation part
    and overstates the floor; once it dominates, it is mostly the floor.)"""
    return (m.pruning > PRUNE_SHARE * SAFETY * target
            and m.pruning > FLOOR_DOMINANCE * m.truncation)


def choose_method(terms: int) -> tuple[str, str]:
    """(method, why) for a series that needs ``terms`` terms (module docstring)."""
    steps = math.ceil(math.log2(terms + 1))
    if 2 * steps <= NS_PRODUCT_SHARE * max(terms - 1, 0):
        return "newton-schulz", (f"newton-schulz ({2 * steps} products for {2 ** steps - 1} "
                                 f"terms against power's {terms - 1})")
    return "power", (f"power ({max(terms - 1, 0)} products; newton-schulz would take "
                     f"{2 * steps})")


def smaller_prune(prune: float, pruning: float, target: float) -> float:
    """A step of PRUNE_GRID small enough that the pruning part (measured ``pruning`` at
    ``prune``, roughly proportional to it) takes PRUNE_SHARE / 2 of the safe target; at
    least one step smaller. (By decades, the 96x128 Cornell box at 3e-4 went from 3e-6
    to 3e-8, its pruning part then 1.9e-5 where 6e-5 was enough.)"""
    want = PRUNE_SHARE * SAFETY * target / 2
    return min(grid_floor(prune * want / max(pruning, want)), grid_floor(prune / 1.01))


def check_target(target: float, dtype) -> None:
    """Refuse a target outside (0, 1) or below what T's precision can show."""
    if not (isinstance(target, (int, float)) and 0 < target < 1):
        raise BigTError(f"target error must be a number in (0, 1), got {target!r}")
    floor = TARGET_FLOOR_EPS * float(np.finfo(np.result_type(dtype, np.float32)).eps)
    if target < floor:
        raise BigTError(f"target error {target:g} is below what T's {np.dtype(dtype).name} "
                        f"can show ({TARGET_FLOOR_EPS} machine epsilons = {floor:.1e}): "
                        "ask for a larger one or store T as float64")


@dataclass(frozen=True)
class _Setting:
    """The engine's arguments shared by every call of a run."""

    first_bounce: object
    memory_limit: object
    scheduler: object
    workers: int
    progress: bool
    seed: int


def _run_attempt(T, out, method, thresholds: Thresholds, cap, target, ctx, products, D,
                 powers, t0, overwrite):
    """Terms of one (method, thresholds) until the target, a floor or the cap: one engine
    run, each term measured as it is published (the engine's ``on_term``).

    Returns
    -------
    (Attempt, InverseReport, reason to restart or None)
    """
    measured: list[TermErrors] = []

    def measure(held: int, during_run: bool = True, X=None) -> None:
        # during the engine's run, the curve's extensions leave the tile cache alone;
        # X: the term's X the engine holds in memory (else read from the store)
        measured.append(measure_term(products, open_store(out) if X is None else X, D,
                                     _power(products, powers, held, cache=not during_run),
                                     held, time.perf_counter() - t0))

    worth: dict[int, bool] = {}  # by term: asked before the term, then after it

    def reads_term(k: int) -> bool:
        if k not in worth:
            worth[k] = _worth_measuring(method, k, products, powers, D, target)
        return worth[k]

    def on_term(record, X=None) -> str | None:
        if not reads_term(record.term):
            return None
        measure(record.term, X=X)
        return _verdict(measured[-1], target)[0] or None

    # the engine writes only the terms measured (in memory; out of core, every term)
    on_term.reads_term = reads_term
    # the probes' errors decide: the engine's own residual estimate (an M product per
    # term) is not made
    on_term.needs_residual = False
    # in memory, the engine hands over the X it holds: not read back from the store
    on_term.takes_X = True

    # term 0 (F^-1, nothing pruned) is never handed over (its error ||M d|| / ||d|| is
    # known); it is measured only as the held term of a cap of 0
    report = stratified_inverse(
        T, out, terms=cap, prune=thresholds.prune, prune_feed=thresholds.feed,
        prune_operator=thresholds.operator, method=method, first_bounce=ctx.first_bounce,
        memory_limit=ctx.memory_limit, scheduler=ctx.scheduler, workers=ctx.workers,
        progress=ctx.progress, seed=ctx.seed, overwrite=overwrite, on_term=on_term,
        T_rows=products.rows)
    held = min(report.terms, report.history[-1].term)  # an exhausted series: its last
    if not measured or measured[-1].term != held:  # cap 0, exhausted, or not worth it
        measure(held, during_run=False)
    ended, reason = _verdict(measured[-1], target)
    if not ended and "exhausted" in report.stopped:
        ended, reason = report.stopped, (f"{report.stopped} with error "
                                         f"{measured[-1].worst:.2e} above the target")
    return (Attempt(method, thresholds.prune, tuple(measured), ended or f"term cap {cap}",
                    thresholds.feed, thresholds.operator), report, reason)


def _worth_measuring(method: str, term: int, products: _Products, powers, D,
                     target: float) -> bool:
    """Whether to measure the probes' error after ``term`` (two streamed products):
    always for Newton-Schulz (few, costly steps); else once the truncation part alone
    is within MEASURE_WITHIN of the safe target (the error may be met), and at terms
    4, 8, 16, ... to see a pruning floor early in a long series. A short series
    (small rho) is so measured only where it can stop."""
    if method == "newton-schulz" or (term >= 4 and term & (term - 1) == 0):
        return True
    truncation = float(_rel(_power(products, powers, term, cache=False), D).max())
    return truncation <= MEASURE_WITHIN * SAFETY * target


def _verdict(m: TermErrors, target: float) -> tuple[str, str | None]:
    """(why the attempt ends after term ``m``, or "" to go on; the reason to restart
    with a smaller prune, or None)."""
    if m.worst <= SAFETY * target:
        return "target reached", None
    if floored(m, target):
        return "pruning floor", (f"at term {m.term} the pruning part {m.pruning:.2e} "
                                 f"exceeds {PRUNE_SHARE:g} of the safe target "
                                 f"{SAFETY * target:.2e} and {FLOOR_DOMINANCE:g}x the "
                                 f"truncation part {m.truncation:.2e}")
    return "", None


def invert_to_target(T, out, target: float, *, method: str | None = None,
                     prune: float | None = None, max_terms: int | None = None,
                     first_bounce=defaults.FIRST_BOUNCE, memory_limit=None, scheduler=None,
                     workers=defaults.WORKERS, progress=False, overwrite=False,
                     seed=0) -> TargetReport:
    """The stratified inverse whose compensated images reach ``target`` at the least
    cost found (module docstring).

    Parameters
    ----------
    T : BlockCSR or path, shape (n, n)
    out : str or PathLike, the inverse store (as :func:`stratified_inverse`'s)
    target : float in (0, 1)
        Relative error ||T X d - d|| / ||d|| of the compensated probe images, e.g.
        1/255 for an 8-bit display.
    method : str, optional
        Fix the method instead of choosing it.
    prune : float, optional
        The first prune tried (default: :func:`first_prune`); smaller
        ones follow when it floors above the target. The power form's feed and
        operator thresholds are fixed multiples of it (:func:`first_thresholds`).
        Without ``method``, ``prune`` and ``overwrite``, a store ``out`` that holds an
        inverse of ``T`` is resumed with the method and thresholds it records
        (:func:`~bigT.algorithms.fingerprint.recorded_setting`): made by other
        defaults, it is continued, not refused.
    max_terms : int, optional
        Cap on the terms (default: the unpruned series' count + 3, at most 200).
    first_bounce, memory_limit, scheduler, workers, progress, seed
        Passed to :func:`stratified_inverse`.
    overwrite : bool
        Start anew in ``out`` whatever it holds (restarts always do).

    Returns
    -------
    TargetReport

    Raises
    ------
    BigTError
        A target outside (0, 1) or below T's precision; and whatever
        :func:`stratified_inverse` raises (a diverging series, a bad store).
    """
    t0 = time.perf_counter()
    T = as_store(T, "T")
    check_target(target, T.dtype)
    rows = held_rows(T, memory_limit, workers)
    fb = (resolve_first_bounce(T, first_bounce) if rows is None
          else first_bounce_of_rows(T, first_bounce, rows))
    ctx = _Setting(first_bounce, memory_limit, scheduler, workers, progress, seed)
    products = _Products(T, fb, workers, keep_tiles=keeps_tiles(T, memory_limit),
                         rows=rows)
    try:
        D = probe_vectors(T, fb.active, seed)
        limit = MAX_TERMS if max_terms is None else int(max_terms)
        powers, predicted = predicted_curve(products, D,
                                            SAFETY * target * (1 - PRUNE_SHARE), limit)
        cap = min(limit, predicted + EXTRA_TERMS) if max_terms is None else limit
        recorded = None if overwrite or method is not None or prune is not None \
            else recorded_setting(T, fb, out)
        if recorded is not None:  # resumed as it was made, whatever defaults made it
            method, thresholds = recorded.method, recorded.thresholds
            method_why = f"{method} (recorded in the store resumed)"
        else:
            if method is None:
                method, method_why = choose_method(predicted)
            else:
                method_why = f"{method} (given)"
            thresholds = first_thresholds(
                method, first_prune(target, decay_rate(powers, D)) if prune is None
                else float(prune))
        attempts, restarts = [], []
        while True:
            attempt, report, reason = _run_attempt(
                T, out, method, thresholds, cap, target, ctx, products, D, powers, t0,
                overwrite or bool(attempts))
            attempts.append(attempt)
            if reason is None or len(restarts) >= MAX_RESTARTS:
                break
            p = thresholds.prune
            nxt = smaller_prune(p, attempt.terms[-1].pruning, target)
            thresholds = thresholds.scaled(nxt / p)  # the triple keeps its ratios
            restarts.append(f"{attempt.thresholds.describe()} ({reason}): restarted with "
                            f"{thresholds.describe()}")
    finally:
        products.close()
    return _report(target, attempts, tuple(restarts), report, predicted,
                   time.perf_counter() - t0, method_why)


def _report(target, attempts, restarts, report, predicted, seconds, method_why):
    last = attempts[-1].terms[-1]
    met = last.worst <= target
    why = (f"the unpruned series needs {predicted} terms to bring the probes' truncation "
           f"error below {SAFETY * (1 - PRUNE_SHARE):g} of the target "
           f"(spectral radius {report.spectral_radius:.3g}); "
           f"{attempts[-1].thresholds.describe()} kept the pruning part at {last.pruning:.2e}; {method_why}; "
           f"stopped: {attempts[-1].ended}")
    return TargetReport(
        target=float(target), met=met, method=attempts[-1].method,
        prune=attempts[-1].prune, terms=last.term, why=why, error=last.worst,
        clipped_error=max(last.clipped_errors), probes=PROBE_NAMES,
        predicted_terms=predicted, spectral_radius=report.spectral_radius,
        seconds=seconds, restarts=restarts, attempts=tuple(attempts),
        inverse=report.to_dict(), prune_feed=attempts[-1].feed,
        prune_operator=attempts[-1].operator)
