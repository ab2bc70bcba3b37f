"""Benchmark of the stratified inverse on a synthetic wall-corner scene (reported, not
asserted).

For each method (default: power and horner side by side) a fresh child process runs
``bigT.stratified_inverse`` on the scene's T and reports: time per term, nnz of P and
X, the residual estimate, the error against the known true inverse F^-1 (I - A)
(relative Frobenius, computed tile row by tile row) and the child's peak RSS.

    python benchmarks/bench_inverse.py --size 192x256 --terms 4 --prune 1e-5 \
        --method power,horner

The scene comes from ``bigT.scenes.corner(size=..., path=..., density=...)`` (a
``--workdir`` that already holds it is reused); the error is
``Scene.inverse_error``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time


# run from a checkout: the repository's bigT, whatever the venv's install points at
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _size(text):
    h, w = text.lower().split("x")
    return int(h), int(w)


def make_scene(size, path, density):
    """Build the corner scene at ``path``; returns (scene, seconds)."""
    import bigT.scenes as scenes

    t0 = time.perf_counter()
    sc = scenes.corner(size=size, path=path, density=density, preview=False, progress=False)
    return sc, time.perf_counter() - t0


def peak_rss() -> int:
    """Peak resident set of this process in bytes (VmHWM; see
    :func:`bigT.schedule.memory.peak_resident_bytes`)."""
    from bigT.schedule.memory import peak_resident_bytes

    return peak_resident_bytes()


def child(args):
    import bigT

    scene = bigT.scenes.load(args.scene)
    T = scene.T
    out = os.path.join(args.workdir, f"X-{args.method}.zarr")
    if os.path.exists(out):
        import shutil

        shutil.rmtree(out)
    t0 = time.perf_counter()
    rep = bigT.stratified_inverse(T, out, terms=args.terms, prune=args.prune,
                                  method=args.method, memory_limit=args.memory_limit,
                                  progress=False)
    wall = time.perf_counter() - t0
    peak = peak_rss()
    X = bigT.open(out)
    err = scene.inverse_error(X)
    res = {"method": args.method, "wall_s": wall, "peak_rss_bytes": peak,
           "error_vs_true_inverse": err, "nnz_X": int(X.nnz), "n": int(X.shape[0]),
           "report": rep.to_dict()}
    print(json.dumps(res, default=str))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=_size, default=(96, 128), help="HxW (default 96x128)")
    p.add_argument("--density", default="sparse",
                   help="scene density preset (exact, sparse, dense) or a form-factor cut")
    p.add_argument("--terms", type=int, default=4)
    p.add_argument("--prune", type=float, default=1e-5)
    p.add_argument("--method", default="power,horner",
                   help="comma-separated: power, horner, newton-schulz")
    p.add_argument("--memory-limit", default=None)
    p.add_argument("--workdir", default=None)
    p.add_argument("--json", default=None)
    p.add_argument("--_child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--scene", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args._child:
        return child(args)
    import bigT

    workdir = args.workdir or tempfile.mkdtemp(prefix="bench_inverse_")
    try:
        density = float(args.density)
    except ValueError:
        density = args.density
    scene_path = os.path.join(workdir, f"corner-{args.size[0]}x{args.size[1]}-{args.density}.zarr")
    if not os.path.exists(scene_path):
        sc, t_scene = make_scene(args.size, scene_path, density)
        print(f"built in {t_scene:.1f} s: " + sc.describe())
    else:
        print("reused: " + bigT.scenes.load(scene_path).describe())
    results = []
    for method in args.method.split(","):
        cmd = [sys.executable, os.path.abspath(__file__), "--_child", "--scene", scene_path,
               "--workdir", workdir, "--method", method, "--terms", str(args.terms),
               "--prune", str(args.prune)]
        if args.memory_limit:
            cmd += ["--memory-limit", args.memory_limit]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode:
            print(proc.stderr, file=sys.stderr)
            raise SystemExit(f"{method}: child failed")
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        results.append(r)
        rep = r["report"]
        print(f"\n== {method}: {r['wall_s']:.1f} s, peak RSS {r['peak_rss_bytes'] / 2**30:.2f} GiB, "
              f"nnz(X)/row {r['nnz_X'] / r['n']:.0f}, relative error vs F^-1(I-A) "
              f"{r['error_vs_true_inverse']:.3e}, rho(M) {rep['spectral_radius']:.3f}")
        print(f"{'term':>4} {'time s':>8} {'nnz(P)':>12} {'nnz(X)':>12} {'tiles':>7} "
              f"{'skipped':>7} {'residual':>10}")
        for h in rep["history"]:
            print(f"{h['term']:>4} {h['seconds']:>8.2f} {h['nnz_P']:>12d} {h['nnz_X']:>12d} "
                  f"{h['tiles_computed']:>7d} {h['tiles_skipped']:>7d} {h['residual']:>10.3e}")
    if len(results) > 1:
        base = results[0]
        for r in results[1:]:
            print(f"{base['method']} is {r['wall_s'] / base['wall_s']:.2f}x faster than "
                  f"{r['method']} (error {base['error_vs_true_inverse']:.2e} vs "
                  f"{r['error_vs_true_inverse']:.2e})")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1, default=str)


if __name__ == "__main__":
    main()
