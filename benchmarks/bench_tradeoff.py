"""Run time against error of the stratified inverse (reported, not asserted).

A. **Per term.** For each scene (the wall corner at 96x128, 192x256 and 384x512, each
   with the ``sparse`` and ``dense`` density presets, the Cornell box and the
   hemispheres) and each method (power, horner, newton-schulz; the latter holds terms
   0, 1, 3, 7, ...) at prune 1e-5, one engine call computes the terms, and each term's
   error against the exact inverse F^-1 (I - A) is measured as soon as it is published
   (``Scene.inverse_error``: all rows up to 192x256, 4096 sampled rows at 384x512),
   between the engine's timed terms (see :func:`on_each_term`: resuming the output
   call by call would re-read T at every term). Per term: the cumulative time (the sum
   of the engine's own term times, ``TermRecord.seconds``, its residual estimate
   included), the wall time of the call so far less the error measurements (setup,
   spectral radius and deleting each superseded term included), the error, the
   engine's residual estimate and nnz(X). One PNG per scene (``tradeoff-<scene>.png``):
   error against cumulative time, all methods.
B. **Pruning as a trade.** On the 192x256 dense corner (``--quick``: the 96x128
   sparse one), 4 terms of power and horner with the prune threshold swept over
   decades, and of the power form fed on a P_k pruned harder (``prune_feed``): time,
   nnz(X), error, each a plain engine call from scratch. The Pareto front of time
   against error across all of them is marked in the table and drawn in
   ``tradeoff-pruning.png``; the plain calls at prune 1e-5 check that measuring the
   errors between terms in part A did not slow the terms.

Every engine run is in this process (after a warm-up on a tiny scene, so that no
kernel compiles and no first import lands inside a timed term), one at a time, with
progress bars off. On the largest dense corner horner stops at 3 terms and
newton-schulz at term 1 (time).

    nice -n 10 python benchmarks/bench_tradeoff.py --quick        # 96x128 corners, ~1 min
    nice -n 10 python benchmarks/bench_tradeoff.py --workdir DIR  # everything, ~15 min

Scenes are built into ``--workdir`` (default: a new temporary directory) and reused
when it already holds them (building all the full mode's scenes takes ~5 min; the
384x512 dense corner alone ~2 min). Tables are printed as markdown and recorded with
``Results("tradeoff")`` into ``$BIGT_BENCH_OUT/tradeoff.json`` (default ``bench-out``),
beside the PNGs. Values for the summary: ``best:<scene>`` (the fastest setting reaching
an error <= 1e-4, and its time) and the table ``pareto``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import gc
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

# run from a checkout: the repository's bigT and the benchmarks' helpers
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _results import Results, beside  # noqa: E402

METHODS = ("power", "horner", "newton-schulz")
#: The prune threshold of part A (the engine's default).
PRUNE = 1e-5
#: The error the ``best:<scene>`` values ask for.
TARGET_ERROR = 1e-4
COLORS = {"power": "tab:blue", "horner": "tab:orange", "newton-schulz": "tab:green",
          "power fed": "tab:purple"}


# --- what is measured ---------------------------------------------------------------------

@dataclass(frozen=True)
class SceneSpec:
    """A scene of part A and how far each method goes on it.

    Attributes
    ----------
    name : str
        A scene of :mod:`bigT.scenes` ("corner", "cornell", "hemispheres").
    size : (H, W)
    density : str
        Density preset ("sparse", "dense").
    terms : tuple of (method, int)
        The last term computed per method (newton-schulz: the last held term it may
        reach, 1, 3 or 7).
    sample : int or None
        Rows the error is measured on (None: all).
    """

    name: str
    size: tuple[int, int]
    density: str
    terms: tuple[tuple[str, int], ...] = (("power", 4), ("horner", 4), ("newton-schulz", 3))
    sample: int | None = None

    @property
    def key(self) -> str:
        return f"{self.name}-{self.size[0]}x{self.size[1]}-{self.density}"

    def max_terms(self, method: str) -> int:
        return dict(self.terms)[method]


@dataclass(frozen=True)
class Setting:
    """One point of the pruning sweep: ``method`` at ``prune``, P_k fed on at ``feed``
    (power only; None: at ``prune``), ``terms`` terms."""

    method: str
    prune: float
    feed: float | None = None
    terms: int = 4

    @property
    def label(self) -> str:
        return "power fed" if self.feed is not None else self.method

    def describe(self) -> str:
        feed = "" if self.feed is None else f" feed {self.feed:g}"
        return f"{self.method} prune {self.prune:g}{feed}, {self.terms} terms"


@dataclass(frozen=True)
class TermPoint:
    """The state after one term of a method on a scene (part A).

    Attributes
    ----------
    term_seconds : float
        The engine's time for this term (``TermRecord.seconds``).
    seconds : float
        Cumulative: the engine's term times from term 0 to this one.
    wall : float
        Wall time of the engine call up to this term's publication, the error
        measurements of the earlier terms left out.
    error : float
        ||X - F^-1 (I - A)||_F / ||F^-1 (I - A)||_F (on the spec's rows).
    residual : float or None
        The engine's estimate of ||I - T X||_F / sqrt(n).
    """

    scene: str
    method: str
    term: int
    term_seconds: float
    seconds: float
    wall: float
    error: float
    residual: float | None
    nnz_X: int


@dataclass(frozen=True)
class SweepPoint:
    """One finished inverse of the pruning sweep (part B): ``seconds`` the engine's term
    times summed, ``wall`` the call's, ``multiply_adds`` its products' (all terms)."""

    setting: Setting
    seconds: float
    wall: float
    nnz_X: int
    error: float
    residual: float | None
    multiply_adds: int


def _corner(size, density, sample=None, ns=3, horner=4, power=4) -> SceneSpec:
    """The corner at ``size`` and ``density``, each method's last term given."""
    return SceneSpec("corner", size, density,
                     (("power", power), ("horner", horner), ("newton-schulz", ns)), sample)


# the dense 96x128 corner (1177 nonzeros per row) costs ~10 s a term: two terms in --quick
QUICK_SCENES = (_corner((96, 128), "sparse"),
                _corner((96, 128), "dense", ns=1, horner=2, power=2))
FULL_SCENES = (
    _corner((96, 128), "sparse", ns=7), _corner((96, 128), "dense", ns=7),
    _corner((192, 256), "sparse", ns=7), _corner((192, 256), "dense"),
    _corner((384, 512), "sparse", sample=4096),
    # horner and newton-schulz bounded on the largest dense scene (time)
    _corner((384, 512), "dense", sample=4096, ns=1, horner=3),
    SceneSpec("cornell", (64, 80), "sparse"),
    SceneSpec("hemispheres", (96, 128), "sparse"),
)


def sweep_settings(quick: bool) -> list[Setting]:
    """The settings of part B: power and horner over decades of prune, and the power
    form fed on P_k pruned at 1e-4 while X keeps entries down to prune."""
    prunes = (1e-3, 1e-4, 1e-5) if quick else (1e-3, 1e-4, 1e-5, 1e-6)
    fed = ((1e-5, 1e-4),) if quick else ((1e-5, 1e-4), (3e-6, 1e-4), (1e-6, 1e-4))
    return ([Setting(m, p) for m in ("power", "horner") for p in prunes]
            + [Setting("power", p, f) for p, f in fed])


# --- running the engine -------------------------------------------------------------------

def load_or_build(spec: SceneSpec, workdir: Path):
    """The scene of ``spec`` from ``workdir``, built there first when missing."""
    import bigT

    path = workdir / f"{spec.key}.zarr"
    if path.exists():
        return bigT.scenes.load(path)
    t0 = time.perf_counter()
    scene = bigT.scenes.make(spec.name, size=spec.size, path=path, density=spec.density,
                             preview=False, progress=False)
    print(f"built {spec.key} in {time.perf_counter() - t0:.1f} s", flush=True)
    return scene


def warm_up(workdir: Path) -> float:
    """Run every method (and the fed power form) and an error measurement on a 12x16
    corner, so that imports and kernel loads happen before the first timed term."""
    import bigT

    t0 = time.perf_counter()
    scene = bigT.scenes.corner(size=(12, 16), path=workdir / "warm-up.zarr", preview=False,
                               progress=False, overwrite=True)
    for method, feed in [(m, None) for m in METHODS] + [("power", 1e-4)]:
        out = workdir / "X-warm-up.zarr"
        bigT.stratified_inverse(scene.T, out, terms=3, method=method, prune=1e-6,
                                prune_feed=feed, progress=False, overwrite=True)
        measure_error(scene, out, None)
    return time.perf_counter() - t0


def measure_error(scene, out: Path, sample: int | None,
                  term: int | None = None) -> tuple[float, int]:
    """(relative error of the inverse held in ``out``, its nnz); ``term``: the term it
    must hold. The store is let go before returning: a reader's lease would keep the
    engine from deleting the term."""
    import bigT

    X = bigT.open(out)
    try:
        held = X.metadata.get("inverse", {}).get("term")
        if term is not None and held != term:
            raise RuntimeError(f"{out} holds term {held}, not term {term}")
        return scene.inverse_error(X, sample=sample), int(X.nnz)
    finally:
        del X
        gc.collect()


def invert(scene, out: Path, setting: Setting, terms: int, memory_limit):
    """One engine call from scratch; returns (report, wall seconds)."""
    import bigT

    t0 = time.perf_counter()
    report = bigT.stratified_inverse(scene.T, out, terms=terms, prune=setting.prune,
                                     prune_feed=setting.feed, method=setting.method,
                                     memory_limit=memory_limit, progress=False,
                                     overwrite=True)
    return report, time.perf_counter() - t0


@contextlib.contextmanager
def on_each_term(callback):
    """While inside, ``callback(k)`` runs each time the engine has published term k:
    after the term's record (its time) is taken, before the next term's clock starts.

    It wraps the engine's private ``InverseEngine._finish_term`` (benchmark only): extending
    the output call by call instead (``terms=1``, then ``terms=2``, ...) would start
    every term with an empty cache of T's rows, which a single call keeps from term to
    term (measured: 40 % more time on the 192x256 dense corner).
    """
    from bigT.algorithms import engine as engine_module
    from bigT.algorithms.engine import InverseEngine

    engine = InverseEngine
    original = engine._finish_term
    interval = engine_module.PUBLISH_INTERVAL_SECONDS
    engine_module.PUBLISH_INTERVAL_SECONDS = 0.0  # in memory too, each term published

    @functools.wraps(original)
    def finish_and_report(self, k, *args, **kwargs):
        original(self, k, *args, **kwargs)
        callback(k)

    engine._finish_term = finish_and_report
    try:
        yield
    finally:
        engine._finish_term = original
        engine_module.PUBLISH_INTERVAL_SECONDS = interval


def term_curve(scene, spec: SceneSpec, method: str, workdir: Path,
               memory_limit) -> tuple[list[TermPoint], float]:
    """Part A for one method on one scene: one engine call, the error of each term
    measured as it is published (outside the engine's clock, and subtracted from the
    wall time). Returns the points and the spectral-radius seconds."""
    out = workdir / f"X-{spec.key}-{method}.zarr"
    measured: dict[int, tuple[float, int, float]] = {}  # term -> error, nnz, engine wall
    paused = 0.0
    t0 = time.perf_counter()

    def measure(k: int) -> None:
        nonlocal paused
        t = time.perf_counter()
        measured[k] = (*measure_error(scene, out, spec.sample, term=k), t - t0 - paused)
        paused += time.perf_counter() - t

    with on_each_term(measure):
        report, _ = invert(scene, out, Setting(method, PRUNE), spec.max_terms(method),
                           memory_limit)
    if report.stopped != "terms reached":
        print(f"  {method}: held term {report.terms}, stopped: {report.stopped}")
    points, seconds = [], 0.0
    for rec in report.history:
        seconds += rec.seconds
        error, nnz, wall = measured[rec.term]
        points.append(TermPoint(spec.key, method, rec.term, rec.seconds, seconds, wall,
                                error, rec.residual, nnz))
    return points, report.seconds_spectral_radius


def sweep_point(scene, setting: Setting, workdir: Path, sample, memory_limit) -> SweepPoint:
    """Part B: one inverse of ``setting``'s terms from scratch, then its error."""
    out = workdir / "X-sweep.zarr"
    report, wall = invert(scene, out, setting, setting.terms, memory_limit)
    error, nnz = measure_error(scene, out, sample)
    return SweepPoint(setting, sum(h.seconds for h in report.history), wall, nnz, error,
                      report.residual, sum(h.multiply_adds for h in report.history))


# --- reading the results ------------------------------------------------------------------

def pareto_front(points: list[SweepPoint]) -> set[int]:
    """Indices of the points no other point beats in both time and error (at least as
    good in both, better in one)."""
    def beaten(p, q):
        return (q.seconds <= p.seconds and q.error <= p.error
                and (q.seconds < p.seconds or q.error < p.error))

    return {i for i, p in enumerate(points) if not any(beaten(p, q) for q in points)}


def best_setting(terms: list[TermPoint], sweep: list[SweepPoint]) -> str:
    """The fastest setting with error <= TARGET_ERROR among a scene's per-term points (at
    prune PRUNE) and sweep points, as a short string; else the lowest error reached."""
    cands = [(p.seconds, p.error, f"{p.method} prune {PRUNE:g}, {p.term} terms")
             for p in terms]
    cands += [(p.seconds, p.error, p.setting.describe()) for p in sweep]
    ok = [c for c in cands if c[1] <= TARGET_ERROR]
    if ok:  # the error with the digits that show it is below the target, not at it
        s, e, what = min(ok)
        return f"{what}: {s:.3g} s (error {beside(e, TARGET_ERROR)})"
    s, e, what = min(cands, key=lambda c: c[1])
    return (f"none reaches {TARGET_ERROR:g}; lowest error {beside(e, TARGET_ERROR)}: "
            f"{what}, {s:.3g} s")


def watched_against_plain(terms: list[TermPoint], sweep: list[SweepPoint]) -> str:
    """Part A's engine time to term 4 (errors measured between the terms) against part
    B's plain call of the same setting: a sentence, or ''."""
    parts = []
    for p in sweep:
        s = p.setting
        same = [t for t in terms if t.method == s.method and t.term == s.terms]
        if s.feed is None and s.prune == PRUNE and same:
            parts.append(f"{s.method} {same[0].seconds:.3g} s with the errors measured "
                         f"between terms, {p.seconds:.3g} s without")
    return (f"Engine time to term 4 at prune {PRUNE:g}: " + "; ".join(parts) + "."
            if parts else "")


def _num(x, digits=3):
    """A number rounded to ``digits`` significant figures (None stays None)."""
    if x is None or x != x:
        return None
    return float(f"{x:.{digits}g}")


def term_rows(points: list[TermPoint]) -> list[list]:
    """The rows of a part A table (:data:`TERM_COLUMNS`). Errors are not rounded:
    RESULTS.md's summary compares them with error targets (a 3-digit 1.00e-4 may be
    1.004e-4), and prints them with the digits that tell."""
    return [[p.method, p.term, _num(p.term_seconds), _num(p.seconds), _num(p.wall),
             p.error, _num(p.residual), p.nnz_X] for p in points]


TERM_COLUMNS = ["method", "term", "term s", "cumulative s", "wall s", "error",
                "residual", "nnz(X)"]
PARETO_COLUMNS = ["method", "prune", "feed", "seconds", "nnz(X)", "error", "on front"]
SWEEP_COLUMNS = ["method", "prune", "feed", "seconds", "wall s", "multiply-adds", "nnz(X)",
                 "error", "residual", "on front"]


def pareto_rows(points: list[SweepPoint], front: set[int]) -> list[list]:
    """The rows of the ``pareto`` table (:data:`PARETO_COLUMNS`)."""
    return [[p.setting.method, p.setting.prune, "-" if p.setting.feed is None else p.setting.feed,
             _num(p.seconds), p.nnz_X, p.error, "yes" if i in front else "no"]
            for i, p in enumerate(points)]


def sweep_rows(points: list[SweepPoint], front: set[int]) -> list[list]:
    """The rows of the full sweep table (:data:`SWEEP_COLUMNS`)."""
    return [[p.setting.method, p.setting.prune, "-" if p.setting.feed is None else p.setting.feed,
             _num(p.seconds), _num(p.wall), _num(p.multiply_adds), p.nnz_X, p.error,
             _num(p.residual), "yes" if i in front else "no"] for i, p in enumerate(points)]


def markdown(title: str, columns: list[str], rows: list[list], note: str = "") -> str:
    """A table as markdown, under its title and above its note."""
    def cell(v):
        return "-" if v is None else (f"{v:g}" if isinstance(v, float) else str(v))

    lines = [f"\n### {title}\n", "| " + " | ".join(columns) + " |",
             "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines + ([f"\n{note}"] if note else []))


# --- figures --------------------------------------------------------------------------------

def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def scene_words(spec: "SceneSpec") -> str:
    """A scene key in plain words for a figure's title: "wall corner 96x128, sparse"."""
    names = {"corner": "wall corner", "cornell": "Cornell box", "hemispheres": "hemispheres"}
    H, W = spec.size
    return f"{names.get(spec.name, spec.name)} {H}x{W} ({spec.density} light transport)"


def plot_terms(points: list[TermPoint], title: str, path: Path) -> None:
    """Error (solid, markers labelled by term) and residual estimate (dotted) against
    cumulative time, one colour per method, log y."""
    from bigT.figures import label_points, legend_outside

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8.2, 4.4))
    labelled = []
    for method in METHODS:
        pts = [p for p in points if p.method == method]
        if not pts:
            continue
        t = [p.seconds for p in pts]
        ax.plot(t, [p.error for p in pts], "o-", color=COLORS[method], label=method)
        ax.plot(t, [p.residual for p in pts], ":", color=COLORS[method], alpha=0.6)
        labelled += [(p, COLORS[method]) for p in pts]
    ax.plot([], [], ":", color="grey", label="residual estimate\n(same colour: method)")
    ax.axhline(TARGET_ERROR, color="grey", lw=0.8, ls="--",
               label=f"error {TARGET_ERROR:g} (the target)")
    ax.set_yscale("log")
    # labels placed once the axes are set, all in one call: none may cover another
    label_points(ax, [(p.seconds, p.error) for p, _ in labelled],
                 [f"{p.term}" for p, _ in labelled], colors=[c for _, c in labelled])
    _finish(plt, fig, ax, "time, s: the engine's term times summed (terms 0..n)",
            "relative error ||X_n - T^-1||_F / ||T^-1||_F", title, path, legend_outside)


