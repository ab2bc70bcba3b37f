"""Benchmark of the stratified inverse on a synthetic wall-corner scene (reported, not
asserted).

For each method (default: power and horner side by side) a fresh child process runs
``bigT.stratified_inverse`` on the scene's T and reports: time per term, nnz of P and
X, the residual estimate, the error against the known true inverse F^-1 (I - A)
(relative Frobenius, computed tile row by tile row) and the child's peak RSS.

    python benchmarks/bench_inverse.py --size 192x256 --terms 4 --prune 1e-5 \
        --method power,horner

The scene comes from ``bigT.scenes.corner(size=..., path=...)``, or (until that lands)
from a stand-in built with the scenes layer's geometry/radiosity pieces (make_scene).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

# run from a checkout: the repository's bigT, whatever the venv's install points at
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _size(text):
    h, w = text.lower().split("x")
    return int(h), int(w)


def make_scene(size, path, density):
    """Build the corner scene at ``path``; returns (T, A, F, description, seconds).

    ``bigT.scenes.corner`` when it exists. Until it lands, a stand-in built from the
    scenes layer's geometry and radiosity pieces (wall_corner, form_factors with
    ``density`` as the form-factor cut, interreflection, transport_rows): T = (sum_k
    A^k) F, truncated at 1e-7, so F^-1 (I - A) is its inverse up to that truncation.
    """
    import bigT
    import bigT.scenes as scenes

    t0 = time.perf_counter()
    if hasattr(scenes, "corner"):
        import inspect

        kw = {}
        if density is not None and "density" in inspect.signature(scenes.corner).parameters:
            kw["density"] = density
        sc = scenes.corner(size=size, path=path, **kw)
        return sc.T, sc.A, np.asarray(sc.F), "bigT.scenes.corner", time.perf_counter() - t0
    import scipy.sparse as sp

    from bigT.scenes.geometry import wall_corner
    from bigT.scenes.radiosity import form_factors, interreflection, transport_rows

    cut = 1e-6 if density is None else density
    P = wall_corner(size)
    A = interreflection(form_factors(P, cut), np.full(P.n, 0.6))
    f = 0.6 * P.first_bounce_gain()
    rows = []
    for r0 in range(0, P.n, 4096):
        Tr, _ = transport_rows(A, f, r0, min(P.n, r0 + 4096), prune=1e-7, stop=1e-7,
                               max_bounces=60)
        rows.append(Tr)
    T = sp.csr_array(sp.vstack(rows, format="csr"))
    os.makedirs(path, exist_ok=True)
    kw = dict(image_shape=size, pixel_order="tile-major", dtype="float32")
    Ts = bigT.from_scipy(T, os.path.join(path, "T.zarr"), **kw)
    As = bigT.from_scipy(A, os.path.join(path, "A.zarr"), **kw)
    F = f[Ts.pixel_order.permutation]
    np.save(os.path.join(path, "F.npy"), F)
    return Ts, As, F, f"stand-in corner (form-factor cut {cut:g})", time.perf_counter() - t0


def load_scene(path):
    import bigT

    if os.path.exists(os.path.join(path, "F.npy")):
        return (bigT.open(os.path.join(path, "T.zarr")), bigT.open(os.path.join(path, "A.zarr")),
                np.load(os.path.join(path, "F.npy")))
    sc = bigT.scenes.load(path)
    return sc.T, sc.A, np.asarray(sc.F)


def true_inverse_error(X, A, F):
    """||X - F^-1 (I - A)||_F / ||F^-1 (I - A)||_F, tile row by tile row."""
    import scipy.sparse as sp

    finv = 1.0 / np.asarray(F, dtype=np.float64)
    num = den = 0.0
    for i in range(X.grid[0]):
        a, b = X.tile_row_range(i)
        Ai = sp.csr_array(A.get_tile_row(i)).astype(np.float64)
        I = sp.csr_array((np.ones(b - a), (np.arange(b - a), np.arange(a, b))), shape=Ai.shape)
        ref = sp.csr_array(sp.diags(finv[a:b]) @ (I - Ai))
        diff = sp.csr_array(X.get_tile_row(i)).astype(np.float64) - ref
        num += float(np.sum(diff.data ** 2))
        den += float(np.sum(ref.data ** 2))
    return (num / den) ** 0.5


def peak_rss() -> int:
    """Peak resident set of this process in bytes: VmHWM of /proc/self/status (the
    high-water mark of this process's own memory). Not ru_maxrss: after fork + exec
    Linux carries the parent's high-water mark into the child's ru_maxrss, so a child
    started by a parent that built a big scene would report the parent's peak."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def child(args):
    import bigT

    T, A, F = load_scene(args.scene)
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
    err = true_inverse_error(X, A, F)
    res = {"method": args.method, "wall_s": wall, "peak_rss_bytes": peak,
           "error_vs_true_inverse": err, "nnz_X": int(X.nnz), "n": int(X.shape[0]),
           "report": rep.to_dict()}
    print(json.dumps(res, default=str))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=_size, default=(96, 128), help="HxW (default 96x128)")
    p.add_argument("--density", type=float, default=None)
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

    workdir = args.workdir or tempfile.mkdtemp(prefix="bench_inverse_")
    scene_path = os.path.join(workdir, f"corner-{args.size[0]}x{args.size[1]}.zarr")
    if not os.path.exists(scene_path):
        T, A, F, what, t_scene = make_scene(args.size, scene_path, args.density)
        print(f"scene {args.size[0]}x{args.size[1]} ({what}): n={T.shape[0]} nnz(T)={T.nnz} "
              f"({T.nnz / T.shape[0]:.0f}/row), nnz(A)={A.nnz}, built in {t_scene:.1f} s")
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
