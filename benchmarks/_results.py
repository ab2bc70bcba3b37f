"""What a benchmark hands to ``benchmarks/RESULTS.md``: its tables, figures, named values
and, for the paper's figures, the paper's claim beside the value measured.

Every benchmark script keeps printing its own tables; it also records them here::

    from _results import Results, run_name
    res = Results(run_name("scale"))             # one per script run
    res.table("inverse", "4-term inverse against n", ["n", "s", "error"], rows)
    png = res.figure_path("scale.png")           # where to save a plot
    ...; res.figure("scale.png", "time and peak memory against n")
    res.value("exponent", 0.73, "fitted exponent of time against n")
    res.claim("Fig. 6", "T_7^-1 > 8x faster than the true inverse", "11.2x faster")
    res.save()                                   # -> $BIGT_BENCH_OUT/scale.json

``run_all.py`` sets ``BIGT_BENCH_OUT`` (``benchmarks/results`` for the full plan,
``bench-out`` for ``--quick`` and for a script run by hand) and ``BIGT_BENCH_NAME`` (the
plan's name for the run, so one script run twice with other arguments keeps two
records), stamps the machine and versions into ``machine.json`` (:func:`machine`) and,
once every script has run, ``report.py`` assembles RESULTS.md from the JSON files:
nothing in RESULTS.md is typed in by hand. Values are plain numbers (or strings), so the
summary at the top of RESULTS.md can quote them by ``(benchmark, key)``.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

#: Where every benchmark writes its JSON record and figures (``run_all.py`` sets it).
OUT_ENV = "BIGT_BENCH_OUT"
#: The name ``run_all.py`` gives a run of a script (one script may run twice in a plan,
#: with other arguments: each run needs its own record).
NAME_ENV = "BIGT_BENCH_NAME"
#: The stamp of the machine and versions, written by ``run_all.py`` as the run starts.
MACHINE_FILE = "machine.json"
#: The packages whose versions the stamp names (the rivals only when installed).
PACKAGES = ("numpy", "scipy", "numba", "dask", "distributed", "zarr")
RIVALS = ("sparse_dot_topn", "python-graphblas", "pypardiso")


def out_dir() -> Path:
    """The directory benchmarks write their records and figures into (created)."""
    path = Path(os.environ.get(OUT_ENV, "bench-out"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def run_name(default: str) -> str:
    """The record's name: ``run_all.py``'s name for this run, else ``default``."""
    return os.environ.get(NAME_ENV) or default


@dataclass(frozen=True)
class Table:
    """A table of RESULTS.md: ``rows`` are lists of cells (numbers or strings), one per
    column; ``note`` is a sentence printed under it (what was run, how to read it)."""

    key: str
    title: str
    columns: list[str]
    rows: list[list[Any]]
    note: str = ""


@dataclass(frozen=True)
class Figure:
    """A PNG written into :func:`out_dir` (``file`` is relative to it)."""

    file: str
    caption: str


@dataclass(frozen=True)
class Value:
    """A named number the summary can quote."""

    key: str
    value: Any
    what: str


@dataclass(frozen=True)
class Claim:
    """One of the paper's claims and what this run measured for it."""

    figure: str
    paper: str
    measured: str
    holds: bool | None = None


def significant(x: float, digits: int = 3) -> str:
    """``x`` to ``digits`` significant figures, scientific below 1e-3 (errors) and from
    1e6, as RESULTS.md's cells print numbers: "4.98e-4", "0.0392", "1.5"."""
    a = abs(x)
    if a != 0 and math.isfinite(x) and (a < 1e-3 or a >= 1e6):
        mant, exp = f"{x:.{digits - 1}e}".split("e")
        return f"{mant}e{int(exp)}"
    return f"{x:.{digits}g}"


#: The most significant figures :func:`beside` prints (float64 holds ~16).
MAX_DIGITS = 12


