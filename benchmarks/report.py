"""Write RESULTS.md from the records the benchmarks left in the output directory.

    python benchmarks/report.py [--out DIR] [--results FILE]

Reads every ``<name>.json`` there (written by ``_results.Results``), ``machine.json``
(the stamp ``run_all.py`` takes as a run starts) and ``runs.json`` (each benchmark's
command, exit status and time, in the plan's order), and writes RESULTS.md: the stamp,
a summary whose every sentence is generated from the records and quotes their numbers,
the paper's claims beside what was measured, then one section per benchmark with its
tables, figures (linked relatively, so the file displays on GitHub), notes, values and
run time. Every figure gets the stamp drawn under it. Nothing here is typed by hand:
a benchmark that did not run says "not measured in this run".
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterable

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import (  # noqa: E402
    MACHINE_FILE,
    OUT_ENV,
    Claim,
    CodeState,
    Figure,
    Machine,
    Table,
    Value,
    beside,
    machine,
)

#: What ``run_all.py`` writes beside the records: the plan's order and each run's status.
RUNS_FILE = "runs.json"
#: The PNG text key marking a figure already stamped (a rerun of the report leaves it).
STAMP_KEY = "bigT-stamp"
#: Lines of a failed benchmark's log quoted in RESULTS.md.
LOG_TAIL = 25
#: Lines quoted of a benchmark that prints its tables without recording them.
OUTPUT_TAIL = 60
NOT_MEASURED = "not measured in this run"


# --- what run_all.py hands over -----------------------------------------------------------

@dataclass(frozen=True)
class Run:
    """One benchmark of a plan as ``run_all.py`` ran it."""

    name: str
    command: list[str]
    returncode: int | None  # None: started and never finished (interrupted)
    seconds: float
    log: str  # its printed output, a file in the output directory
    # what the plan expected (run_all.Step.minutes); None in runs.json of older plans
    estimated_seconds: float | None = None


@dataclass(frozen=True)
class Plan:
    """The plan's order of names and the runs done so far (``runs.json``)."""

    kind: str  # "full", "quick" or "custom"
    order: list[str]
    runs: list[Run]

    def run(self, name: str) -> Run | None:
        return next((r for r in self.runs if r.name == name), None)

    def save(self, directory: Path) -> Path:
        path = Path(directory) / RUNS_FILE
        path.write_text(json.dumps(asdict(self), indent=1))
        return path

    @classmethod
    def load(cls, directory: Path) -> "Plan | None":
        path = Path(directory) / RUNS_FILE
        if not path.exists():
            return None
        d = json.loads(path.read_text())
        return cls(d["kind"], d["order"], [Run(**r) for r in d["runs"]])


# --- the records ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Record:
    """A benchmark's ``<name>.json``, read back."""

    name: str
    title: str
    command: str
    tables: list[Table]
    figures: list[Figure]
    values: dict[str, Value]
    claims: list[Claim]
    notes: list[str]
    seconds: float | None
    started: float | None
    code: CodeState | None  # None: a record from before records named their code

    @classmethod
    def from_json(cls, d: dict) -> "Record":
        return cls(d["name"], d.get("title", ""), d.get("command", ""),
                   [Table(**t) for t in d.get("tables", [])],
                   [Figure(**f) for f in d.get("figures", [])],
                   {v["key"]: Value(**v) for v in d.get("values", [])},
                   [Claim(**c) for c in d.get("claims", [])], list(d.get("notes", [])),
                   d.get("seconds"), d.get("started"),
                   CodeState.from_dict(d["code"]) if d.get("code") else None)

    def table(self, key: str) -> Table | None:
        return next((t for t in self.tables if t.key == key), None)

    def tables_from(self, prefix: str) -> list[Table]:
        return [t for t in self.tables if t.key.startswith(prefix)]

    def value(self, key: str, default: Any = None) -> Any:
        v = self.values.get(key)
        return default if v is None else v.value


def load_records(directory: Path) -> dict[str, Record]:
    """Every record in ``directory`` by name (the stamp and the plan are not records)."""
    out = {}
    for path in sorted(Path(directory).glob("*.json")):
        if path.name in (MACHINE_FILE, RUNS_FILE):
            continue
        try:
            rec = Record.from_json(json.loads(path.read_text()))
        except (ValueError, KeyError, TypeError):  # not a record: a script's own JSON
            continue
        out[rec.name] = rec
    return out


# --- numbers and markdown -------------------------------------------------------------------

def fmt(x: Any) -> str:
    """A cell: 3 significant digits, scientific below 1e-3 (errors) and from 1e6."""
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}" if abs(x) >= 1000 else str(x)
    if isinstance(x, float):
        if not math.isfinite(x):
            return "–"
        a = abs(x)
        if a == 0:
            return "0"
        if a < 1e-3 or a >= 1e6:
            mant, exp = f"{x:.2e}".split("e")
            return f"{mant}e{int(exp)}"
        return f"{x:,.0f}" if a >= 100 else f"{x:.3g}"
    if isinstance(x, (list, tuple)):
        return " ".join(fmt(v) for v in x)
    return str(x)


def _cell(x: Any) -> str:
    return fmt(x).replace("|", "\\|").replace("\n", " ")


def md_table(t: Table) -> list[str]:
    lines = [f"**{t.title or t.key}**", "",
             "| " + " | ".join(_cell(c) for c in t.columns) + " |",
             "|" + "---|" * len(t.columns)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in t.rows]
    if t.note:
        lines += ["", f"*{t.note}*"]
    return lines + [""]


def _num(x: Any) -> float | None:
    """A cell as a number (None for text such as "did not fit", or a missing value)."""
    if isinstance(x, bool) or x is None:
        return None
    if isinstance(x, (int, float)):
        return float(x) if math.isfinite(x) else None
    try:
        return float(str(x).replace(",", ""))
    except ValueError:
        return None


def _rows(t: Table) -> list[dict[str, Any]]:
    return [dict(zip(t.columns, row)) for row in t.rows]


def _when(stamp: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(stamp)) if stamp else "?"


# --- the summary ----------------------------------------------------------------------------

#: Frame counts the alternatives are compared at: one image, a clip, a long video.
FRAME_COUNTS = (1, 1000)


