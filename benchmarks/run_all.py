"""Run every benchmark in turn and keep each one's output in ``bench-out/`` (``make bench``).

    python benchmarks/run_all.py            # the figures quoted in README.md (about 20 min)
    python benchmarks/run_all.py --quick    # small sizes, a few minutes

Nothing is asserted: each benchmark prints its own table; this script only runs them
one after the other (never two at once: they would share the 2 cores and skew each
other's timings) and saves what they print.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

FULL = [
    ("store", ["bench_store.py"]),
    ("kernels", ["bench_kernels.py", "--sizes", "96x128,192x256"]),
    ("scenes", ["bench_scenes.py", "--large"]),
    ("inverse-sparse", ["bench_inverse.py", "--size", "384x512", "--density", "sparse",
                        "--method", "power,horner"]),
    ("inverse-dense", ["bench_inverse.py", "--size", "384x512", "--density", "dense",
                       "--method", "power", "--memory-limit", "2GiB"]),
    ("out-of-core", ["bench_out_of_core.py", "--n", "393216", "--memory-limit", "1536MiB"]),
    # the full-HD point (--max-size 2073600, ~40 min) is run on its own
    ("scale", ["bench_scale.py", "--min-size", "49152", "--max-size", "786432",
               "--workdir", "bench-out/scale"]),
    ("compensate", ["bench_compensate.py"]),
    ("acquire", ["bench_acquire.py", "--grid", "48x64", "--camera", "120x160"]),
    ("stability", ["bench_stability.py"]),
    ("reliability", ["bench_reliability.py"]),
]
QUICK = [
    ("store", ["bench_store.py", "--n", "20000", "--nnz-per-row", "20"]),
    ("kernels", ["bench_kernels.py", "--sizes", "48x64", "--repeat", "1"]),
    ("scenes", ["bench_scenes.py"]),
    ("inverse", ["bench_inverse.py", "--size", "96x128", "--method", "power,horner"]),
    ("out-of-core", ["bench_out_of_core.py", "--n", "32768", "--memory-limit", "2GiB"]),
    ("scale", ["bench_scale.py", "--max-size", "49152", "--workdir", "bench-out/scale-quick"]),
    ("compensate", ["bench_compensate.py", "--size", "96x128", "--scene-size", "32x48",
                    "--frames", "64", "--no-splu"]),
    ("acquire", ["bench_acquire.py"]),
    ("stability", ["bench_stability.py", "--quick"]),
    ("reliability", ["bench_reliability.py", "--quick"]),
]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes")
    p.add_argument("--only", default=None, help="comma-separated benchmark names")
    p.add_argument("--out", default="bench-out")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plan = QUICK if args.quick else FULL
    if args.only:
        wanted = set(args.only.split(","))
        plan = [c for c in plan if c[0] in wanted]
    failed = []
    for name, cmd in plan:
        log = out / f"{name}.txt"
        print(f"== {name}: {' '.join(cmd)}  (-> {log})", flush=True)
        t0 = time.perf_counter()
        with open(log, "w") as f:
            proc = subprocess.Popen([sys.executable, str(HERE / cmd[0]), *cmd[1:]],
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                    env={**os.environ, "PYTHONWARNINGS": "ignore"})
            for line in proc.stdout:
                sys.stdout.write(line)
                f.write(line)
            proc.wait()
        print(f"== {name}: exit {proc.returncode} after {time.perf_counter() - t0:.0f} s\n",
              flush=True)
        if proc.returncode:
            failed.append(name)
    if failed:
        print("failed: " + ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