def beside(value: float, target: float, digits: int = 3) -> str:
    """``value`` printed beside ``target`` with enough significant figures (``digits``
    at least) that it reads on its own side: an error of 4.998e-4 against a target of
    5e-4 prints "4.998e-4", never "5.00e-4", which would read as meeting it exactly.
    A value equal to its target prints at ``digits``."""
    for d in range(digits, MAX_DIGITS + 1):
        text = significant(value, d)
        shown = float(text)
        if (value < target) == (shown < target) and (value > target) == (shown > target):
            return text
    return significant(value, MAX_DIGITS)


def _jsonable(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if hasattr(x, "item") and callable(x.item):  # numpy scalars
        return _jsonable(x.item())
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    return x


@dataclass
class Results:
    """The record of one benchmark run (one JSON file, ``<name>.json``)."""

    name: str
    title: str = ""
    command: str = ""
    tables: list[Table] = field(default_factory=list)
    figures: list[Figure] = field(default_factory=list)
    values: list[Value] = field(default_factory=list)
    claims: list[Claim] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    started: float = field(default_factory=time.time)
    #: The code this record was measured with, read as it is saved (a plan run in parts,
    #: or a tree edited during a long run, would otherwise hide behind the run's stamp).
    code: dict = field(default_factory=dict)

    def table(self, key: str, title: str, columns: Sequence[str],
              rows: Sequence[Sequence[Any]], note: str = "") -> None:
        self.tables.append(Table(key, title, list(columns), [list(r) for r in rows], note))

    def figure_path(self, file: str) -> Path:
        """Where to save figure ``file`` (a PNG name, no directories)."""
        return out_dir() / file

    def figure(self, file: str, caption: str) -> None:
        self.figures.append(Figure(file, caption))

    def value(self, key: str, value: Any, what: str) -> None:
        self.values.append(Value(key, value, what))

    def claim(self, figure: str, paper: str, measured: str, holds: bool | None = None) -> None:
        self.claims.append(Claim(figure, paper, measured, holds))

    def note(self, text: str) -> None:
        self.notes.append(text)

    def save(self) -> Path:
        """Write ``<name>.json`` into :func:`out_dir` and return its path."""
        record = asdict(self)
        record["seconds"] = time.time() - self.started
        record["code"] = asdict(code_state())
        path = out_dir() / f"{self.name}.json"
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(_jsonable(record), indent=1))
        os.replace(tmp, path)
        return path


@dataclass(frozen=True)
class CodeState:
    """Which commit the benchmarks ran and whether the work tree matched it.

    ``clean`` is None when git could not tell (no checkout); ``changed`` names the
    files that differed from the commit (at most :data:`CHANGED_SHOWN`; the results a
    run writes are not counted: they are not the code that made them)."""

    commit: str  # short hash of HEAD, "unknown" without git
    clean: bool | None
    changed: list[str] = field(default_factory=list)
    changed_count: int = 0

    def words(self) -> str:
        """"commit 1a2b3c4, clean tree" or the changes that make it no commit's state."""
        if self.clean is None:
            return f"commit {self.commit} (whether the tree was clean is unknown)"
        if self.clean:
            return f"commit {self.commit}, clean tree"
        if not self.changed_count:  # an older stamp: "+dirty", the files not named
            return f"commit {self.commit} with uncommitted changes: not any commit's code"
        more = self.changed_count - len(self.changed)
        files = ", ".join(self.changed) + (f" and {more} more" if more > 0 else "")
        return (f"commit {self.commit} with uncommitted changes to {self.changed_count} "
                f"file{'s' if self.changed_count != 1 else ''} ({files}): not any "
                "commit's code")

    @classmethod
    def from_dict(cls, d: dict | str | None) -> "CodeState":
        """From a record or stamp; an older stamp's ``"1a2b3c4+dirty"`` string too."""
        if isinstance(d, dict) and d:
            return cls(d.get("commit", "unknown"), d.get("clean"), list(d.get("changed", [])),
                       d.get("changed_count", len(d.get("changed", []))))
        if isinstance(d, str) and d:
            head, dirty = d.removesuffix("+dirty"), d.endswith("+dirty")
            return cls(head, None if head == "unknown" else not dirty)
        return cls("unknown", None)