@dataclass(frozen=True)
class Cost:
    """One method's cost at one size, from the alternatives table."""

    method: str
    setup: float
    frame1: float | None  # s per frame at batch 1
    frame64: float | None  # s per frame at batch 64
    error: Any
    peak: float | None

    def total(self, frames: int) -> float | None:
        """Setup and ``frames`` frames, batched when there are enough to batch."""
        per = self.per_frame(frames)
        return None if per is None else self.setup + frames * per

    def batched(self, frames: int) -> bool:
        """Whether ``frames`` frames go quicker in batches of 64 than one by one (a
        user batches only where it pays: a sparse LU's solve of 64 right-hand sides
        may take longer a frame than one)."""
        if frames < 64 or self.frame64 is None:
            return False
        return self.frame1 is None or self.frame64 <= self.frame1

    def per_frame(self, frames: int) -> float | None:
        return self.frame64 if self.batched(frames) else self.frame1


def _costs(rows: list[dict]) -> list[Cost]:
    out = []
    for r in rows:
        setup = _num(r.get("setup s"))
        f1, f64 = _num(r.get("frame s (batch 1)")), _num(r.get("frame s (batch 64)"))
        if setup is None or (f1 is None and f64 is None):
            continue
        out.append(Cost(str(r.get("method")), setup, f1, f64, r.get("error"),
                        _num(r.get("peak MiB"))))
    return out


def _break_even(a: Cost, b: Cost, frames: int) -> float | None:
    """Frames after which ``a`` (more setup, cheaper frames) overtakes ``b``."""
    pa, pb = a.per_frame(frames), b.per_frame(frames)
    if pa is None or pb is None or pb <= pa:
        return None
    return max((a.setup - b.setup) / (pb - pa), 0.0)


def _cost_text(c: Cost, frames: int) -> str:
    total = c.total(frames)
    per = c.per_frame(frames)
    batch = "batch 64" if c.batched(frames) else "batch 1"
    return (f"{c.method} ({fmt(c.setup)} s setup + {fmt(frames)} × {fmt(per)} s a frame "
            f"at {batch} = {fmt(total)} s; error {fmt(c.error)})")


def _crossings(costs: list[Cost], few: Cost, many: Cost) -> str:
    """Where the quickest for many frames overtakes the quickest for one, and where the
    method with the cheapest frames pays back its setup against it."""
    text, big = "", FRAME_COUNTS[-1]
    if few.method != many.method:
        k = _break_even(many, few, big)
        if k is not None:
            text += f" {many.method} overtakes {few.method} after about {fmt(whole_frames(k))} frames."
    cheapest = min(costs, key=lambda c: c.per_frame(big))
    if cheapest.method != many.method:
        k = _break_even(cheapest, many, big)
        if k is not None:
            batched = ", batched" if cheapest.batched(big) else ""
            text += (f" {cheapest.method} has the cheapest frames ({fmt(cheapest.per_frame(big))}"
                     f" s each{batched}) and pays back its {fmt(cheapest.setup)} s setup "
                     f"against {many.method} after about {fmt(whole_frames(k))} frames.")
    return text


def summary_alternatives(rec: Record | None) -> list[str]:
    """Per size: the quickest for one frame and for many, where they cross, memory."""
    table = rec.table("alternatives") if rec else None
    if table is None:
        return ["The alternatives a user would pick instead (dense inverse, sparse LU, "
                f"PARDISO, GMRES, Jacobi, bigT's two paths): {NOT_MEASURED}."]
    out = alternatives_sentences(table)
    out += _quoted_values(rec, "winner:")
    return out or [f"The alternatives table has no timed rows: {NOT_MEASURED}."]


def summary_alternatives_colour(rec: Record | None) -> list[str]:
    """The same answers for the colour Cornell box (``alternatives-colour``)."""
    table = rec.table("alternatives-colour") if rec else None
    if table is None:
        return ["bigT's colour inverse against the rivals that take a colour T (sparse LU "
                f"and GMRES on the 3n system, three grey solves with un-mixing): {NOT_MEASURED}."]
    return [f"Colour Cornell box: {s}" for s in alternatives_sentences(table)] \
        or [f"The colour alternatives table has no timed rows: {NOT_MEASURED}."]


def alternatives_sentences(table: Table) -> list[str]:
    """Per size of an alternatives table: the quickest for 1 and for 1,000 frames, where
    they cross, the least memory and what did not run; then who wins where."""
    rows = _rows(table)
    out, wins = [], {}
    for size in dict.fromkeys(r.get("size") for r in rows):
        sized = [r for r in rows if r.get("size") == size]
        costs = _costs(sized)
        if not costs:
            continue
        n = fmt(sized[0].get("n"))
        best = {k: quickest(costs, k) for k in FRAME_COUNTS}
        parts = [f"for {fmt(k)} frame{'s' if k > 1 else ''} the quickest is "
                 f"{_cost_text(best[k], k)}" for k in FRAME_COUNTS]
        text = f"At {size} (n = {n}): " + "; ".join(parts) + "."
        text += _crossings(costs, best[FRAME_COUNTS[0]], best[FRAME_COUNTS[-1]])
        text += _paybacks(costs)
        light = [c for c in costs if c.peak is not None]
        if light:
            low = min(light, key=lambda c: c.peak)
            text += f" Least memory: {low.method} ({fmt(low.peak)} MiB peak)."
        skipped = [f"{r.get('method')} ({r.get('setup s')})" for r in sized
                   if _num(r.get("setup s")) is None and r.get("setup s") not in (None, "")]
        if skipped:
            text += " Not run here: " + ", ".join(skipped) + "."
        out.append(text)
        for k in FRAME_COUNTS:
            wins.setdefault((best[k].method, k), []).append(str(size))
    out += [f"{m} is the quickest for {fmt(k)} frame{'s' if k > 1 else ''} at "
            f"{', '.join(sizes)}." for (m, k), sizes in sorted(wins.items())]
    return out


#: The rivals bigT's explicit inverse's payback is stated against, one sentence each
#: (issue #34: PARDISO, the fastest direct solver, and bigT's own matrix-free path).
PAYBACK_RIVALS = ("PARDISO", "matrix-free")