def _finish(plt, fig, ax, xlabel: str, ylabel: str, title: str, path: Path,
            legend) -> None:
    """Log y axis, labels, legend (placed by ``legend(ax)``) and grid; the figure saved
    to ``path`` and closed."""
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    legend(ax)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _log_time_axis(ax, seconds: list[float]) -> None:
    """A log x axis labelled at 1, 2, 5, 10, 20, ... seconds (no crowded minor labels)."""
    from matplotlib.ticker import NullFormatter

    ax.set_xscale("log")
    ticks = [m * 10.0 ** e for e in range(-2, 5) for m in (1, 2, 5)]
    ax.set_xticks([t for t in ticks if min(seconds) / 1.5 <= t <= max(seconds) * 1.5])
    ax.set_xticklabels([f"{t:g}" for t in ax.get_xticks()])
    ax.xaxis.set_minor_formatter(NullFormatter())


def plot_sweep(points: list[SweepPoint], front: set[int], title: str, path: Path) -> None:
    """All sweep points (labelled by prune, /feed where P_k was pruned harder) and the
    Pareto front, log-log; labels placed so that none overlaps another."""
    from bigT.figures import label_points, legend_outside

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8.2, 4.6))
    for label, words in (("power", "power"), ("horner", "horner"),
                         ("power fed", "power, P_k pruned\nharder (label prune/feed)")):
        pts = [p for p in points if p.setting.label == label]
        if pts:
            ax.scatter([p.seconds for p in pts], [p.error for p in pts], color=COLORS[label],
                       label=words, zorder=3)
    on = sorted((points[i] for i in front), key=lambda p: p.seconds)
    ax.step([p.seconds for p in on], [p.error for p in on], "k-", where="post", lw=0.8,
            label="Pareto front: no setting\nis faster and more accurate")
    ax.set_yscale("log")
    ax.margins(y=0.12)  # room for the labels of the outermost points
    _log_time_axis(ax, [p.seconds for p in points])
    label_points(ax, [(p.seconds, p.error) for p in points],
                 [f"{p.setting.prune:g}" + ("" if p.setting.feed is None else f"/{p.setting.feed:g}")
                  for p in points])
    _finish(plt, fig, ax, "time, s: the engine's term times summed (terms 0..4)",
            "relative error ||X - T^-1||_F / ||T^-1||_F", title, path, legend_outside)


