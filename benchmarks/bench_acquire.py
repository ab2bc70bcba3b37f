"""Acquisition: how well and how fast T comes back from (simulated) captures.

For each method (brute force, stripes) and camera noise, a synthetic corner scene's
captures are simulated at a camera resolution unlike the projector's, T is built by
``bigT acquire build`` in a fresh child process (so its peak resident memory is its
own), and compared with what a perfect build gives (exposure x mean camera gain of each
group x the scene's T, :meth:`bigT.acquisition.CameraModel.expected_scale`):

* relative error (Frobenius) and the largest entry error;
* the stripes' over-estimate against brute force on the same captures' scene: total
  light (sum of T) and the off-diagonal part, as Ding et al.'s method is known to
  over-estimate (paper §2.2);
* T 1 against the captured white image (paper Fig. 8).

    python benchmarks/bench_acquire.py                 # 24x32 grid, camera 60x80
    python benchmarks/bench_acquire.py --grid 48x64 --camera 120x160
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def child(patterns: str, captures: str, out: str, memory: int | None) -> None:
    from bench_inverse import peak_rss

    from bigT.acquisition import build_transport
    from bigT.acquisition.validate import check_white

    t0 = time.perf_counter()
    report = build_transport(patterns, captures, out, memory_bytes=memory, overwrite=True,
                             progress=False)
    seconds = time.perf_counter() - t0
    print(json.dumps({"seconds": seconds, "passes": report.passes, "nnz": report.nnz,
                      "seen": report.seen, "n": report.n, "floor": report.settings.floor,
                      "white_error": check_white(out).relative_error,
                      "peak_rss_bytes": peak_rss()}))


def _size(text: str) -> tuple[int, int]:
    h, w = text.lower().split("x")
    return int(h), int(w)


def measure(scene, workdir: Path, method: str, noise: float, camera, memory) -> dict:
    from bigT.acquisition import make_manifest, simulate_captures, write_patterns
    from bigT.storage import open as open_store

    grid = scene.pixel_order.image_shape
    patterns = workdir / f"patterns-{method}"
    if not patterns.exists():
        write_patterns(patterns, make_manifest(method, (2 * grid[0], 2 * grid[1]), 2,
                                               graycode=True), progress=False)
    captures = workdir / f"captures-{method}-{noise}"
    t0 = time.perf_counter()
    model = simulate_captures(scene.path, patterns, captures, camera=camera, noise=noise,
                              black=0.02, seed=1, progress=False)
    t_sim = time.perf_counter() - t0
    out = workdir / f"T-{method}-{noise}.zarr"
    cmd = [sys.executable, __file__, "--_child", str(patterns), str(captures), str(out)]
    if memory:
        cmd.append(str(memory))
    res = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)
    scale = model.expected_scale(scene.pixel_order)
    E = scene.T.to_scipy(output_order="matrix").multiply(scale[:, None]).tocsr()
    E = E[:, scale > 0] if False else E
    E = E.toarray()
    E[:, scale == 0] = 0
    T = open_store(out).to_scipy(output_order="matrix").toarray()
    off = ~np.eye(len(T), dtype=bool)
    res.update(method=method, noise=noise, simulate_seconds=t_sim,
               captures=len(list(captures.glob("*.png"))),
               rel_error=float(np.linalg.norm(T - E) / np.linalg.norm(E)),
               max_error=float(np.abs(T - E).max()),
               light_ratio=float(T.sum() / E.sum()),
               offdiag_ratio=float(T[off].sum() / E[off].sum()),
               diag_error=float(np.abs(np.diag(T) - np.diag(E)).max() / np.diag(E).max()))
    return res


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grid", type=_size, default=(24, 32),
                   help="the projector's super-pixel grid = the scene's image (default 24x32)")
    p.add_argument("--camera", type=_size, default=(60, 80))
    p.add_argument("--noise", default="0,0.002", help="comma-separated noise levels")
    p.add_argument("--methods", default="brute-force,stripes")
    p.add_argument("--memory-limit", type=int, default=None,
                   help="bytes for one pass's entries (default bigT's)")
    p.add_argument("--workdir", default=None)
    p.add_argument("--json", default=None)
    p.add_argument("--_child", nargs="+", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args._child:
        pat, cap, out, *mem = args._child
        return child(pat, cap, out, int(mem[0]) if mem else None)

    import bigT.scenes as scenes

    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench_acquire_"))
    t0 = time.perf_counter()
    scene = scenes.make("corner", args.grid, workdir / "scene.zarr", overwrite=True,
                        preview=False, progress=False)
    print(f"scene: corner {args.grid[0]}x{args.grid[1]} (n = {scene.T.shape[0]}, "
          f"{scene.T.nnz / scene.T.shape[0]:.0f} entries per row), built in "
          f"{time.perf_counter() - t0:.1f} s; camera {args.camera[0]}x{args.camera[1]}")
    print(f"{'method':<12} {'noise':>6} {'captures':>8} {'sim s':>6} {'build s':>7} "
          f"{'passes':>6} {'peak MiB':>8} {'nnz/row':>7} {'rel err':>8} {'max err':>8} "
          f"{'diag err':>8} {'light x':>7} {'offdiag x':>9} {'T1 vs white':>11}")
    results = []
    for method in args.methods.split(","):
        for noise in (float(v) for v in args.noise.split(",")):
            r = measure(scene, workdir, method, noise, args.camera, args.memory_limit)
            results.append(r)
            print(f"{method:<12} {noise:>6g} {r['captures']:>8d} {r['simulate_seconds']:>6.1f} "
                  f"{r['seconds']:>7.2f} {r['passes']:>6d} {r['peak_rss_bytes'] / 2**20:>8.0f} "
                  f"{r['nnz'] / r['n']:>7.1f} {r['rel_error']:>8.2e} {r['max_error']:>8.1e} "
                  f"{r['diag_error']:>8.1e} {r['light_ratio']:>7.3f} {r['offdiag_ratio']:>9.3f} "
                  f"{r['white_error']:>11.3g}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