def _paybacks(costs: list[Cost]) -> str:
    """After how many frames bigT's explicit X, its setup included, has caught up with
    each of :data:`PAYBACK_RIVALS` timed at this size (per-frame times as for 1,000
    frames: batched where that is quicker)."""
    ours = next((c for c in costs if c.method.startswith("bigT explicit")), None)
    if ours is None:
        return ""
    big, parts = FRAME_COUNTS[-1], []
    for name in PAYBACK_RIVALS:
        rival = next((c for c in costs if name in c.method and c is not ours), None)
        if rival is None:
            continue
        k = _break_even(ours, rival, big)
        if k is None:
            parts.append(f"never with {rival.method} (its frames are as cheap)")
        elif k == 0:
            parts.append(f"with {rival.method} from the first frame (less setup)")
        else:
            parts.append(f"with {rival.method} after {fmt(whole_frames(k))} frames")
    return (f" {ours.method}, its setup included, catches up " + " and ".join(parts) + "."
            if parts else "")


def quickest(costs: list[Cost], frames: int) -> Cost:
    """The method that compensates ``frames`` frames soonest, its setup included."""
    return min(costs, key=lambda c: c.total(frames) if c.total(frames) is not None
               else math.inf)


def payback(costs: list[Cost], method: Cost,
            frames: int = FRAME_COUNTS[-1]) -> tuple[int, Cost | None] | None:
    """(frames from which ``method``, its setup included, is the quickest of ``costs``,
    the method it overtakes last, None when it leads from the first frame), per-frame
    times as for ``frames`` frames; None when another method's frames are as cheap (it
    is never ahead for good)."""
    mine, worst, last = method.per_frame(frames), 1, None
    if mine is None:
        return None
    for other in costs:
        theirs = other.per_frame(frames)
        if other is method or theirs is None:
            continue
        if theirs <= mine:
            return None
        if other.setup > method.setup:
            continue  # behind from the first frame, and falling further behind
        k = whole_frames(_break_even(method, other, frames))
        if k > worst:
            worst, last = k, other
    return worst, last


def whole_frames(x: float) -> int:
    """The frames a break-even point ``x`` needs: ``x`` rounded up, after rounding off
    float noise (0.6 / 5e-5 is 12000.000000000002 in floats, and 12,000 frames)."""
    return math.ceil(float(f"{x:.9g}"))


#: The error targets the tradeoff summary answers, loosest first.
TRADEOFF_TARGETS = (1e-2, 1e-3, 1e-4)


@dataclass(frozen=True)
class Setting:
    """One measured setting of a tradeoff table: what it was, its time and its error."""

    scene: str
    what: str  # "power, 4 terms, prune 1e-05"
    seconds: float
    error: float


def _after(pattern: str, text: str) -> str | None:
    """The first group of ``pattern`` in ``text`` (a table's note or title), or None."""
    m = re.search(pattern, text or "")
    return m.group(1) if m else None


def tradeoff_settings(rec: Record) -> dict[str, list[Setting]]:
    """Every setting the tradeoff tables measured, per scene: each term of each method
    (``terms:<scene>``, at the prune its note states) and each pruning-sweep run
    (``pareto``, on the scene its title names). One list per scene, so that a summary
    sentence weighs every setting its tables show, and nothing else."""
    out: dict[str, list[Setting]] = {}
    for t in rec.tables_from("terms:"):
        scene, prune = t.key.split(":", 1)[1], _after(r"prune ([0-9.e+-]+)\.", t.note)
        for r in _rows(t):
            secs, err = _num(r.get("cumulative s")), _num(r.get("error"))
            if secs is None or err is None:
                continue
            terms = r.get("term")
            what = f"{r.get('method')}, {terms} term{'' if terms == 1 else 's'}" + (
                f", prune {prune}" if prune else "")
            out.setdefault(scene, []).append(Setting(scene, what, secs, err))
    sweep = rec.table("pareto")
    if sweep is not None:
        scene = (sweep.title.rsplit(": ", 1)[-1] if ": " in sweep.title else sweep.key)
        terms = _after(r"(\d+) terms each", sweep.note)
        for r in _rows(sweep):
            secs, err = _num(r.get("seconds")), _num(r.get("error"))
            if secs is None or err is None:
                continue
            feed = r.get("feed")
            what = (f"{r.get('method')}" + (f", {terms} terms" if terms else "")
                    + f", prune {fmt(r.get('prune'))}"
                    + ("" if feed in (None, "", "-") else f", P_k pruned at {fmt(feed)}"))
            out.setdefault(scene, []).append(Setting(scene, what, secs, err))
    return out


def fastest_within(settings: list[Setting], target: float) -> Setting | None:
    """The quickest setting whose error is at most ``target`` (None: none reaches it)."""
    ok = [s for s in settings if s.error <= target]
    return min(ok, key=lambda s: (s.seconds, s.error)) if ok else None


def summary_tradeoff(rec: Record | None) -> list[str]:
    """Per scene, one answer per error target: the fastest setting its tables show
    reaching it, or the lowest error any reached."""
    per_scene = tradeoff_settings(rec) if rec else {}
    if not per_scene:
        return [f"Time against error (the prune threshold and method trade): {NOT_MEASURED}."]
    out = []
    for scene, settings in per_scene.items():
        parts = []
        for target in TRADEOFF_TARGETS:
            best = fastest_within(settings, target)
            if best is None:
                low = min(settings, key=lambda s: s.error)
                parts.append(f"none of its {len(settings)} settings reaches error ≤ "
                             f"{fmt(target)} (lowest: {beside(low.error, target)}, {low.what}, "
                             f"{fmt(low.seconds)} s)")
                break  # a tighter target is not reached either
            # the error with the digits that show it is within the target, not at it
            parts.append(f"error ≤ {fmt(target)} takes {fmt(best.seconds)} s ({best.what}: "
                         f"error {beside(best.error, target)})")
        out.append(f"{scene}, fastest of the {len(settings)} settings measured: "
                   + "; ".join(parts) + ".")
    return out


def _quoted_values(rec: Record, prefix: str) -> list[str]:
    """The verdicts a benchmark recorded itself, quoted as it worded them."""
    out = []
    for key, v in rec.values.items():
        if key.startswith(prefix):
            # the key names what the wording may not (the size of "winner:<size>:...")
            where = key[len(prefix):].split(":")[0]
            out.append(f"{v.what}{'' if where in v.what else f' ({where})'}: {fmt(v.value)}.")
    return out