# --- the two parts ----------------------------------------------------------------------------

def term_note(scene, spec: SceneSpec, rho: dict[str, float]) -> str:
    """The sentence under a part A table: the scene, what the columns mean, the rows
    the error is measured on, the load."""
    rows = "all rows" if spec.sample is None else f"{spec.sample} sampled rows"
    if not scene.exact:
        rows += (f"; T is truncated (threshold {scene.summary['threshold']:g}), so the "
                 "error levels off at the distance between the stored T's inverse and "
                 "F^-1 (I - A) while the residual (against the stored T) keeps falling")
    return (f"n = {scene.T.shape[0]}, T {scene.T.nnz / scene.T.shape[0]:.0f} nonzeros/row, "
            f"prune {PRUNE:g}. cumulative s: the engine's term times (residual estimate "
            f"included) summed from term 0; wall s: the call's wall time up to the term, "
            f"less the error measurements (spectral radius estimate: "
            + ", ".join(f"{m} {s:.2f} s" for m, s in rho.items())
            + f"). Error vs F^-1 (I - A) on {rows}. Load average at the end "
            f"{os.getloadavg()[0]:.1f} (2 cores).")


def part_a(spec: SceneSpec, workdir: Path, res: Results, memory_limit) -> list[TermPoint]:
    """Per-term curves of every method on one scene: table, figure."""
    scene = load_or_build(spec, workdir)
    points, rho = [], {}
    for method in METHODS:
        pts, rho[method] = term_curve(scene, spec, method, workdir, memory_limit)
        points += pts
    rows, note = term_rows(points), term_note(scene, spec, rho)
    title = f"Time against error per term: {spec.key}"
    print(markdown(title, TERM_COLUMNS, rows, note), flush=True)
    res.table(f"terms:{spec.key}", title, TERM_COLUMNS, rows, note)
    png = f"tradeoff-{spec.key}.png"
    plot_terms(points, f"Error against time, term by term (labels: term)\n"
                       f"{scene_words(spec)}, n = {scene.T.shape[0]:,}, prune {PRUNE:g}",
               res.figure_path(png))
    res.figure(png, f"{spec.key}: error against cumulative engine time per term "
                    "(dotted: residual estimate; dashed: 1e-4)")
    return points


