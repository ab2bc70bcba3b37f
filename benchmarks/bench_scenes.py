"""Scene generation: time, nonzeros, peak memory and spectral radius (reported, not
asserted).

Each scene is built by ``bigT.scenes.make`` in a fresh child process, so the peak
resident memory (VmHWM) is that scene's alone.

    python benchmarks/bench_scenes.py                       # every scene at its default size
    python benchmarks/bench_scenes.py --large               # + the 384x512 sparse and dense corner
    python benchmarks/bench_scenes.py --only corner:384x512:dense
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

DEFAULT_CASES = ["dihedral4", "corner", "convex", "flat", "cornell", "hemispheres"]
LARGE_CASES = ["corner:384x512:sparse", "corner:384x512:dense"]


def child(spec: str, workdir: str) -> None:
    from bench_inverse import peak_rss

    import bigT.scenes as scenes

    name, size, density = (spec.split(":") + [None, None])[:3]
    size = None if not size else tuple(int(v) for v in size.split("x"))
    kw = {} if name == "dihedral4" else {"density": density, "progress": False}
    sc = scenes.make(name, size, os.path.join(workdir, f"{name}.zarr"), overwrite=True, **kw)
    s = dict(sc.summary)
    s["peak_rss_bytes"] = peak_rss()
    s["disk_bytes"] = sum(f.stat().st_size for f in sc.path.rglob("*") if f.is_file())
    print(json.dumps(s))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--large", action="store_true", help="also the 384x512 sparse/dense corner")
    p.add_argument("--only", default=None, help="comma-separated NAME[:HxW[:density]]")
    p.add_argument("--workdir", default=None)
    p.add_argument("--json", default=None)
    p.add_argument("--_child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    workdir = args.workdir or tempfile.mkdtemp(prefix="bench_scenes_")
    if args._child:
        return child(args._child, workdir)
    cases = args.only.split(",") if args.only else DEFAULT_CASES + (LARGE_CASES if args.large else [])
    print(f"{'scene':<26} {'n':>7} {'nnz(T)':>11} {'/row':>6} {'nnz(A)':>10} {'rho(M)':>7} "
          f"{'rho(A)':>7} {'bounce1':>8} {'time s':>7} {'peak MiB':>9} {'disk MiB':>9}")
    results = []
    for spec in cases:
        sub = os.path.join(workdir, spec.replace(":", "_"))
        os.makedirs(sub, exist_ok=True)
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--_child", spec,
                               "--workdir", sub], capture_output=True, text=True)
        if proc.returncode:
            print(proc.stderr[-2000:], file=sys.stderr)
            raise SystemExit(f"{spec}: child failed")
        s = json.loads(proc.stdout.strip().splitlines()[-1])
        results.append(s)
        shares = s["bounce_shares"]
        H, W = s["image_shape"]
        label = f"{s['name']} {H}x{W}" + (f" {s['density']}" if s.get("density") else "")
        print(f"{label:<26} {s['n']:>7} {s['nnz_T']:>11,} {s['nnz_T'] / s['n']:>6.1f} "
              f"{s['nnz_A']:>10,} {s['spectral_radius']:>7.4f} {s['spectral_radius_A']:>7.4f} "
              f"{100 * (shares[1] if len(shares) > 1 else 0):>7.2f}% {s['seconds']:>7.1f} "
              f"{s['peak_rss_bytes'] / 2**20:>9.0f} {s['disk_bytes'] / 2**20:>9.1f}", flush=True)
        if not args.workdir:
            shutil.rmtree(sub, ignore_errors=True)
    print("rho(M): spectral radius of M = I - T diag(T)^-1 (what bigT invert uses); bounce1: "
          "||A F 1|| / ||T 1||")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
