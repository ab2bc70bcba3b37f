"""Run every benchmark in turn and write RESULTS.md from what they record (``make bench``).

    python benchmarks/run_all.py            # full: benchmarks/RESULTS.md + benchmarks/results/
    python benchmarks/run_all.py --quick    # small sizes, under 5 min: bench-out/RESULTS.md
    python -m benchmarks --quick            # the same, from the repository's root
    python benchmarks/run_all.py --only paper,scale   # some of the plan; others' records stay
    python benchmarks/run_all.py --only reliability   # a long point run on its own
    python benchmarks/run_all.py --list     # the plan, each step's estimated minutes

The machine and versions are stamped into ``machine.json`` as the run starts; each
benchmark then runs in its own process (never two at once: they would share the cores
and skew each other's timings), with ``BIGT_BENCH_OUT`` pointing at the output folder
and ``BIGT_BENCH_NAME`` naming its record; its printed output is kept as
``<name>.txt`` beside the records. ``report.py`` then writes RESULTS.md, the figures
beside it. A benchmark that fails is reported as failed there, with the end of its log.
A whole plan first removes the records an earlier run left in the folder; ``--only``
keeps the others' (RESULTS.md marks them as from an earlier run).

The committed results (``benchmarks/RESULTS.md``, the full plan without ``--out``) must
come from a commit: run_all refuses a work tree with uncommitted changes there (the
results themselves excepted), since numbers from code no commit holds cannot be
reproduced or reviewed; ``--allow-dirty`` runs anyway and RESULTS.md then says, at its
top, that it is not from a committed state. Other runs (``--quick``, ``--out``) only
say so. Every record names the code it was measured with, so a plan run in parts, or
a tree that changed during a long run, shows in RESULTS.md.
Scratch data (scenes, inverses) stays in ``bench-out/``, which git ignores; the full
plan's scenes are reused by a later run.

Every step carries its estimated minutes and where the estimate comes from
(:class:`Step`): ``--list`` prints them, each step is announced with its estimate and
the plan's time left, and ``runs.json`` keeps the estimate beside the time taken.
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

import report  # noqa: E402
from _results import NAME_ENV, OUT_ENV, code_state, machine  # noqa: E402

@dataclass(frozen=True)
class Step:
    """One benchmark of a plan and how long it is expected to take.

    ``argv`` is the script (in benchmarks/) and its arguments, run from the repository's
    root; ``minutes`` the wall time expected on this machine (2 cores, otherwise idle)
    with the scenes an earlier run left in bench-out/; ``basis`` says where that number
    comes from (a recorded run, a timing of the step, or of its parts), so that a plan's
    length is known before it runs and can be checked after (RESULTS.md shows both)."""

    name: str
    argv: tuple[str, ...]
    minutes: float
    basis: str

    @property
    def shown(self) -> list[str]:
        """The command as RESULTS.md and the log show it."""
        return ["python", f"benchmarks/{self.argv[0]}", *self.argv[1:]]


def step(name: str, minutes: float, basis: str, *argv: str) -> Step:
    return Step(name, tuple(argv), minutes, basis)


#: Where the per-step estimates come from (the ``basis`` of each step).
RECORDED = "the last full run's runs.json (2026-11-24, load ~1.1 at its start)"
MEASURED = ("the full run of 2026-11-27 (37ecaa5, load ~1.5, its scenes built): "
            "results/runs.json")
#: The grey scenes of tradeoff, inverse-dense and defaults share one folder: the same
#: builder and arguments, so each scene (the dense 384x512 corner above all, minutes
#: to build) is built once for the three.
GREY_SCENES = "bench-out/tradeoff"
#: The last commit whose stores are format 1 (a group of three arrays per tile): the
#: layout's baseline.
LAST_FORMAT_1 = "2789f82"
#: The records of bench_scale's own runs at full HD and 4K (the scale step's comment).
OWN_SCALE_RUNS = "bench-out/scale-fhd.json,bench-out/scale-4k.json"

#: The full plan (``make bench``, within about an hour on 2 cores: issue #34), in the
#: order of issue #16: the paper's figures, time against error, the alternatives,
#: scaling; then the rest. Scratch folders are under bench-out/ (relative to the
#: repository's root, the children's working directory); the estimates are for a run
#: that finds the scenes an earlier run built there (a first run builds them too:
#: :data:`FIRST_RUN_BUILDS`). Trimmed to fit, each cut a point another step measures or
#: that this wave does not change; they are in :data:`OWN_RUNS`, run with ``--only``:
#: the target sweeps at 48x64 (rho 0.2 and 0.5; target-96x128 measures rho 0.2 where
#: runs last seconds, defaults the default target on six scenes) and at rho 0.9, the
#: defaults' 192x256 scenes (between the 96x128 ones and the dense 384x512 corner), the
#: kernels at 96x128 (192x256 is the size of the alternatives' and the scheduler runs),
#: reliability (the tests assert its crash points); and, as before, compensate's
#: 384x512 throughput (alternatives and video measure it), stability's long sweep and
#: the scenes' build times (scale's table has them).
FULL = [
    step("paper", 3.7, MEASURED, "bench_paper.py"),
    step("tradeoff", 8.8, MEASURED, "bench_tradeoff.py", "--workdir", GREY_SCENES),
    # rho 0.2 at n = 12288, where the runs last seconds, not tenths (fixed costs)
    step("target-96x128", 0.4, MEASURED, "bench_target.py", "--size", "96x128", "--rho",
         "0.2"),
    # grey 48x64 to 384x512, and the colour Cornell box at 48x64 and 96x128 (issue #34)
    step("alternatives", 11.3, MEASURED, "bench_alternatives.py",
         "--workdir", "bench-out/alternatives"),
    # the full-HD point (~40 min) and 4K (~1 h) are run on their own, each into its own
    # record, which this step's table and plot take in, marked as such:
    #   BIGT_BENCH_OUT=bench-out BIGT_BENCH_NAME=scale-4k python benchmarks/bench_scale.py
    #       --min-size 8294400 --max-size 8294400 --ff-cut 7e-5 --workdir bench-out/scale
    #   (scale-fhd: --min-size 2073600 --max-size 2073600)
    step("scale", 5.9, MEASURED, "bench_scale.py", "--min-size", "12288", "--max-size",
         "786432", "--workdir", "bench-out/scale", "--own-runs", OWN_SCALE_RUNS),
    step("kernels", 4.1, MEASURED, "bench_kernels.py", "--sizes", "192x256", "--repeat",
         "2"),
    step("distributed", 1.6, MEASURED, "bench_distributed.py", "--size", "192x256",
         "--workdir", "bench-out/distributed"),
    # issue #34 (5): the cluster model checked on threads, local:1 and local:2 (192x256),
    # its full-HD and 4K predictions beside them
    step("cluster-model", 3.0, "its own note (6 runs of the 192x256 corner, ~3 min)",
         "bench_scale.py", "--cluster-model", "--workdir", "bench-out/cluster-model"),
    step("inverse-dense", 2.1, MEASURED, "bench_inverse.py", "--size", "384x512",
         "--density", "dense", "--settings", "power:1e-5,power:3e-6:1e-4,"
         "power:3e-6:1e-4:1e-5,power:3e-6:1e-4:3e-5", "--sample", "2048",
         "--memory-limit", "2GiB", "--workdir", GREY_SCENES),
    # issue #30: today's defaults against the old at equal error, on the six 96x128
    # scenes and the dense 384x512 corner of the timing goal
    step("defaults", 2.5, MEASURED,
         "bench_defaults.py", "--sizes", "96x128", "--workdir", GREY_SCENES),
    step("video", 6.3, MEASURED, "bench_video.py", "--out", "bench-out/video"),
    # the colour Cornell box at 384x512 (issue #28's goals): grey vs general vs
    # global-mixing, seen ΔE, video; time against error of both paths at 96x128, at the
    # loosest and tightest prune (the middle decade adds a third of the sweep's time)
    step("colour", 4.4, MEASURED, "bench_colour.py",
         "--sweep-prunes", "1e-4,1e-6", "--workdir", "bench-out/colour"),
    # issue #29 on the simulated nonlinear rig: T from one exposure against brackets, the
    # seen error with and without the calibrated responses (12x16 and 24x32)
    step("calibration", 0.8, MEASURED,
         "bench_calibration.py", "--workdir", "bench-out/calibration"),
    step("compensate", 1.0, MEASURED, "bench_compensate.py", "--skip", "throughput"),
    step("out-of-core", 0.6, MEASURED, "bench_out_of_core.py", "--n", "393216",
         "--memory-limit", "1536MiB"),
    step("store", 0.2, MEASURED, "bench_store.py"),
    # the store layout's seconds, files and bytes per term against 2789f82, the last
    # commit that wrote format 1 (a group per tile); at full HD: the own run layout-fhd
    step("layout", 1.3, "two runs of each tree at ~12 and ~20 s, and the imports",
         "bench_layout.py", "--baseline-commit", LAST_FORMAT_1, "--workdir",
         "bench-out/layout"),
    # whole bigT processes: every help, a warm 4x4
    step("startup", 0.3, MEASURED,
         "bench_startup.py"),
    # issue #31: local directory against S3 (moto) on loopback, threads and 2 workers;
    # one repeat (six runs of the 192x256 corner)
    step("objects", 2.5, MEASURED,
         "bench_objects.py", "--repeats", "1", "--workdir", "bench-out/objects"),
    step("acquire", 0.8, MEASURED, "bench_acquire.py", "--grid", "48x64", "--camera",
         "120x160"),
    step("stability", 0.1, MEASURED, "bench_stability.py", "--quick"),
]
#: What a first run (no scenes in bench-out/ yet) adds to the full plan's estimate,
#: minutes: the dense 384x512 corner four times (tradeoff's folder, alternatives',
#: layout's in both formats; ~2 min each idle, 8 under load), tradeoff's other scenes
#: (~3), the colour Cornell boxes of 384x512 (grey and colour, 5.5), the scale ladder's and the 192x256
#: scenes of the scheduler runs (~3).
FIRST_RUN_BUILDS = 20
#: Long points run on their own (``--only NAME``, into the same results: RESULTS.md
#: marks their records as from their own run), out of the full plan to keep it within
#: the hour: each answers what a step of the full plan answers at another size or
#: setting, or what the tests assert.
OWN_RUNS = [
    # rho 0.2 and 0.5 (48x64 corner and Cornell box), two targets
    step("target", 5.4, RECORDED, "bench_target.py", "--quick", "--rho", "0.2,0.5"),
    # rho 0.9 (48x64 Cornell box): tens of terms per setting
    step("target-high-rho", 8.3, RECORDED, "bench_target.py", "--quick", "--rho", "0.9",
         "--targets", "0.00392"),
    step("defaults-192x256", 12.0, "its docstring (all sizes ~25 min) less the 96x128 "
         "scenes and the 384x512 corner", "bench_defaults.py", "--sizes", "192x256",
         "--large", "", "--workdir", GREY_SCENES),
    step("kernels-96x128", 1.8, "results/kernels.txt of the last full run (26 s a "
         "repeat, 3 repeats)", "bench_kernels.py", "--sizes", "96x128"),
    step("reliability", 4.6, RECORDED, "bench_reliability.py", "--quick"),
    # the layout at full HD: T of the scale step's own full-HD run (the dense preset at
    # 1080x1920) for this tree; the baseline builds its own in format 1 (~15 min)
    # issue #30's size sweep at full HD (n = 2073600): the engine against the plain
    # scipy series (~10 min, most of it scipy's), on the scale step's full-HD scene
    step("paper-fhd", 16.2, "its own run (f679881: 969 s, one round: engine 180 s, "
         "scipy 776 s)",
         "bench_paper.py", "--only", "sweep", "--sweep-min", "2073600", "--sweep-max",
         "2073600", "--sweep-scenes", "bench-out/scale"),
    step("layout-fhd", 20.0, "its own run's build and inverses", "bench_layout.py",
         "--size", "1080x1920", "--repeats", "1", "--baseline-commit", LAST_FORMAT_1,
         "--scene", "bench-out/scale/corner-1080x1920/T.zarr", "--workdir",
         "bench-out/layout-fhd"),
]
#: The quick plan, under 5 minutes on 2 cores: the benchmarks the summary quotes, at
#: small sizes. Video, compensate, inverse, scenes, acquire, stability and reliability
#: are left to the full plan: with them the quick plan would take twice as long.
QUICK_RUN = "a quick run from a fresh clone (2026-11-26 23:01, load ~1)"
QUICK = [
    step("paper", 0.3, QUICK_RUN, "bench_paper.py", "--quick"),
    step("tradeoff", 0.2, QUICK_RUN, "bench_tradeoff.py", "--quick", "--scenes",
         "corner-96x128-sparse", "--workdir", "bench-out/tradeoff-quick"),
    step("target", 0.15, QUICK_RUN, "bench_target.py", "--quick", "--rho", "0.2",
         "--targets", "0.00392"),
    step("alternatives", 1.15, QUICK_RUN, "bench_alternatives.py", "--quick", "--sizes",
         "32x48,48x64", "--colour-sizes", "24x32", "--workdir",
         "bench-out/alternatives-quick"),
    step("scale", 0.35, QUICK_RUN, "bench_scale.py", "--max-size", "49152",
         "--no-compensate", "--workdir", "bench-out/scale-quick"),
    step("kernels", 0.45, QUICK_RUN, "bench_kernels.py", "--sizes", "48x64", "--repeat",
         "1"),
    step("distributed", 0.8, QUICK_RUN, "bench_distributed.py", "--size", "48x64",
         "--workdir", "bench-out/distributed-quick"),
    step("out-of-core", 0.1, QUICK_RUN, "bench_out_of_core.py", "--n", "32768",
         "--memory-limit", "2GiB"),
    step("store", 0.1, QUICK_RUN, "bench_store.py", "--n", "20000", "--nnz-per-row",
         "20"),
    step("colour", 0.3, QUICK_RUN, "bench_colour.py", "--quick", "--workdir",
         "bench-out/colour-quick"),
]


def estimate(plan: list[Step]) -> float:
    """The plan's estimated wall time, minutes."""
    return sum(s.minutes for s in plan)


