"""What a user waits for before bigT does anything: whole ``bigT`` processes, from the
interpreter's start to its exit, for every command's help and for a warm invert of the
paper's 4x4 (issue #30: ``bigT --help`` <= 0.3 s, the 4x4 <= 1.0 s).

Each case is a new process (``python -m bigT.cli ...``, the checkout's bigT first on
``PYTHONPATH``), timed by the wall clock around it: the interpreter's start, the
imports, the work and the exit. The 4x4 is ``bigT scene dihedral4``, inverted with
``--terms 7`` into a fresh X.zarr each time, after one untimed run (warm: numba's
cache, the page cache). The best of ``--repeat`` runs is reported, with the median;
the cases take turns, so a load that comes and goes on the shared machine touches all
of them alike. ``--baseline DIR`` times another checkout (an older commit, in a
``git worktree``) in the same turns, for a before/after measured in one run.

    python benchmarks/bench_startup.py                        # best of 5
    python benchmarks/bench_startup.py --baseline /tmp/base   # before/after, one run
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from _results import Results, run_name  # noqa: E402

#: The goals of issue #30, seconds for a whole process.
GOALS = {"bigT --help": 0.3, "bigT invert (4x4, warm)": 1.0}
INVERT = "bigT invert (4x4, warm)"


@dataclass(frozen=True)
class Case:
    """One command line, run in the scratch folder after removing the entries
    ``clear`` names there (what the previous run wrote)."""

    label: str
    argv: tuple[str, ...]
    clear: tuple[str, ...] = ()


def commands(root: Path) -> list[tuple[str, ...]]:
    """Every command and acquire step of the checkout at ``root``, as its parser lists
    them (read in a child process, so this one imports nothing of that bigT)."""
    code = ("import argparse\nfrom bigT.cli import build_parser\n"
            "def subs(p):\n"
            "    return next((a.choices for a in p._actions\n"
            "                 if isinstance(a, argparse._SubParsersAction)), {})\n"
            "for name, p in subs(build_parser()).items():\n"
            "    print(name)\n"
            "    for step in subs(p):\n"
            "        print(name, step)\n")
    out = subprocess.run([sys.executable, "-c", code], env=_env(root), check=True,
                         capture_output=True, text=True).stdout
    return [tuple(line.split()) for line in out.splitlines() if line.strip()]


def _env(root: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(root), "PYTHONWARNINGS": "ignore"}


def run_once(case: Case, root: Path, workdir: Path) -> float:
    """Seconds of one whole ``bigT`` process of ``case``, with ``root``'s bigT."""
    for name in case.clear:
        shutil.rmtree(workdir / name, ignore_errors=True)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "bigT.cli", *case.argv], cwd=workdir,
                          env=_env(root), capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"bigT {' '.join(case.argv)} failed ({proc.returncode}):\n"
                         f"{proc.stderr}")
    return seconds


def cases(root: Path) -> list[Case]:
    helps = [Case("bigT --help", ("--help",))]
    helps += [Case(f"bigT {' '.join(c)} --help", (*c, "--help")) for c in commands(root)]
    invert = Case(INVERT, ("invert", "T.zarr", "-o", "X.zarr", "--terms", "7"),
                  clear=("X.zarr",))
    return helps + [invert]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5, help="runs of each case (default 5)")
    p.add_argument("--baseline", type=Path, default=None, metavar="DIR",
                   help="another checkout to time in the same turns (before/after)")
    args = p.parse_args(argv)

    roots = {"after": ROOT} if args.baseline is None else {"before": args.baseline.resolve(),
                                                           "after": ROOT}
    workdir = Path(tempfile.mkdtemp(prefix="bench_startup-"))
    res = Results(run_name("startup"), "Start-up: whole bigT processes")
    try:
        subprocess.run([sys.executable, "-m", "bigT.cli", "scene", "dihedral4", "-o",
                        "T.zarr", "--no-preview"], cwd=workdir, env=_env(ROOT), check=True,
                       capture_output=True)
        plan = cases(ROOT)
        for root in roots.values():  # untimed: numba's cache and the page cache warm
            run_once(plan[-1], root, workdir)
        times: dict[tuple[str, str], list[float]] = {}
        for _ in range(args.repeat):
            for case in plan:
                for which, root in roots.items():
                    times.setdefault((case.label, which), []).append(
                        run_once(case, root, workdir))
        res.table("startup", "whole processes, seconds", *_table(plan, roots, times),
                  note=f"best and median of {args.repeat} runs each, interleaved, on "
                       f"{os.cpu_count()} shared cores; load average "
                       f"{os.getloadavg()[0]:.1f} at the end")
        for label, key in (("bigT --help", "help_s"), (INVERT, "invert_4x4_s")):
            res.value(key, min(times[(label, "after")]), f"best {label}, seconds")
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    res.save()
    return 0


def _table(plan: list[Case], roots: dict, times: dict) -> tuple[list[str], list[list]]:
    """(columns, rows) of the table, printed as they are recorded."""
    columns = ["command"]
    for which in roots:
        columns += [f"{which}: best s", f"{which}: median s"]
    columns += ["goal s"] + (["before / after"] if "before" in roots else [])
    rows = []
    for case in plan:
        row = [case.label]
        for which in roots:
            runs = times[(case.label, which)]
            row += [round(min(runs), 3), round(statistics.median(runs), 3)]
        row.append(GOALS.get(case.label, ""))
        if "before" in roots:
            row.append(round(min(times[(case.label, "before")])
                             / min(times[(case.label, "after")]), 2))
        rows.append(row)
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join(str(cell) for cell in row))
    return columns, rows


if __name__ == "__main__":
    sys.exit(main())