def part_b(spec: SceneSpec, settings: list[Setting], workdir: Path, res: Results,
           memory_limit) -> list[SweepPoint]:
    """The pruning sweep on one scene: tables (full, and the ``pareto`` one), figure."""
    scene = load_or_build(spec, workdir)
    points = []
    for s in settings:
        points.append(sweep_point(scene, s, workdir, spec.sample, memory_limit))
        print(f"  {s.describe()}: {points[-1].seconds:.2f} s, error {points[-1].error:.3g}",
              flush=True)
    front = pareto_front(points)
    note = (f"{spec.key}, 4 terms each from scratch; seconds: the engine's term times "
            "summed; on front: no other point is both faster and more accurate. Load "
            f"average at the end {os.getloadavg()[0]:.1f} (2 cores).")
    title = f"Pruning as a trade: {spec.key}"
    print(markdown(title, SWEEP_COLUMNS, sweep_rows(points, front), note), flush=True)
    res.table("sweep", title, SWEEP_COLUMNS, sweep_rows(points, front), note)
    res.table("pareto", f"Pareto front of time against error: {spec.key}", PARETO_COLUMNS,
              pareto_rows(points, front), note)
    plot_sweep(points, front, f"Error against time over prune thresholds (labels: prune)\n"
                              f"{scene_words(spec)}, 4 terms", res.figure_path("tradeoff-pruning.png"))
    res.figure("tradeoff-pruning.png", f"{spec.key}: time against error over prune "
                                       "thresholds, and the Pareto front")
    return points


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true",
                   help="only the 96x128 corners and a small prune sweep (~1 min)")
    p.add_argument("--workdir", default=None, help="scenes and inverses (reused if present)")
    p.add_argument("--scenes", default=None,
                   help="comma-separated scene keys of part A to run (default: all of the mode)")
    p.add_argument("--no-sweep", action="store_true", help="skip part B")
    p.add_argument("--memory-limit", default=None, help="for every engine run, e.g. 2GiB")
    return p.parse_args(argv)