def describe(plan: list[Step]) -> list[str]:
    """One line per step (name, estimate, command) and the total: ``--list``."""
    lines = [f"{s.name:<22} ~{s.minutes:4.1f} min  {shlex.join(s.argv)}" for s in plan]
    return lines + [f"{'total':<22} ~{estimate(plan):4.1f} min"]


def describe_full() -> list[str]:
    """``--list`` of the full plan: its steps, a first run's scene builds, the own runs."""
    return (describe(FULL) + [f"(a first run also builds the scenes: ~{FIRST_RUN_BUILDS} "
                              "min more)", "", "run on their own (--only NAME):"]
            + describe(OWN_RUNS))


def default_paths(quick: bool, out: str | None) -> tuple[Path, Path]:
    """(output folder, RESULTS.md). The full run's results are committed, so a quick run
    writes elsewhere (``bench-out/``, ignored by git) and never overwrites them."""
    if out:
        folder = Path(out).resolve()
        return folder, folder / "RESULTS.md"
    if quick:
        return ROOT / "bench-out", ROOT / "bench-out" / "RESULTS.md"
    return HERE / "results", HERE / "RESULTS.md"


def refuse_dirty(results: Path, allow_dirty: bool) -> str | None:
    """Why this run may not write ``results``, or None. Only the committed RESULTS.md is
    guarded: a quick run or one into another folder is scratch, and says what it ran."""
    if allow_dirty or results.resolve() != (HERE / "RESULTS.md").resolve():
        return None
    code = code_state(ROOT)
    if code.clean is not False:
        return None
    return (f"run_all: the committed results must come from a commit, and this tree is at "
            f"{code.words()}. Commit (or stash) first, or pass --allow-dirty to run anyway "
            "(RESULTS.md will then say it is not from a committed state), or --out DIR.")