#: Changed files named in a stamp (the count is always given).
CHANGED_SHOWN = 5


@dataclass(frozen=True)
class Machine:
    """The machine a run ran on and the code it ran: stamped on RESULTS.md and on every
    figure, so a number is never read without them."""

    cpu_model: str
    cores: int  # os.cpu_count()
    usable_cores: int  # the affinity: what this process may run on
    memory_gib: float
    python: str
    code: CodeState
    versions: dict[str, str]
    load_average: list[float]  # at the start: the machine may be shared
    started: float

    def line(self) -> str:
        """One line: the machine, the code, then the versions."""
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime(self.started))
        vers = ", ".join(f"{k} {v}" for k, v in self.versions.items())
        return (f"{self.cpu_model}, {self.cores} cores ({self.usable_cores} usable), "
                f"{self.memory_gib:.1f} GiB; bigT {self.code.words()}; Python "
                f"{self.python}, {vers}; {when}")

    def save(self, directory: Path) -> Path:
        path = Path(directory) / MACHINE_FILE
        path.write_text(json.dumps(asdict(self), indent=1))
        return path

    @classmethod
    def load(cls, directory: Path) -> "Machine | None":
        path = Path(directory) / MACHINE_FILE
        if not path.exists():
            return None
        d = json.loads(path.read_text())
        d["code"] = CodeState.from_dict(d.pop("code", None) or d.pop("commit", None))
        d.pop("commit", None)
        return cls(**d)


def _proc_field(path: str, key: str) -> str | None:
    """The value of the first ``key: value`` line of a /proc file (None off Linux)."""
    try:
        for line in Path(path).read_text().splitlines():
            name, _, value = line.partition(":")
            if name.strip() == key:
                return value.strip()
    except OSError:
        pass
    return None


def code_state(root: Path | None = None) -> CodeState:
    """HEAD's short hash and whether tracked or untracked files differ from it (the
    results a run writes excepted: they are not the code that made them)."""
    root = root or Path(__file__).resolve().parent.parent

    def git(*args):
        out = subprocess.run(["git", "-C", str(root), *args], capture_output=True,
                             text=True, timeout=30)
        if out.returncode:
            raise OSError(out.stderr.strip())
        return out.stdout

    try:
        head = git("rev-parse", "--short", "HEAD").strip()
        status = git("status", "--porcelain", "--", ".", ":!benchmarks/results",
                     ":!benchmarks/RESULTS.md", ":!bench-out")
    except (OSError, subprocess.SubprocessError):
        return CodeState("unknown", None)
    changed = [line[3:] for line in status.splitlines() if line.strip()]
    return CodeState(head or "unknown", not changed, changed[:CHANGED_SHOWN], len(changed))


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in PACKAGES + RIVALS:
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            if pkg in PACKAGES:
                out[pkg] = "not installed"
    return out


def machine(root: Path | None = None) -> Machine:
    """Read the stamp off this machine and the checkout at ``root`` (this repository)."""
    root = root or Path(__file__).resolve().parent.parent
    kib = _proc_field("/proc/meminfo", "MemTotal")
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        usable = os.cpu_count() or 1
    return Machine(
        cpu_model=_proc_field("/proc/cpuinfo", "model name") or platform.processor()
        or platform.machine(),
        cores=os.cpu_count() or 1, usable_cores=usable,
        memory_gib=int(kib.split()[0]) / 2**20 if kib else float("nan"),
        python=platform.python_version(), code=code_state(root), versions=_versions(),
        load_average=[round(v, 2) for v in os.getloadavg()], started=time.time())


def load(path: Path) -> dict:
    """A record written by :meth:`Results.save`, as a dict."""
    return json.loads(Path(path).read_text())