def summary_scale(rec: Record | None) -> list[str]:
    """The largest size this run measured: its time, memory and error, and the fitted
    exponents; then each row of an own run (full HD, 4K) with where it comes from."""
    table = rec.table("scale") if rec else None
    if table is None or not table.rows:
        return [f"Scaling of the 4-term inverse with n: {NOT_MEASURED}."]
    rows = _rows(table)
    here = [r for r in rows if r.get("measured", "this run") == "this run"] or rows
    own = [r for r in rows if r not in here]
    last = here[-1]
    text = (f"At {last.get('size')} (n = {fmt(last.get('n'))}, "
            f"{fmt(last.get('T nnz/row'))} nonzeros a row) the 4-term inverse took "
            f"{fmt(last.get('inverse s'))} s at {fmt(last.get('peak GiB'))} GiB peak, "
            f"error {fmt(last.get('error'))} against the exact inverse")
    e_t, e_m = rec.value("exponent:time"), rec.value("exponent:peak")
    if e_t is not None:
        text += (f"; from {here[0].get('size')} to {last.get('size')} its time grows as "
                 f"n^{fmt(e_t)} and its peak memory as n^{fmt(e_m)}")
    out = [text + "."]
    for r in own:
        out.append(f"At {r.get('size')} (n = {fmt(r.get('n'))}; {r.get('measured')}, not "
                   f"this run) the 4-term inverse took {fmt(r.get('inverse s'))} s at "
                   f"{fmt(r.get('peak GiB'))} GiB peak, error {fmt(r.get('error'))}; "
                   f"its scene build {fmt(r.get('build s'))} s at "
                   f"{fmt(r.get('build peak GiB'))} GiB.")
    return out


def summary_kernels(rec: Record | None) -> list[str]:
    """Per size: every method's time for the pruned product, and bigT against scipy."""
    tables = rec.tables_from("spgemm:") if rec else []
    if not tables:
        return [f"The pruned product against scipy and its rivals: {NOT_MEASURED}."]
    out = []
    for t in tables:
        times = ", ".join(f"{r.get('method')} {fmt(r.get('time s'))} s" for r in _rows(t))
        ratio = rec.value(f"speedup:{t.key.split(':', 1)[1]}")
        out.append(f"{t.title}: {times}" + (f"; bigT is {fmt(ratio)}× scipy's speed"
                                             if ratio is not None else "") + ".")
    return out


def summary_distributed(rec: Record | None) -> list[str]:
    """The total time on each scheduler."""
    table = rec.table("schedulers") if rec else None
    if table is None:
        return [f"The same inversion on threads, local:2 and two dask workers: {NOT_MEASURED}."]
    parts = [f"{r.get('scheduler')} {fmt(r.get('total s'))} s" for r in _rows(table)]
    return [f"{table.title}: " + ", ".join(parts) + "."]


def summary_video(rec: Record | None) -> list[str]:
    """Frames per second with X in memory (float32, H.264), batch 1 and 64."""
    table = rec.table("video") if rec else None
    if table is None:
        return [f"Real-time compensation of a video: {NOT_MEASURED}."]
    rows = [r for r in _rows(table) if str(r.get("mode", "")).startswith("in memory, mp4")
            and r.get("precision") == "float32"]
    parts = [f"{fmt(r.get('frames/s'))} frames/s at batch {r.get('batch')}" for r in rows]
    return [f"{table.title}: X held in memory compensates " + ", ".join(parts) + "."] \
        if parts else []


#: The goals issue #28 set for the colour paths' time over the grey inverse's.
COLOUR_GOALS = {"general_over_grey": 10.0, "global_over_grey": 3.5}


def summary_colour(rec: Record | None) -> list[str]:
    """The colour paths' time against grey (beside their goals), the seen test pattern
    per compensation, and the time-against-error sweep."""
    if rec is None or rec.table("inverse") is None:
        return [f"Colour (RGB transport): {NOT_MEASURED}."]
    ratios = {k: rec.value(k) for k in COLOUR_GOALS}
    words = [f"the {what} path took {beside(ratios[k], COLOUR_GOALS[k])}× the grey "
             f"inverse's time (goal ≤ {fmt(COLOUR_GOALS[k])})"
             for k, what in (("general_over_grey", "general"),
                             ("global_over_grey", "global-mixing"))
             if _num(ratios[k]) is not None]
    out = [f"{rec.table('inverse').title}: " + " and ".join(words) + "."] if words else []
    seen = rec.table("seen")
    if seen is not None:
        rows = [r for r in _rows(seen) if r.get("target") == "F test pattern"]
        parts = [f"{r.get('projector image')} {fmt(r.get('dE2000 mean'))} / "
                 f"{fmt(r.get('dE2000 p95'))} (PSNR {fmt(r.get('PSNR dB'))} dB, SSIM "
                 f"{fmt(r.get('SSIM'))})" for r in rows]
        if parts:
            out.append("CIEDE2000 ΔE (mean / p95) of the seen colour test pattern: "
                       + "; ".join(parts) + ".")
    out += colour_sweep_sentences(rec.table("tradeoff"))
    return out


def colour_sweep_sentences(table: Table | None) -> list[str]:
    """Per colour path: its quickest setting to each seen ΔE of :data:`DELTA_E_TARGETS`
    (the sweep's rows, term by term over prunes)."""
    if table is None:
        return []
    rows = _rows(table)
    parts = []
    for path in dict.fromkeys(r.get("path") for r in rows):
        settings = [Setting(str(path), f"prune {fmt(r.get('prune'))}, {r.get('terms')} "
                            f"term{'' if r.get('terms') == 1 else 's'}",
                            _num(r.get("seconds")), _num(r.get("seen dE2000 mean")))
                    for r in rows if r.get("path") == path]
        settings = [x for x in settings if x.seconds is not None and x.error is not None]
        for target in DELTA_E_TARGETS:
            best = fastest_within(settings, target)
            parts.append(f"the {path} path reaches seen ΔE ≤ {fmt(target)} in "
                         f"{fmt(best.seconds)} s ({best.what}: ΔE "
                         f"{beside(best.error, target)})" if best else
                         f"the {path} path does not reach seen ΔE ≤ {fmt(target)} in its "
                         f"{len(settings)} settings")
    return [f"{table.title}: " + "; ".join(parts) + "."] if parts else []