def run_one(todo: Step, out: Path) -> report.Run:
    """Run one benchmark in a child process, its output shown and kept in ``<name>.txt``."""
    name, log = todo.name, f"{todo.name}.txt"
    (out / f"{name}.json").unlink(missing_ok=True)  # a failed run must not show the old record
    argv = [sys.executable, str(HERE / todo.argv[0]), *todo.argv[1:]]
    print(f"== {name}: {' '.join(todo.shown)}  (-> {out / log}; estimated "
          f"~{todo.minutes:g} min)", flush=True)
    env = {**os.environ, "PYTHONWARNINGS": "ignore", OUT_ENV: str(out), NAME_ENV: name}
    # the benchmarks that call the library in their own process run it as the bigT
    # command does (bigT.cli._advise_no_huge_pages), their rivals in that process too
    env.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
    t0 = time.perf_counter()
    with open(out / log, "w") as f:
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=env, cwd=ROOT)
        for line in proc.stdout:
            sys.stdout.write(line)
            f.write(line)
        proc.wait()
    seconds = time.perf_counter() - t0
    print(f"== {name}: exit {proc.returncode} after {seconds:.0f} s (estimated "
          f"{60 * todo.minutes:.0f} s)\n", flush=True)
    return report.Run(name, todo.shown, proc.returncode, seconds, log, 60 * todo.minutes)