def record_best(res: Results, terms: dict[str, list[TermPoint]], sweep: list[SweepPoint],
                sweep_key: str) -> None:
    """The ``best:<scene>`` values, and the check of part A's times against part B's."""
    for key, points in terms.items():
        best = best_setting(points, sweep if key == sweep_key else [])
        res.value(f"best:{key}", best, f"fastest setting reaching error <= {TARGET_ERROR:g} "
                                       f"on {key}, with its engine time")
        print(f"best:{key} = {best}")
    check = watched_against_plain(terms.get(sweep_key, []), sweep)
    if check:
        print(check)
        res.note(check)


def main(argv=None) -> int:
    args = parse_args(argv)
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench_tradeoff_"))
    workdir.mkdir(parents=True, exist_ok=True)
    command = " ".join(["python benchmarks/bench_tradeoff.py", *(argv or sys.argv[1:])])
    res = Results("tradeoff", title="Run time against error: methods, terms and pruning",
                  command=command)
    print(f"warm-up {warm_up(workdir):.1f} s; workdir {workdir}; load {os.getloadavg()[0]:.1f}",
          flush=True)
    scenes = QUICK_SCENES if args.quick else FULL_SCENES
    if args.scenes:
        scenes = [s for s in scenes if s.key in args.scenes.split(",")]
    terms = {s.key: part_a(s, workdir, res, args.memory_limit) for s in scenes}
    sweep_spec = _corner((96, 128), "sparse") if args.quick else _corner((192, 256), "dense")
    sweep = ([] if args.no_sweep else
             part_b(sweep_spec, sweep_settings(args.quick), workdir, res, args.memory_limit))
    record_best(res, terms, sweep, sweep_spec.key)
    res.note(f"load average at the end {os.getloadavg()[0]:.1f} (2 cores; shared machine)")
    print(f"\nrecorded in {res.save()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
