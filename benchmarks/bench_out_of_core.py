"""Out-of-core benchmark: an inverse larger on disk than the memory limit it is
computed under (reported, not asserted).

T is a synthetic banded transport matrix, written tile row by tile row (never whole
in memory): every row holds a unit diagonal (the first bounce) and ``--per-row``
interreflection entries at random offsets within ``+-band`` columns, positive, summing
to ``--rho`` (so rho(M) <= rho). The width of X's rows does not depend on n, so n sets
the size of X on disk; the default (n = 393216, prune 1e-6, 3 terms: 470 entries per
row) gives an X of 1.7 GiB on disk, above the default limit of 1.5 GiB.

A child process runs ``bigT.stratified_inverse(..., memory_limit=LIMIT)``; the report
gives per-term times, the residual estimate, X's size on disk and the child's peak
resident memory (VmHWM), next to the limit.

    python benchmarks/bench_out_of_core.py --n 393216 --memory-limit 1536MiB --terms 3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def banded_T(path, n, per_row, band, rho, tile_size, seed=0):
    """Write the synthetic T (n x n, float32) to ``path`` tile row by tile row."""
    import scipy.sparse as sp

    from bigT.storage import BlockCSRWriter

    rng = np.random.default_rng(seed)
    w = BlockCSRWriter(path, (n, n), tile_size=tile_size, dtype="float32")
    for i, a in enumerate(range(0, n, tile_size)):
        b = min(a + tile_size, n)
        r = b - a
        rows = np.repeat(np.arange(a, b), per_row)
        cols = rows + rng.integers(-band, band + 1, size=rows.size)
        cols = np.where((cols < 0) | (cols >= n) | (cols == rows), -1, cols)
        vals = rng.random(rows.size)
        vals[cols < 0] = 0
        sums = vals.reshape(r, per_row).sum(axis=1, keepdims=True)
        vals = (rho * vals.reshape(r, per_row) / np.maximum(sums, 1e-30)).ravel()
        keep = cols >= 0
        block = sp.csr_array((np.r_[vals[keep], np.ones(r)],
                              (np.r_[rows[keep], np.arange(a, b)] - a,
                               np.r_[cols[keep], np.arange(a, b)])), shape=(r, n),
                             dtype=np.float32)
        block.sum_duplicates()
        w.write_tile_row(i, block)
    return w.finalize()


def disk_bytes(path) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def child(args):
    import bigT
    from bench_inverse import peak_rss

    import warnings

    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", bigT.MemoryLimitWarning)
        rep = bigT.stratified_inverse(args.T, args.out, terms=args.terms, prune=args.prune,
                                      memory_limit=args.memory_limit, progress=False)
    wall = time.perf_counter() - t0
    print(json.dumps({"wall_s": wall, "peak_rss_bytes": peak_rss(), "report": rep.to_dict(),
                      "warnings": [str(w.message) for w in caught]}, default=str))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=393216)
    p.add_argument("--per-row", type=int, default=8)
    p.add_argument("--band", type=int, default=512)
    p.add_argument("--rho", type=float, default=0.4)
    p.add_argument("--tile-size", type=int, default=8192)
    p.add_argument("--terms", type=int, default=3)
    p.add_argument("--prune", type=float, default=1e-6)
    p.add_argument("--memory-limit", default="1536MiB")
    p.add_argument("--workdir", default=None)
    p.add_argument("--json", default=None)
    p.add_argument("--_child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--T", default=None, help=argparse.SUPPRESS)
    p.add_argument("--out", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args._child:
        return child(args)
    if args.workdir is None:
        # T and a 1.7 GiB X: removed afterwards unless a --workdir keeps them
        with tempfile.TemporaryDirectory(prefix="bench_ooc_") as tmp:
            return run(args, tmp)
    return run(args, args.workdir)


def run(args, workdir):
    from bigT.sizes import parse_size

    tpath = os.path.join(workdir, f"T-banded-{args.n}-{args.per_row}-{args.band}.zarr")
    if not os.path.exists(tpath):
        t0 = time.perf_counter()
        T = banded_T(tpath, args.n, args.per_row, args.band, args.rho, args.tile_size)
        print(f"wrote T: n = {args.n}, {T.nnz} nonzeros, {disk_bytes(tpath) / 2**20:.0f} MiB "
              f"on disk, in {time.perf_counter() - t0:.1f} s")
    out = os.path.join(workdir, "X.zarr")
    if os.path.exists(out):
        import shutil

        shutil.rmtree(out)
    cmd = [sys.executable, os.path.abspath(__file__), "--_child", "--T", tpath, "--out", out,
           "--terms", str(args.terms), "--prune", str(args.prune),
           "--memory-limit", args.memory_limit]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        print(proc.stderr, file=sys.stderr)
        raise SystemExit("child failed")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    rep = r["report"]
    limit = parse_size(args.memory_limit, "--memory-limit")
    x_disk = disk_bytes(out)
    r.update(limit_bytes=limit, X_disk_bytes=x_disk, n=args.n)
    print(f"{'term':>4} {'time s':>8} {'nnz(P)':>13} {'nnz(X)':>13} {'residual':>10}")
    for h in rep["history"]:
        print(f"{h['term']:>4} {h['seconds']:>8.2f} {h['nnz_P']:>13d} {h['nnz_X']:>13d} "
              f"{h['residual']:>10.3e}")
    print(f"{rep['memory']}")
    for w in r["warnings"]:
        print("warning:", w)
    print(f"total {r['wall_s']:.1f} s; X on disk {x_disk / 2**20:.0f} MiB "
          f"({x_disk / limit:.2f}x the limit); peak RSS {r['peak_rss_bytes'] / 2**20:.0f} MiB "
          f"({r['peak_rss_bytes'] / limit:.2f}x the limit)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(r, f, indent=1, default=str)


if __name__ == "__main__":
    main()