def select(plan: list[Step], only: str | None, others: list[Step] = ()) -> list[Step]:
    """The steps ``--only`` names (of ``plan``, or of ``others``: the long points run on
    their own), in the plan's order; the whole plan without ``--only``."""
    if not only:
        return plan
    wanted = set(only.split(","))
    known = [s for s in [*plan, *others]]
    unknown = wanted - {s.name for s in known}
    if unknown:
        raise SystemExit(f"run_all: not in this plan: {', '.join(sorted(unknown))} "
                         f"(--list shows the plan)")
    return [s for s in known if s.name in wanted]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes, under 5 minutes")
    p.add_argument("--only", default=None, help="comma-separated benchmark names")
    p.add_argument("--out", default=None,
                   help="output folder (records, logs, figures, RESULTS.md); default "
                        "benchmarks/results with benchmarks/RESULTS.md, or bench-out "
                        "with --quick")
    p.add_argument("--list", action="store_true", help="print the plan and stop")
    p.add_argument("--allow-dirty", action="store_true",
                   help="write benchmarks/RESULTS.md from a tree with uncommitted changes "
                        "(it is marked as such)")
    args = p.parse_args(argv)
    plan = QUICK if args.quick else FULL
    others = [] if args.quick else OWN_RUNS
    if args.list:
        print("\n".join(describe(plan) if args.quick else describe_full()))
        return 0
    todo = select(plan, args.only, others)
    out, results = default_paths(args.quick, args.out)
    refusal = refuse_dirty(results, args.allow_dirty)
    if refusal:
        raise SystemExit(refusal)
    out.mkdir(parents=True, exist_ok=True)
    print(f"stamp: {machine().save(out)}", flush=True)  # at the start: it describes the run
    earlier = report.Plan.load(out) if args.only else None
    if not args.only:  # a whole plan: RESULTS.md shows this run's records and no older ones
        for name in report.load_records(out):
            (out / f"{name}.json").unlink()
    names = {s.name for s in todo}
    runs = [r for r in (earlier.runs if earlier else []) if r.name not in names]
    kind = ("quick" if args.quick else "full") + (" (part)" if args.only else "")
    print(f"plan: {len(todo)} benchmark{'' if len(todo) == 1 else 's'}, estimated "
          f"~{estimate(todo):.0f} min", flush=True)
    t0 = time.perf_counter()
    try:
        for i, todo_step in enumerate(todo):
            order = [s.name for s in plan] + [r.name for r in runs
                                              if r.name not in {s.name for s in plan}]
            order += [todo_step.name] if todo_step.name not in order else []
            left = estimate(todo[i:])
            print(f"-- {i + 1}/{len(todo)}, {(time.perf_counter() - t0) / 60:.0f} min "
                  f"so far, ~{left:.0f} min estimated to go", flush=True)
            # saved before and after each run: an interrupted one is reported as such
            report.Plan(kind, order, runs + [report.Run(
                todo_step.name, todo_step.shown, None, 0.0, f"{todo_step.name}.txt",
                60 * todo_step.minutes)]).save(out)
            runs.append(run_one(todo_step, out))
            report.Plan(kind, order, runs).save(out)
    finally:  # Ctrl-C too: what did run is reported
        print(f"results: {report.write(out, results)} "
              f"({time.perf_counter() - t0:.0f} s of benchmarks, "
              f"~{60 * estimate(todo):.0f} s estimated)", flush=True)
    failed = [r.name for r in runs if r.returncode]
    if failed:
        print("failed: " + ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