#: Seen colour errors the colour sweep's summary answers: ΔE 1 is about the smallest
#: difference a viewer notices side by side; 0.1 a tenth of it.
DELTA_E_TARGETS = (1.0, 0.1)


def summary_calibration(rec: Record | None) -> list[str]:
    """T's error from one exposure against brackets, and the seen error with and
    without the calibrated responses (``bench_calibration.py``)."""
    hdr = rec.table("hdr") if rec else None
    seen = rec.table("seen") if rec else None
    if hdr is None and seen is None:
        return ["Calibration on the simulated nonlinear rig (HDR brackets, the projector's "
                f"response): {NOT_MEASURED}."]
    out = []
    for grid, rows in _grouped(_rows(hdr) if hdr else [], "grid").items():
        known = [r for r in rows if r.get("response") == "gamma:2.2"]
        recovered = [r for r in rows if r.get("response") == "recover"]
        if not known:
            continue
        errors = ", ".join(f"{fmt(r.get('T rel. error'))} ({r.get('exposures')} "
                           f"exposure{'s' if r.get('exposures') != 1 else ''})" for r in known)
        text = (f"On the {grid} grid (camera {known[0].get('camera')}), T's relative error "
                f"against the scene's truth from the known camera response: {errors}; its "
                f"interreflection part {fmt(known[0].get('interreflection (off-diagonal)'))} "
                f"from one exposure, {fmt(known[-1].get('interreflection (off-diagonal)'))} "
                f"from {known[-1].get('exposures')}")
        if recovered:
            text += ("; with the response recovered from the brackets: " + ", ".join(
                f"{fmt(r.get('T rel. error'))} ({r.get('exposures')} exposures)"
                for r in recovered))
        out.append(text + ".")
    for r in _rows(seen) if seen else []:
        out.append(f"The seen error of a compensated gradient on the {r.get('grid')} grid: "
                   f"{fmt(r.get('linear rig'))} on a linear rig; on the nonlinear rig "
                   f"{fmt(r.get('nonlinear, calibrated'))} with the calibrated responses "
                   f"({r.get('calibrated / linear')}× the linear rig's) and "
                   f"{fmt(r.get('nonlinear, uncalibrated'))} without them.")
    return out or [f"The calibration tables have no rows: {NOT_MEASURED}."]


def _grouped(rows: list[dict], column: str) -> dict[Any, list[dict]]:
    """Rows by their value in ``column``, in the table's order."""
    out: dict[Any, list[dict]] = {}
    for r in rows:
        out.setdefault(r.get(column), []).append(r)
    return out


def summary_objects(rec: Record | None) -> list[str]:
    """Object storage against the local directory, per scheduler and engine path (in
    memory, out of core): each S3 run beside the local run of the same two."""
    table = rec.table("runs") if rec else None
    if table is None:
        return [f"Object storage (S3 on loopback) against a local directory: {NOT_MEASURED}."]
    rows = _rows(table)
    parts = [f"{fmt(r.get('seconds'))} s with {r.get('scheduler')}, {r.get('engine path')} "
             f"({fmt(r.get('/ local'))}× the local directory's {fmt(_local_seconds(rows, r))} "
             "s)" for r in rows if r.get("storage") != "local directory"]
    return [f"{table.title.split(':')[0]}: S3 on loopback took " + ", ".join(parts) + "."] \
        if parts else []


def summary_layout(records: Iterable[Record | None]) -> list[str]:
    """The store layout against the baseline tree of each layout record (384x512 in
    the full plan, full HD in its own run): the whole run's seconds and the files a
    term writes, this tree beside the baseline."""
    out = []
    for rec in records:
        runs, terms = (rec.table("runs"), rec.table("terms")) if rec else (None, None)
        if runs is None or terms is None:
            continue
        by_code = {r.get("code"): r for r in _rows(runs)}
        base = next((c for c in by_code if c != "this tree"), None)
        if base is None or "this tree" not in by_code:
            continue
        written = {code: [r.get("files written") for r in _rows(terms)
                          if r.get("code") == code and r.get("files written") is not None]
                   for code in (base, "this tree")}
        what = rec.title.split(": ", 1)[-1] if rec.title else rec.name  # its size, terms
        out.append(
            f"Store layout, {what}: {fmt(by_code['this tree'].get('seconds'))}"
            f" s in format {by_code['this tree'].get('store format')} (this tree) against "
            f"{fmt(by_code[base].get('seconds'))} s in format {by_code[base].get('store format')}"
            f" ({base}); a term wrote {_span(written['this tree'])} files against "
            f"{_span(written[base])}.")
    return out


def _span(values: list) -> str:
    """"a" or "a-b" of the smallest and largest value (formatted), "–" when none."""
    if not values:
        return "–"
    lo, hi = fmt(min(values)), fmt(max(values))
    return lo if lo == hi else f"{lo}–{hi}"


def _local_seconds(rows: list[dict], row: dict) -> Any:
    """The local directory's seconds with ``row``'s scheduler and engine path."""
    return next((r.get("seconds") for r in rows if r.get("storage") == "local directory"
                 and r.get("scheduler") == row.get("scheduler")
                 and r.get("engine path") == row.get("engine path")), None)


def summary_cluster_model(rec: Record | None) -> list[str]:
    """The model's error against the runs made here, and its predictions at the largest
    size for 1 worker and the quickest worker count, per storage."""
    if rec is None:
        return ["The cluster model's predictions (`bench_scale.py --cluster-model`): "
                f"{NOT_MEASURED}."]
    out = []
    check = rec.table("check")
    if check is not None:
        errs = [(_num(r.get("error %")), r) for r in _rows(check)]
        errs = [(e, r) for e, r in errs if e is not None]
        if errs:
            worst, r = max(errs, key=lambda x: abs(x[0]))
            out.append(f"The cluster model predicted the {len(errs)} runs made here within "
                       f"{fmt(abs(worst))} % of their time (worst: {r.get('predicts')} from "
                       f"{r.get('from')}, {fmt(r.get('predicted s'))} s predicted against "
                       f"{fmt(r.get('measured s'))} s measured).")
    predicted = rec.table("predicted")
    if predicted is not None and predicted.rows:
        rows = _rows(predicted)
        n = max(_num(r.get("n")) or 0 for r in rows)
        parts = []
        for storage, mine in _grouped([r for r in rows if _num(r.get("n")) == n],
                                      "storage").items():
            timed = [r for r in mine if _num(r.get("seconds")) is not None]
            if not timed:
                continue
            one = min(timed, key=lambda r: _num(r.get("workers")))
            best = min(timed, key=lambda r: _num(r.get("seconds")))
            parts.append(f"{storage}: {fmt(one.get('seconds'))} s on {one.get('workers')} "
                         f"worker, {fmt(best.get('seconds'))} s at best on "
                         f"{best.get('workers')} workers")
        if parts:
            out.append(f"It predicts the inverse at n = {fmt(int(n))} as " + "; ".join(parts)
                       + ".")
    return out


