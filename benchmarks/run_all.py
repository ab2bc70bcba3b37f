"""Run every benchmark in turn and write RESULTS.md from what they record (``make bench``).

    python benchmarks/run_all.py            # full: benchmarks/RESULTS.md + benchmarks/results/
    python benchmarks/run_all.py --quick    # small sizes, under 5 min: bench-out/RESULTS.md
    python -m benchmarks --quick            # the same, from the repository's root
    python benchmarks/run_all.py --only paper,scale   # some of the plan; others' records stay

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
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

import report  # noqa: E402
from _results import NAME_ENV, OUT_ENV, code_state, machine  # noqa: E402

#: The full plan (about 70 minutes on 2 cores before issue #34's colour alternatives,
#: colour sweep, calibration and cluster model, which add about 11), in the order of
#: issue #16: the paper's
#: figures, time against error (pruning included), the alternatives, scaling, kernels,
#: distributed; then the rest. Scratch folders are under bench-out/ (relative to the
#: repository's root, the children's working directory), where a later run reuses the
#: scenes. Trimmed to fit: the target sweep at rho 0.9 asks for one target only,
#: compensate its 384x512 throughput (alternatives and video measure that),
#: stability and reliability run their quick sweeps (the tests run them all), and the
#: scenes' build times come from scale's table instead of bench_scenes.py.
FULL = [
    ("paper", ["bench_paper.py"]),
    ("tradeoff", ["bench_tradeoff.py", "--workdir", "bench-out/tradeoff"]),
    ("target", ["bench_target.py", "--quick", "--rho", "0.2,0.5"]),
    # rho 0.2 at n = 12288, where the runs last seconds, not tenths (fixed costs)
    ("target-96x128", ["bench_target.py", "--size", "96x128", "--rho", "0.2"]),
    # rho 0.9 (48x64 Cornell box): tens of terms per setting, ~10 min with its sweep
    ("target-high-rho", ["bench_target.py", "--quick", "--rho", "0.9", "--targets",
                         "0.00392"]),
    # grey up to 384x512, and the colour Cornell box at 48x64 and 96x128 (issue #34)
    ("alternatives", ["bench_alternatives.py", "--workdir", "bench-out/alternatives"]),
    # the full-HD point (--max-size 2073600, ~40 min) is run on its own
    ("scale", ["bench_scale.py", "--min-size", "12288", "--max-size", "786432",
               "--workdir", "bench-out/scale"]),
    ("kernels", ["bench_kernels.py", "--sizes", "96x128,192x256"]),
    ("distributed", ["bench_distributed.py", "--size", "192x256",
                     "--workdir", "bench-out/distributed"]),
    # issue #34 (5): the cluster model checked on threads, local:1 and local:2 (192x256,
    # ~3 min), its full-HD and 4K predictions beside them
    ("cluster-model", ["bench_scale.py", "--cluster-model", "--workdir",
                       "bench-out/cluster-model"]),
    ("inverse-dense", ["bench_inverse.py", "--size", "384x512", "--density", "dense",
                       "--settings", "power:1e-5,power:3e-6:1e-4,power:3e-6:1e-4:1e-5,"
                       "power:3e-6:1e-4:3e-5", "--sample", "2048",
                       "--memory-limit", "2GiB", "--workdir", "bench-out/inverse"]),
    ("defaults", ["bench_defaults.py", "--workdir", "bench-out/defaults"]),  # issue #30
    ("video", ["bench_video.py", "--out", "bench-out/video"]),
    # the colour Cornell box at 384x512: grey vs general vs global-mixing, seen ΔE, video;
    # time against error of both paths at 96x128
    ("colour", ["bench_colour.py", "--workdir", "bench-out/colour"]),
    # issue #29 on the simulated nonlinear rig: T from one exposure against brackets, the
    # seen error with and without the calibrated responses (12x16 and 24x32, ~3 min)
    ("calibration", ["bench_calibration.py", "--workdir", "bench-out/calibration"]),
    ("compensate", ["bench_compensate.py", "--skip", "throughput"]),
    ("out-of-core", ["bench_out_of_core.py", "--n", "393216", "--memory-limit", "1536MiB"]),
    ("store", ["bench_store.py"]),
    # the store layout's files and bytes per term (the before/after of issue #30 is run
    # on its own with --baseline, an older checkout)
    ("layout", ["bench_layout.py", "--workdir", "bench-out/layout"]),
    ("startup", ["bench_startup.py"]),  # whole bigT processes: every help, a warm 4x4
    # issue #31: local directory against S3 (moto) on loopback, threads and 2 workers
    ("objects", ["bench_objects.py", "--workdir", "bench-out/objects"]),
    ("acquire", ["bench_acquire.py", "--grid", "48x64", "--camera", "120x160"]),
    ("stability", ["bench_stability.py", "--quick"]),
    ("reliability", ["bench_reliability.py", "--quick"]),
]
#: The quick plan, under 5 minutes on 2 cores: the benchmarks the summary quotes, at
#: small sizes (measured, CPU seconds: paper 15, tradeoff 94, target 6, alternatives
#: 119, scale 26, kernels 23, distributed 37, out-of-core 6, store 5). Video (49 CPU-s at
#: 64 frames of 96x128), compensate, inverse, scenes, acquire, stability and reliability
#: are left to the full plan: with them the quick plan would take twice as long.
QUICK = [
    ("paper", ["bench_paper.py", "--quick"]),
    ("tradeoff", ["bench_tradeoff.py", "--quick", "--scenes", "corner-96x128-sparse",
                  "--workdir", "bench-out/tradeoff-quick"]),
    ("target", ["bench_target.py", "--quick", "--rho", "0.2", "--targets", "0.00392"]),
    ("alternatives", ["bench_alternatives.py", "--quick", "--sizes", "32x48,48x64",
                      "--colour-sizes", "24x32", "--workdir", "bench-out/alternatives-quick"]),
    ("scale", ["bench_scale.py", "--max-size", "49152", "--no-compensate",
               "--workdir", "bench-out/scale-quick"]),
    ("kernels", ["bench_kernels.py", "--sizes", "48x64", "--repeat", "1"]),
    ("distributed", ["bench_distributed.py", "--size", "48x64",
                     "--workdir", "bench-out/distributed-quick"]),
    ("out-of-core", ["bench_out_of_core.py", "--n", "32768", "--memory-limit", "2GiB"]),
    ("store", ["bench_store.py", "--n", "20000", "--nnz-per-row", "20"]),
    ("colour", ["bench_colour.py", "--quick", "--workdir", "bench-out/colour-quick"]),
]


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


def run_one(name: str, cmd: list[str], out: Path) -> report.Run:
    """Run one benchmark in a child process, its output shown and kept in ``<name>.txt``."""
    log = f"{name}.txt"
    (out / f"{name}.json").unlink(missing_ok=True)  # a failed run must not show the old record
    argv = [sys.executable, str(HERE / cmd[0]), *cmd[1:]]
    shown = ["python", f"benchmarks/{cmd[0]}", *cmd[1:]]
    print(f"== {name}: {' '.join(shown)}  (-> {out / log})", flush=True)
    env = {**os.environ, "PYTHONWARNINGS": "ignore", OUT_ENV: str(out), NAME_ENV: name}
    t0 = time.perf_counter()
    with open(out / log, "w") as f:
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=env, cwd=ROOT)
        for line in proc.stdout:
            sys.stdout.write(line)
            f.write(line)
        proc.wait()
    seconds = time.perf_counter() - t0
    print(f"== {name}: exit {proc.returncode} after {seconds:.0f} s\n", flush=True)
    return report.Run(name, shown, proc.returncode, seconds, log)


def select(plan: list, only: str | None) -> list:
    if not only:
        return plan
    wanted = set(only.split(","))
    unknown = wanted - {name for name, _ in plan}
    if unknown:
        raise SystemExit(f"run_all: not in this plan: {', '.join(sorted(unknown))}")
    return [c for c in plan if c[0] in wanted]


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
    if args.list:
        for name, cmd in plan:
            print(f"{name:<14} {' '.join(cmd)}")
        return 0
    todo = select(plan, args.only)
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
    runs = [r for r in (earlier.runs if earlier else []) if r.name not in dict(todo)]
    kind = ("quick" if args.quick else "full") + (" (part)" if args.only else "")
    t0 = time.perf_counter()
    try:
        for name, cmd in todo:
            # saved before and after each run: an interrupted one is reported as such
            report.Plan(kind, [n for n, _ in plan], runs + [report.Run(
                name, ["python", f"benchmarks/{cmd[0]}", *cmd[1:]], None,
                0.0, f"{name}.txt")]).save(out)
            runs.append(run_one(name, cmd, out))
            report.Plan(kind, [n for n, _ in plan], runs).save(out)
    finally:  # Ctrl-C too: what did run is reported
        print(f"results: {report.write(out, results)} "
              f"({time.perf_counter() - t0:.0f} s of benchmarks)", flush=True)
    failed = [r.name for r in runs if r.returncode]
    if failed:
        print("failed: " + ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
