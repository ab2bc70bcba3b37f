"""The same inversion on three schedulers: local threads, ``--scheduler local:2`` and a
scheduler with two ``dask worker`` processes started here (127.0.0.1 only, stopped by
PID). Each run is a fresh ``bigT invert`` process; its JSON report gives the time per
term, each process's peak resident memory and the scheduling overhead per task.

    python benchmarks/bench_distributed.py [--size 192x256] [--density dense]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _results import Results, run_name  # noqa: E402


def scene(workdir: Path, size, density):
    import bigT.scenes as scenes

    path = workdir / f"corner-{size[0]}x{size[1]}-{density}.zarr"
    if path.exists():
        return scenes.load(path)
    return scenes.corner(size=size, path=path, density=density, preview=False,
                         progress=False)


def invert(T: Path, out: Path, scheduler: str | None, args) -> dict:
    """One ``bigT invert`` in a fresh process; its report as a dict."""
    report = out.with_suffix(".json")
    cmd = [str(Path(sys.executable).with_name("bigT")), "invert", str(T), "-o", str(out),
           "--terms", str(args.terms), "--prune", str(args.prune), "--json", str(report),
           "--no-progress"]
    if scheduler:
        cmd += ["--scheduler", scheduler]
    if args.memory_limit:
        cmd += ["--memory-limit", args.memory_limit]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    rep = json.loads(report.read_text())
    rep["wall"] = time.perf_counter() - t0
    return rep


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="192x256")
    p.add_argument("--density", default="dense")
    p.add_argument("--terms", type=int, default=4)
    p.add_argument("--prune", type=float, default=1e-5)
    p.add_argument("--memory-limit", default=None,
                   help="bigT's --memory-limit (each dask worker gets --worker-memory)")
    p.add_argument("--worker-memory", default="4GiB")
    p.add_argument("--workdir", default=str(ROOT / "bench-out" / "distributed"))
    args = p.parse_args(argv)
    size = tuple(int(s) for s in args.size.split("x"))
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)

    import shutil

    import bigT
    from bigT.testing import ProcessCluster

    sc = scene(work, size, args.density)
    print(f"corner {size[0]}x{size[1]} {args.density}: n = {sc.T.shape[0]:,}, "
          f"nnz(T) = {sc.T.nnz:,} ({sc.T.nnz / sc.T.shape[0]:.0f}/row)")
    runs = {}
    for name in ("threads", "local:2", "2 dask workers"):
        out = work / f"X-{name.replace(' ', '-').replace(':', '')}.zarr"
        shutil.rmtree(out, ignore_errors=True)
        if name == "2 dask workers":
            logs = work / "cluster"
            shutil.rmtree(logs, ignore_errors=True)
            logs.mkdir()
            with ProcessCluster(logs, 2, args.worker_memory) as cluster:
                runs[name] = invert(sc.path, out, cluster.address, args)
        else:
            runs[name] = invert(sc.path, out, None if name == "threads" else name, args)
        runs[name]["X"] = out
    ref = bigT.open(runs["threads"]["X"]).to_scipy()
    head = (f"{'scheduler':<16} {'total s':>8} {'terms s':>34} {'tasks':>6} "
            f"{'ms/task':>8}  peak RSS per process        max |X - X_threads|")
    print(head)
    rows = []
    for name, r in runs.items():
        diff = abs(bigT.open(r["X"]).to_scipy() - ref).max()
        terms = " ".join(f"{h['seconds']:.1f}" for h in r["history"])
        peaks = ", ".join(f"{int(b) / 2**20:.0f} MiB" for _, b in r["peak_memory"])
        rows.append([name, r["seconds"], terms, r["tasks"], r["task_overhead_ms"], peaks,
                     float(diff)])
        print(f"{name:<16} {r['seconds']:>8.1f} {terms:>34} {r['tasks']:>6} "
              f"{r['task_overhead_ms']:>8.1f}  {peaks:<27} {diff:.1e}")
    res = Results(run_name("distributed"), "The same inversion on three schedulers",
                  "python benchmarks/bench_distributed.py " + " ".join(argv or sys.argv[1:]))
    res.table("schedulers", f"{args.terms}-term inverse of the {args.density} corner "
              f"{size[0]}x{size[1]} (n = {sc.T.shape[0]:,}, {sc.T.nnz / sc.T.shape[0]:.0f} "
              "nonzeros a row)",
              ["scheduler", "total s", "terms s", "tasks", "ms/task", "peak RSS per process",
               "max |X - X_threads|"], rows,
              note="each run a fresh `bigT invert` process; ms/task: scheduling and idle "
                   "threads per task")
    res.save()
    summary = {k: {kk: vv for kk, vv in v.items() if kk != "X"} for k, v in runs.items()}
    (work / "results.json").write_text(json.dumps(summary, indent=1, default=str))
    print(f"-> {work / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