def summary_when(records: dict[str, Record]) -> list[str]:
    """When to use bigT and when not, each sentence from a table's numbers: the grey and
    the colour alternatives (where bigT's inverse pays back, what is quicker for a few
    frames), and the schedulers (whether more processes paid on this machine)."""
    out = []
    for key, what in (("alternatives", "grey"), ("alternatives-colour", "colour")):
        rec = records.get("alternatives")
        table = rec.table(key) if rec else None
        if table is not None:
            out += when_sentences(table, what)
    rec = records.get("distributed")
    table = rec.table("schedulers") if rec else None
    if table is not None:
        timed = [r for r in _rows(table) if _num(r.get("total s")) is not None]
        if timed:
            best = min(timed, key=lambda r: _num(r.get("total s")))
            others = ", ".join(f"{r.get('scheduler')} {fmt(r.get('total s'))} s"
                               for r in timed if r is not best)
            out.append(f"On one machine, {best.get('scheduler')} ran the inverse quickest "
                       f"of the {len(timed)} schedulers ({fmt(best.get('total s'))} s; "
                       f"{others}).")
    return out or [f"When to use bigT, and when not: {NOT_MEASURED} (the alternatives and "
                   "the schedulers are needed)."]


def when_sentences(table: Table, what: str) -> list[str]:
    """At the largest size of an alternatives table: from how many frames bigT's
    explicit inverse (its cheapest-framed bigT row) is the quickest, and what is quicker
    for one frame."""
    rows = _rows(table)
    size = list(dict.fromkeys(r.get("size") for r in rows))[-1]
    costs = _costs([r for r in rows if r.get("size") == size])
    mine = [c for c in costs if c.method.startswith("bigT") and c.per_frame(64) is not None]
    if not mine:
        return []
    big = FRAME_COUNTS[-1]
    ours = min(mine, key=lambda c: c.per_frame(big))
    paid = payback(costs, ours, big)
    one = quickest(costs, 1)
    if paid is None:
        cheaper = min((c for c in costs if c is not ours and c.per_frame(big) is not None),
                      key=lambda c: c.per_frame(big))
        text = (f"{what.capitalize()}, at {size}: {ours.method} is never the quickest for "
                f"good: {cheaper.method}'s frames are as cheap ({fmt(cheaper.per_frame(big))} "
                f"s against {fmt(ours.per_frame(big))} s)")
    else:
        k, last = paid
        text = (f"{what.capitalize()}, at {size}: use {ours.method} for {fmt(k)} frames or "
                f"more: from there it is the quickest of the {len(costs)} methods timed, its "
                f"{fmt(ours.setup)} s setup included ({fmt(ours.per_frame(big))} s a frame"
                + (f"; the last it overtakes is {last.method}" if last else "") + ")")
    if one is not ours:
        text += (f"; not for a single frame: {one.method} gives it in {fmt(one.total(1))} s "
                 f"against {fmt(ours.total(1))} s")
    return [text + "."]


def summary_target(rec: Record | None) -> list[str]:
    """The range of --target-error's time over the best fixed setting's."""
    table = rec.table("target") if rec else None
    if table is None:
        return [f"`--target-error` against the best fixed setting: {NOT_MEASURED}."]
    ratios = [_num(r.get("ratio")) for r in _rows(table)]
    ratios = [x for x in ratios if x is not None]
    if not ratios:
        return []
    lo, hi = fmt(min(ratios)), fmt(max(ratios))
    cases = f"{len(ratios)} case{'s' if len(ratios) > 1 else ''}"
    return [f"`--target-error` reached its target in {lo if lo == hi else f'{lo}–{hi}'}× "
            f"the time of the best fixed setting found by a sweep ({cases})."]


@dataclass(frozen=True)
class ClaimVerdict:
    """One of the paper's claims and every check of it in this run."""

    figure: str
    paper: str
    checks: list[Claim]

    @property
    def judged(self) -> list[Claim]:
        return [c for c in self.checks if c.holds is not None]

    @property
    def failed(self) -> list[Claim]:
        return [c for c in self.judged if not c.holds]

    @property
    def holds(self) -> bool | None:
        """True when every judged check holds, False when one fails, None when none is
        judged."""
        return None if not self.judged else not self.failed


def claim_verdicts(records: Iterable[Record]) -> list[ClaimVerdict]:
    """The claims of every record, each claim once with all its checks (a claim measured
    several ways, e.g. Fig. 6(a)'s speed by the engine and by plain scipy, is one claim)."""
    groups: dict[tuple[str, str], list[Claim]] = {}
    for r in records:
        for c in r.claims:
            groups.setdefault((c.figure, c.paper), []).append(c)
    return [ClaimVerdict(f, p, cs) for (f, p), cs in groups.items()]


def summary_paper(records: Iterable[Record], found: bool) -> list[str]:
    """How many of the paper's claims hold, and which do not: one count and one list,
    both over the same claims (each claim once however many ways it was checked)."""
    if not found:
        return [f"Figs. 5, 6, 9 and 10(a) reproduced on bigT's scenes: {NOT_MEASURED}."]
    verdicts = [v for v in claim_verdicts(records) if v.holds is not None]
    failing = [v for v in verdicts if not v.holds]
    checks = sum(len(v.judged) for v in verdicts)
    text = (f"{len(verdicts) - len(failing)} of the {len(verdicts)} claims of the paper "
            f"checked hold on bigT's scenes ({checks} checks in all)")
    if failing:
        named = [f'{v.figure} "{v.paper}"' + (
            f" ({len(v.failed)} of its {len(v.judged)} checks fail)"
            if len(v.judged) > 1 else "") for v in failing]
        which = "the one that does not" if len(failing) == 1 else f"the {len(failing)} that do not"
        text += f"; {which}: " + "; ".join(named) + " (measured values in the table below)"
    return [text + "."]


