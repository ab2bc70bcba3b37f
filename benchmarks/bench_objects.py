"""Object storage against a local directory: a 4-term inverse of the dense corner with T
and X on this machine's disk, then in a bucket of an S3-compatible server on loopback
(moto's server mode, ``bigT.testing.S3Server``, 127.0.0.1 only), on local threads and on
two dask worker processes (issue #31, point 5).

Each configuration runs in a child process of its own (``AWS_ENDPOINT_URL`` points it,
and the workers it starts, at the server), interleaved with the others, best of
``--repeats``; the child reports its seconds, the spectral radius's and each term's,
and the requests and bytes it exchanged with the bucket (``bigT.storage.objects.
TRAFFIC``; with worker processes, the client's share only: the workers count their
own). The stores' bytes at rest are listed beside them.

    python benchmarks/bench_objects.py                       # 192x256, 2 repeats
    python benchmarks/bench_objects.py --size 96x128 --repeats 1
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _results import Results, run_name

HERE = Path(__file__).resolve().parent

#: The child: one inverse, one JSON line.
CHILD = r"""
import json, resource, sys, time
import bigT
from bigT.storage import disk_bytes
from bigT.storage.objects import TRAFFIC

T, out, scheduler, in_memory, terms, prune, feed, operator = sys.argv[1:9]
t0 = time.perf_counter()
rep = bigT.stratified_inverse(T, out, terms=int(terms), prune=float(prune),
                              prune_feed=float(feed), prune_operator=float(operator),
                              overwrite=True, progress=False,
                              scheduler=None if scheduler == "threads" else scheduler,
                              in_memory={"auto": None, "no": False}[in_memory])
seconds = time.perf_counter() - t0
requests, read, written = TRAFFIC.snapshot()
X = bigT.open(out)
print(json.dumps({"seconds": seconds, "spectral": rep.seconds_spectral_radius,
                  "terms": [h.seconds for h in rep.history], "engine": rep.engine_path,
                  "requests": requests, "read": read, "written": written,
                  "X_nnz": int(X.nnz), "X_bytes": disk_bytes(X.path), "residual": rep.residual,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def build_scene(size: str, workdir: Path) -> Path:
    path = workdir / f"corner-{size}-dense.zarr"
    if not (path / "zarr.json").exists():
        subprocess.run([sys.executable, "-m", "bigT.cli", "scene", "corner", "--size", size,
                        "--density", "dense", "-o", str(path), "-q"], check=True)
    return path


def run_child(T: str, out: str, scheduler: str, in_memory: str, args, env: dict) -> dict:
    proc = subprocess.run([sys.executable, "-c", CHILD, T, out, scheduler, in_memory,
                           str(args.terms), str(args.prune), str(args.prune_feed),
                           str(args.prune_operator)], capture_output=True, text=True,
                          env={**os.environ, **env}, cwd=args.workdir)
    if proc.returncode:
        raise SystemExit(f"child failed ({T} -> {out}, {scheduler}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    from bigT.storage.upgrade import upgrade_store
    from bigT.testing import S3Server

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="192x256")
    p.add_argument("--terms", type=int, default=4)
    p.add_argument("--prune", type=float, default=3e-6)
    p.add_argument("--prune-feed", type=float, default=1e-4)
    p.add_argument("--prune-operator", type=float, default=1e-5)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--workdir", type=Path, default=Path("bench-out/objects"))
    args = p.parse_args(argv)
    args.workdir = args.workdir.resolve()
    args.workdir.mkdir(parents=True, exist_ok=True)
    scene = build_scene(args.size, args.workdir)
    configs = [("threads", "no"), ("threads", "auto"), ("local:2", "no")]
    best: dict[tuple, dict] = {}
    with S3Server(args.workdir) as s3:
        os.environ.update(s3.env)  # this process copies T into the bucket
        upgrade_store(scene, s3.url("T.zarr"))
        places = {"local directory": (str(scene), str(args.workdir / "X.zarr")),
                  "S3 on loopback": (s3.url("T.zarr"), s3.url("X.zarr"))}
        for _ in range(args.repeats):
            for scheduler, in_memory in configs:
                for place, (T, out) in places.items():  # interleaved: drift hits both
                    run = run_child(T, out, scheduler, in_memory, args, s3.env)
                    key = (place, scheduler, in_memory)
                    print(f"{place}, {scheduler}, in memory {in_memory}: "
                          f"{run['seconds']:.2f} s ({run['engine']}), {run['requests']} "
                          f"requests", flush=True)
                    if key not in best or run["seconds"] < best[key]["seconds"]:
                        best[key] = run
    res = Results(run_name("objects"), f"Object storage: a {args.terms}-term inverse of the "
                  f"dense {args.size} corner, local directory against S3 (moto) on loopback",
                  " ".join(["python benchmarks/bench_objects.py"] + (argv or sys.argv[1:])))
    rows = []
    for (place, scheduler, in_memory), run in best.items():
        local = best[("local directory", scheduler, in_memory)]
        rows.append([place, scheduler, run["engine"], round(run["seconds"], 2),
                     round(run["seconds"] / local["seconds"], 2),
                     round(run["spectral"], 2), " / ".join(f"{t:.2f}" for t in run["terms"]),
                     run["requests"], round(run["read"] / 2**20, 1),
                     round(run["written"] / 2**20, 1), round(run["X_bytes"] / 2**20, 1),
                     round(run["peak_rss_mb"])])
    res.table("runs", "Best of the repeats: whole call, its ratio to the local directory "
              "with the same scheduler, the spectral radius and the terms; the client "
              "process's requests and MiB read and written (worker processes count their "
              "own); X's MiB at rest",
              ["storage", "scheduler", "engine path", "seconds", "/ local", "spectral s",
               "term seconds", "requests", "MiB read", "MiB written", "X MiB", "peak RSS MB"],
              rows)
    for (place, scheduler, in_memory), run in best.items():
        res.value(f"objects:seconds:{place}:{scheduler}:{in_memory}", run["seconds"],
                  f"whole run, {place}, {scheduler}")
    res.save()
    print(json.dumps({" | ".join(k): v for k, v in best.items()}, indent=1))


if __name__ == "__main__":
    started = time.time()
    main()
    print(f"done in {time.time() - started:.0f} s")