def summary(records: dict[str, Record]) -> list[str]:
    """The generated summary: each topic's sentences under a bold lead."""
    topics = [
        ("When to use bigT, and when not", summary_when(records)),
        ("When bigT's stratified inverse, sparse LU or the matrix-free path is the "
         "right tool", summary_alternatives(records.get("alternatives"))),
        ("Which setting meets an error target fastest", summary_tradeoff(records.get("tradeoff"))
         # the 48x64 sweep (an own run) when it ran, else the full plan's 96x128 one
         + summary_target(records.get("target") or records.get("target-96x128"))),
        ("How it scales", summary_scale(records.get("scale"))
         + summary_distributed(records.get("distributed"))
         + summary_cluster_model(records.get("cluster-model"))
         + summary_objects(records.get("objects"))
         + summary_layout([records.get("layout"), records.get("layout-fhd")])),
        ("Kernels and throughput", summary_kernels(records.get("kernels"))
         + summary_video(records.get("video"))),
        ("Colour", summary_colour(records.get("colour"))
         + summary_alternatives_colour(records.get("alternatives"))),
        ("Calibration", summary_calibration(records.get("calibration"))),
        ("The paper's figures", summary_paper(records.values(), "paper" in records)),
    ]
    lines = ["## Summary", ""]
    for lead, sentences in topics:
        lines.append(f"**{lead}.**")
        lines += [f"- {s}" for s in sentences]
        lines.append("")
    return lines


#: The test a benchmark writes into a claim's measured text: "(holds: rho >= 1)", with
#: at most one level of parentheses inside.
_TEST = re.compile(r"\s*\(holds: ((?:[^()]|\([^()]*\))*)\)")


def split_test(measured: str) -> tuple[str, str]:
    """A claim's measured text and the test it was judged by: the benchmarks write the
    test into the text, as "(holds: rho >= 1)"; the table gives it its own column, so
    that a row never reads "(holds: ...) | no"."""
    tests = _TEST.findall(measured)
    return _TEST.sub("", measured).strip(), "; ".join(tests)


def claims_table(records: Iterable[Record]) -> list[str]:
    claims = [c for r in records for c in r.claims]
    lines = ["## The paper's claims against this run", ""]
    if not claims:
        return lines + [f"The paper's figures: {NOT_MEASURED}.", ""]
    lines += ["*Each row is one check: what was measured, the test the claim must pass, "
              "and whether this run passes it.*", "",
              "| figure | the paper | measured here | the claim holds when | holds here |",
              "|---|---|---|---|---|"]
    for c in claims:
        measured, test = split_test(c.measured)
        verdict = "–" if c.holds is None else fmt(bool(c.holds))
        lines.append(f"| {_cell(c.figure)} | {_cell(c.paper)} | {_cell(measured)} | "
                     f"{_cell(test) or '–'} | {verdict} |")
    return lines + [""]


# --- the sections ---------------------------------------------------------------------------

def _link(path: Path, base: Path) -> str:
    return Path(os.path.relpath(path, base)).as_posix()


def _log_tail(path: Path, count: int = LOG_TAIL) -> list[str]:
    try:
        lines = path.read_text(errors="replace").splitlines()[-count:]
    except OSError:
        return ["(no log)"]
    return ["```", *lines, "```"]


def _status(run: Run | None, rec: Record | None, out: Path, base: Path,
            stamp: Machine | None) -> list[str]:
    """The line under a section's heading: command, exit, time, log; or the failure."""
    if run is None:
        when = _when(rec.started) if rec else "?"
        return [f"Not run by this plan: the record is from {when}." + _other_code(rec, stamp),
                ""]
    log = out / run.log
    head = f"`{' '.join(run.command)}`"
    link = f"[{run.log}]({_link(log, base)})"
    if run.returncode is None:
        return [f"{head}: **did not finish** (interrupted after {fmt(run.seconds)} s); "
                f"the end of its log, {link}:", "", *_log_tail(log), ""]
    if run.returncode:
        return [f"{head}: **failed** (exit {run.returncode} after {fmt(run.seconds)} s); "
                f"the end of its log, {link}:", "", *_log_tail(log), ""]
    stale = ""
    if rec and stamp and rec.started and rec.started < stamp.started - 1:
        stale = f" The record below is from an earlier run ({_when(rec.started)})."
    return [f"{head}: ran in {fmt(run.seconds)} s{_estimated(run)}; its output: "
            f"{link}.{stale}" + _other_code(rec, stamp), ""]


def _estimated(run: Run) -> str:
    """The plan's estimate beside a run's time, when the plan gave one."""
    if run.estimated_seconds is None:
        return ""
    return f" (estimated {_duration(run.estimated_seconds)})"


def _other_code(rec: Record | None, stamp: Machine | None) -> str:
    """A sentence when ``rec`` was measured with other code than the run's stamp names."""
    if rec is None or stamp is None:
        return ""
    if rec.code is None:
        return " Its record does not say which code measured it."
    if rec.code != stamp.code:
        return f" **Measured with {rec.code.words()}** (the run started at {stamp.code.words()})."
    return ""


def section(i: int, name: str, run: Run | None, rec: Record | None, out: Path,
            base: Path, stamp: Machine | None) -> list[str]:
    title = rec.title if rec and rec.title else name
    lines = [f"## {i}. {title} (`{name}`)", ""] + _status(run, rec, out, base, stamp)
    if rec is None:
        if run is None:
            lines += [f"{NOT_MEASURED[0].upper()}{NOT_MEASURED[1:]}.", ""]
        elif run.returncode == 0:  # a script that prints its tables and records none
            lines += [f"It records no tables; the end of its output ({OUTPUT_TAIL} lines "
                      "at most):", "", *_log_tail(out / run.log, OUTPUT_TAIL), ""]
        return lines
    if run is not None and run.returncode:
        return lines  # a failed run's record, if any, is not its result
    for t in rec.tables:
        lines += md_table(t)
    for f in rec.figures:
        alt = f.caption.replace("[", "(").replace("]", ")")  # a bracket would end the link
        lines += [f"![{alt}]({_link(out / f.file, base)})", "", f"*{f.caption}*", ""]
    if rec.values:
        lines += [f"- {v.what} (`{v.key}`): **{fmt(v.value)}**" for v in rec.values.values()]
        lines.append("")
    for note in rec.notes:
        lines += [note, ""]
    return lines


# --- figures --------------------------------------------------------------------------------

def stamp_figure(path: Path, text: str) -> bool:
    """Draw ``text`` in a band under the PNG at ``path`` (once: a PNG text chunk marks
    it, so a second report over the same figure leaves it). True when stamped."""
    from PIL import Image, ImageDraw, ImageFont, PngImagePlugin

    with Image.open(path) as im:
        if STAMP_KEY in getattr(im, "text", {}):
            return False
        im = im.convert("RGB")
    font = ImageFont.load_default(size=max(10, im.width // 75))
    lines = _wrap(text, font, im.width - 12)
    step = int(font.size * 1.3)
    out = Image.new("RGB", (im.width, im.height + step * len(lines) + 8), "white")
    out.paste(im, (0, 0))
    draw = ImageDraw.Draw(out)
    for i, line in enumerate(lines):
        draw.text((6, im.height + 4 + i * step), line, fill=(90, 90, 90), font=font)
    info = PngImagePlugin.PngInfo()
    info.add_text(STAMP_KEY, text)
    out.save(path, pnginfo=info)
    return True


def _wrap(text: str, font, width: int) -> list[str]:
    """Greedy word wrap to ``width`` pixels."""
    lines, cur = [], ""
    for word in text.split(" "):
        trial = f"{cur} {word}".strip()
        if cur and font.getlength(trial) > width:
            lines.append(cur)
            cur = word
        else:
            cur = trial
    return lines + [cur] if cur else lines


# --- the whole file -------------------------------------------------------------------------

def render(out: Path, results: Path) -> str:
    """RESULTS.md's text for the records in ``out``, linking from ``results``' folder."""
    out, base = Path(out), Path(results).parent
    records = load_records(out)
    plan = Plan.load(out)
    stamp = Machine.load(out)
    order = list(plan.order) if plan else []
    order += [n for n in records if n not in order]
    lines = ["# bigT benchmark results", ""]
    lines += _stamp_lines(stamp, plan, records)
    lines += summary(records)
    lines += claims_table(records[n] for n in order if n in records)
    for i, name in enumerate(order, 1):
        lines += section(i, name, plan.run(name) if plan else None, records.get(name), out,
                         base, stamp)
    return "\n".join(lines).rstrip() + "\n"


def _duration(seconds: float) -> str:
    return f"{fmt(seconds)} s" if seconds < 120 else f"{fmt(seconds / 60)} min"


def _stamp_lines(stamp: Machine | None, plan: Plan | None,
                 records: dict[str, Record] | None = None) -> list[str]:
    if stamp is None:  # records without run_all.py: the best stamp left is this machine
        stamp, taken = machine(), "as this report was written: no machine.json"
    else:
        taken = "as the run started"
    kind = f"the {plan.kind} plan" if plan else "no plan (records only)"
    total = sum(r.seconds for r in plan.runs) if plan else None
    estimated = [r.estimated_seconds for r in plan.runs] if plan else []
    expected = (f" (estimated {_duration(sum(estimated))})"
                if estimated and None not in estimated else "")
    lines = [f"Generated by `benchmarks/report.py` from {kind}"
             + (f", {_duration(total)} of benchmarks{expected}" if total else "")
             + ". Every number below comes from that run; rerun with `make bench` "
               "(`--quick` for small sizes).", "",
             f"**Machine and versions** (taken {taken}): {stamp.line()}; load average "
             f"{' / '.join(fmt(v) for v in stamp.load_average)} at the start. "
             "Timings on a shared machine drift; compare within one table.", ""]
    return lines + code_lines(stamp.code, records or {})


def code_lines(start: CodeState, records: dict[str, Record]) -> list[str]:
    """Which code the records were measured with: one sentence when all agree with the
    run's start, else the records that differ; a warning when it was no commit's code."""
    lines = []
    if start.clean is False:
        lines += [f"**Not from a committed state:** the run started at {start.words()}; "
                  "its numbers cannot be reproduced from a commit.", ""]
    other = {n: r.code for n, r in records.items() if r.code is not None and r.code != start}
    unknown = [n for n, r in records.items() if r.code is None]
    if records and not other and not unknown:
        lines += [f"**Code:** all {len(records)} records were measured with {start.words()}.",
                  ""]
    if other:  # grouped by code: a part run after a full one names two groups, not 17
        groups: dict[str, list[str]] = {}
        for name, code in other.items():
            groups.setdefault(code.words(), []).append(f"`{name}`")
        here = [f"`{n}`" for n, r in records.items() if r.code == start]
        lines += ["**Code:** " + "; ".join(
            [f"{', '.join(here)} measured with {start.words()} (this run)"] * bool(here)
            + [f"{', '.join(names)} with {words}" for words, names in groups.items()])
            + ".", ""]
    if unknown:
        lines += [f"**Code:** {len(unknown)} record{'s' if len(unknown) > 1 else ''} "
                  f"({', '.join(unknown)}) do not say which code measured them (older "
                  "records).", ""]
    return lines


def write(out: Path, results: Path | None = None) -> Path:
    """Stamp the figures in ``out`` and write RESULTS.md (default ``out/RESULTS.md``)."""
    out = Path(out)
    results = Path(results) if results else out / "RESULTS.md"
    stamp = Machine.load(out) or machine()
    for rec in load_records(out).values():
        for f in rec.figures:
            if (out / f.file).exists():
                stamp_figure(out / f.file, stamp.line())
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(render(out, results), encoding="utf-8")
    return results


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=os.environ.get(OUT_ENV, "bench-out"),
                   help="where the records are (default $BIGT_BENCH_OUT or bench-out)")
    p.add_argument("--results", default=None, help="RESULTS.md to write (default OUT/RESULTS.md)")
    args = p.parse_args(argv)
    print(write(Path(args.out), Path(args.results) if args.results else None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
