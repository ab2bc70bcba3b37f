"""Compensation throughput and quality (reported, never asserted).

Part 1, throughput at 384x512 (n = 196608) with X read from disk in batches:
  * explicit X, batch 1 and batch 64 (frames/s; X streamed once per batch),
  * matrix-free T_n^-1 (n passes over T per batch),
  * scipy ``splu`` of T: factor time, then one solve per frame.
  T and X come from ``bigT.scenes.corner`` (``--density``) and
  ``bigT.stratified_inverse``; ``--synthetic`` uses a synthetic local transport with
  the same nnz/row as docs/DESIGN.md's measured 4-term inverse instead, labelled as such.

Part 2, quality on a small corner scene: fluctuation (max - min)/mean of the camera
image for a constant target, uncompensated and compensated with the stratified inverse
at 1..4 terms (matrix-free, i.e. eq. 13 unpruned; and ``stratified_inverse``) and with
the exact inverse. Writes a scan-line plot like the paper's Fig. 10.

Run:  nice -n 10 .venv/bin/python benchmarks/bench_compensate.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bigT  # noqa: E402
from bigT.compensation import compensate, fluctuation, relative_error, relight, scan_line  # noqa: E402
from bigT.storage.pixel_order import PixelOrder  # noqa: E402

from _results import Results, run_name  # noqa: E402


def _size(text):
    h, w = text.lower().split("x")
    return int(h), int(w)


# --- matrices ---------------------------------------------------------------------------

def _reuse(path, meta, shape):
    """The store at ``path`` when an earlier run left a complete one with ``meta``."""
    try:
        st = bigT.open(path)
    except Exception:
        return None
    same = tuple(st.shape) == tuple(shape) and all(st.metadata.get(k) == v for k, v in meta.items())
    return st if same else None


def synthetic_local(path, size, nnz_per_row, *, diag=0.8, spread=0.3, radius=None, seed=0,
                    tile_size=8192):
    """A transport-like matrix written tile row by tile row (bounded memory).

    Row i holds its diagonal ``diag`` and ``nnz_per_row - 1`` entries at random pixels
    within ``radius`` (image distance) of pixel i, summing to ``spread * diag``: the
    sparsity of a local interreflection kernel, tile-major pixel order.
    """
    from bigT.storage import BlockCSRWriter

    H, W = size
    order = PixelOrder(size, "tile-major")
    n = order.n
    # a window ~9x the row's entries keeps duplicate draws (merged) rare
    radius = radius or int(np.ceil(1.5 * np.sqrt(nnz_per_row)))
    rng = np.random.default_rng(seed)
    perm, inv = order.permutation, order.inverse_permutation
    meta = {"synthetic": True, "nnz_per_row": nnz_per_row, "seed": seed}
    reuse = _reuse(path, meta, (n, n))
    if reuse is not None:
        return reuse
    w = BlockCSRWriter(path, (n, n), tile_size=tile_size, dtype="float32", pixel_order=order,
                       metadata=meta, overwrite=True)
    k = nnz_per_row - 1
    for i in range(-(-n // tile_size)):
        r0, r1 = i * tile_size, min((i + 1) * tile_size, n)
        pix = perm[r0:r1]  # row-major pixel of each matrix row
        y, x = np.divmod(pix, W)
        dy = rng.integers(-radius, radius + 1, (r1 - r0, k))
        dx = rng.integers(-radius, radius + 1, (r1 - r0, k))
        cols_rm = np.clip(y[:, None] + dy, 0, H - 1) * W + np.clip(x[:, None] + dx, 0, W - 1)
        cols = inv[cols_rm]
        vals = rng.uniform(0.5, 1.0, (r1 - r0, k))
        vals *= spread * diag / vals.sum(axis=1, keepdims=True)
        rows = np.repeat(np.arange(r1 - r0), k)
        off = sp.csr_array((vals.ravel(), (rows, cols.ravel())), shape=(r1 - r0, n))
        off.sum_duplicates()
        block = off + sp.csr_array((np.full(r1 - r0, diag), (np.arange(r1 - r0),
                                    np.arange(r0, r1))), shape=(r1 - r0, n))
        block = sp.csr_array(block)
        block.sort_indices()
        w.write_tile_row(i, block.astype(np.float32))
    return w.finalize()


def corner_scene(size, path, density):
    """The corner scene ``bigT.scenes.corner`` at ``path`` (reused when a complete one
    with the same size and density is there)."""
    import bigT.scenes as scenes

    try:
        sc = scenes.load(path)
        if tuple(sc.summary["image_shape"]) == tuple(size) and sc.summary.get("density") == density:
            return sc
    except (bigT.BigTError, KeyError):
        pass
    return scenes.corner(size=size, path=str(path), density=density, overwrite=True,
                         preview=False, progress=False)


def exact_inverse_from_scene(scene, path):
    """X = F^-1 (I - A) from the scene's ground truth, tile row by tile row."""
    from bigT.storage import BlockCSRWriter

    T = scene.T
    w = BlockCSRWriter(path, T.shape, tile_size=T.tile_size, dtype="float32",
                       pixel_order=T.pixel_order, metadata={"exact_inverse": True},
                       overwrite=True)
    for i in range(T.grid[0]):
        w.write_tile_row(i, scene.exact_inverse_rows(i).astype(np.float32))
    return w.finalize()


def stratified(T, path, terms, prune=None):
    """A fresh ``bigT.stratified_inverse`` of T at ``path``: (X, seconds)."""
    import shutil

    if Path(path).exists():  # a fresh inverse of this run's T (the engine resumes otherwise)
        shutil.rmtree(path)
    kw = {} if prune is None else {"prune": prune}
    t0 = time.perf_counter()
    bigT.stratified_inverse(T, path, terms=terms, progress=False, **kw)
    return bigT.open(path), time.perf_counter() - t0


# --- part 1 -----------------------------------------------------------------------------

def throughput(args, out):
    size = _size(args.size)
    res = {"size": list(size)}
    if not args.synthetic:
        t0 = time.perf_counter()
        scene = corner_scene(size, out / f"corner_{size[0]}x{size[1]}.zarr", args.density)
        T = scene.T
        res["T"] = f"bigT.scenes.corner, density {args.density}"
        res["scene_seconds"] = time.perf_counter() - t0
        X, secs = stratified(T, str(out / "X_stratified4.zarr"), 4)
        res["X"] = "bigT.stratified_inverse, 4 terms"
        res["invert_seconds"] = secs
    else:
        T = synthetic_local(out / "T_synth.zarr", size, args.t_nnz, seed=1)
        X = synthetic_local(out / "X_synth.zarr", size, args.x_nnz, seed=2)
        res["T"] = f"synthetic local transport, {args.t_nnz} nnz/row"
        res["X"] = f"synthetic local matrix, {args.x_nnz} nnz/row (docs/DESIGN.md's 4-term inverse)"
    n = T.shape[0]
    res.update(nnz_T=int(T.nnz), nnz_X=int(X.nnz), nnz_X_per_row=X.nnz / n,
               nnz_T_per_row=T.nnz / n)
    print(f"[throughput] {size[0]}x{size[1]}, n = {n:,}; T: {res['T']} ({T.nnz / n:.0f}/row); "
          f"X: {res['X']} ({X.nnz / n:.0f}/row)")
    X = bigT.open(X.path)  # from disk, nothing cached in the object
    from bigT.compensation import stream_matmul
    from bigT.schedule.worker import STATE

    rng = np.random.default_rng(0)
    frames = rng.uniform(0.2, 0.8, (args.frames, *size)).astype(np.float64)
    V64 = X.pixel_order.to_matrix(frames[:64]).astype(np.float32)

    def timed(fn):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        return time.perf_counter() - t0, time.process_time() - c0

    stream_matmul(X, V64[:, :1])  # compile the kernel, warm the page cache
    for K in (1, 64):
        V = np.ascontiguousarray(V64[:, :K])
        wall, cpu = timed(lambda: stream_matmul(X, V, cache_bytes=0))
        res[f"pass_cold_K{K}_seconds"], res[f"pass_cold_K{K}_cpu_seconds"] = wall, cpu
        cache = STATE.cache  # the process's tile cache
        cache.drop_where(lambda path: True)
        stream_matmul(X, V, cache_bytes=args.cache_mb << 20)
        h0, m0 = cache.hits, cache.misses
        wall_w, cpu_w = timed(lambda: stream_matmul(X, V, cache_bytes=args.cache_mb << 20))
        res[f"pass_warm_K{K}_seconds"], res[f"pass_warm_K{K}_cpu_seconds"] = wall_w, cpu_w
        res[f"cache_fraction_K{K}"] = (cache.hits - h0) / max(cache.hits - h0 + cache.misses - m0, 1)
        print(f"  one pass over X, batch {K:>2}: read from disk {wall:.2f} s "
              f"({K / wall:.2f} frames/s, {cpu:.2f} CPU-s); tiles cached "
              f"({100 * res[f'cache_fraction_K{K}']:.0f} % hits) {wall_w:.2f} s "
              f"({K / wall_w:.2f} frames/s, {cpu_w:.2f} CPU-s)")
    wall, cpu = timed(lambda: compensate(X, frames, batch=64, cache_bytes=args.cache_mb << 20))
    res["compensate_batch64_fps"] = len(frames) / wall
    res["compensate_batch64_cpu_ms_per_frame"] = 1e3 * cpu / len(frames)
    wall0, cpu0 = timed(lambda: compensate(X, frames[:64], batch=64, cache_bytes=0))
    res["compensate_batch64_nocache_fps"] = 64 / wall0
    res["compensate_batch64_nocache_cpu_ms_per_frame"] = 1e3 * cpu0 / 64
    print(f"  compensate(), {len(frames)} frames, batch 64, end to end (images in/out, clip): "
          f"{res['compensate_batch64_fps']:.2f} frames/s ({1e3 * cpu / len(frames):.1f} CPU-ms "
          f"per frame) with the tile cache; {res['compensate_batch64_nocache_fps']:.2f} frames/s "
          f"({1e3 * cpu0 / 64:.1f} CPU-ms per frame) re-reading X every batch")
    for cache_mb in (args.cache_mb, 0):
        t0 = time.perf_counter()
        compensate(None, frames[:64], T=T, terms=4, path="matrix-free", batch=64,
                   cache_bytes=cache_mb << 20)
        res[f"matrix_free4_batch64_cache{cache_mb}_fps"] = 64 / (time.perf_counter() - t0)
        print(f"  matrix-free, 4 terms, batch 64, cache {cache_mb} MiB: "
              f"{res[f'matrix_free4_batch64_cache{cache_mb}_fps']:.2f} frames/s")
    choice = bigT.compensation.choose_path(X, T, 4, "auto")
    res["auto_choice"] = f"{choice.path}: {choice.reason}"
    print(f"  auto would take: {res['auto_choice']}")
    if not args.no_splu:
        res.update(splu_in_child(T.path, frames[:args.frames_b1], args))
    return res


def _splu_child(path, frames, q):
    import resource

    from scipy.sparse.linalg import splu

    try:
        T = bigT.open(path)
        t0 = time.perf_counter()
        Ts = sp.csc_matrix(T.to_scipy(output_order="matrix"), dtype=np.float64)
        load = time.perf_counter() - t0
        t0 = time.perf_counter()
        lu = splu(Ts)
        factor = time.perf_counter() - t0
        B = T.pixel_order.to_matrix(frames)
        t0 = time.perf_counter()
        for c in range(B.shape[1]):
            lu.solve(np.ascontiguousarray(B[:, c], dtype=np.float64))
        fps = B.shape[1] / (time.perf_counter() - t0)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        q.put(dict(splu_load_seconds=load, splu_factor_seconds=factor, splu_solve_fps=fps,
                   splu_nnz_LU=int(lu.L.nnz + lu.U.nnz), splu_peak_rss_mb=rss))
    except MemoryError:
        q.put(dict(splu="MemoryError"))


def splu_in_child(path, frames, args):
    """scipy splu of T in a child process with a time and memory limit."""
    import multiprocessing as mp
    import resource

    ctx = mp.get_context("fork")
    q = ctx.Queue()
    limit = args.splu_gb << 30
    old = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (limit, old[1]))  # inherited by the child only
    try:
        proc = ctx.Process(target=_splu_child, args=(str(path), frames, q))
        proc.start()
    finally:
        resource.setrlimit(resource.RLIMIT_AS, old)
    proc.join(args.splu_seconds)
    if proc.is_alive():
        proc.kill()
        proc.join()
        out = {"splu": f"did not finish in {args.splu_seconds} s"}
    else:
        out = q.get() if not q.empty() else {"splu": f"failed (exit {proc.exitcode}, "
                                                      f"{args.splu_gb} GB address-space limit)"}
    if "splu_factor_seconds" in out:
        print(f"  scipy splu: factor {out['splu_factor_seconds']:.1f} s (after "
              f"{out['splu_load_seconds']:.1f} s loading T; nnz(L+U) = {out['splu_nnz_LU']:,}, "
              f"peak RSS {out['splu_peak_rss_mb']:.0f} MB), then {out['splu_solve_fps']:.2f} "
              "frames/s (one solve per frame)")
    else:
        print(f"  scipy splu: {out['splu']}")
    return out


# --- part 2 -----------------------------------------------------------------------------

def quality(args, out, figure: Path | None = None):
    size = _size(args.scene_size)
    scene = corner_scene(size, out / f"corner_q_{size[0]}x{size[1]}.zarr", "exact")
    T, what = scene.T, "bigT.scenes.corner (exact)"
    X = exact_inverse_from_scene(scene, out / "X_q_exact.zarr")
    n = T.shape[0]
    # A constant target the exact inverse reproduces without clipping above 1.
    ones = np.ones(size)
    c = float(min(0.5, 0.9 / compensate(X, ones, clip=None).max()))
    desired = np.full(size, c)
    seen0 = relight(T, desired)
    res = {"size": list(size), "n": n, "nnz_T_per_row": T.nnz / n, "target": c, "rows": [],
           "scene": what}

    def row(label, l_in_raw):
        l_in = np.clip(l_in_raw, 0, 1)
        seen = relight(T, l_in)
        r = dict(label=label, rel_error=relative_error(seen, desired),
                 fluct_image=fluctuation(seen), fluct_scanline=fluctuation(scan_line(seen)),
                 clipped=float(np.mean((l_in_raw < 0) | (l_in_raw > 1))))
        res["rows"].append(r)
        print(f"  {label:<34} error {r['rel_error']:.4f}  fluctuation image "
              f"{r['fluct_image']:.3f}  scan line {r['fluct_scanline']:.3f}  clipped "
              f"{100 * r['clipped']:.2f} %")
        return seen

    print(f"[quality] {what} {size[0]}x{size[1]}, n = {n:,}, T {T.nnz / n:.0f} nnz/row, "
          f"constant target {c:.3f}")
    r0 = dict(label="uncompensated", rel_error=relative_error(seen0, desired),
              fluct_image=fluctuation(seen0), fluct_scanline=fluctuation(scan_line(seen0)),
              clipped=0.0)
    res["rows"].append(r0)
    print(f"  {'uncompensated':<34} error {r0['rel_error']:.4f}  fluctuation image "
          f"{r0['fluct_image']:.3f}  scan line {r0['fluct_scanline']:.3f}")
    lines = {"uncompensated": scan_line(seen0)}
    for terms in range(1, 5):
        raw = compensate(None, desired, T=T, terms=terms, path="matrix-free", clip=None)
        lines[f"{terms} term(s)"] = scan_line(row(f"stratified n={terms} (eq. 13, unpruned)", raw))
        Xs, secs = stratified(T, str(out / f"X_q_{terms}"), terms)
        row(f"stratified_inverse n={terms} ({secs:.1f} s)", compensate(Xs, desired, clip=None))
    lines["exact inverse"] = scan_line(row("exact inverse F^-1 (I - A)",
                                           compensate(X, desired, clip=None)))
    # Throughput at this size, where sparse LU is a serious rival (docs/DESIGN.md).
    frames = np.random.default_rng(1).uniform(0.2, 0.8, (64, *size))
    compensate(X, frames[:1])
    for batch in (1, 64):
        k = 8 if batch == 1 else 64
        t0 = time.perf_counter()
        compensate(X, frames[:k], batch=batch)
        res[f"explicit_batch{batch}_fps"] = k / (time.perf_counter() - t0)
    print(f"  explicit exact X at {size[0]}x{size[1]}: batch 1 {res['explicit_batch1_fps']:.1f} "
          f"frames/s, batch 64 {res['explicit_batch64_fps']:.1f} frames/s")
    if not args.no_splu:
        res.update(splu_in_child(T.path, frames[:8], args))
    from bigT.figures import scan_lines

    res["plot"] = str(scan_lines(figure or out / "scanlines_terms.png", lines, target=c,
                                 title=f"corner {size[0]}x{size[1]}: centre scan line seen by "
                                 "the camera, constant target"))
    return res


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", default="384x512")
    p.add_argument("--scene-size", default="48x64")
    p.add_argument("--frames", type=int, default=256)
    p.add_argument("--frames-b1", type=int, default=8)
    p.add_argument("--x-nnz", type=int, default=445)
    p.add_argument("--t-nnz", type=int, default=385)
    p.add_argument("--synthetic", action="store_true", help="synthetic T and X for part 1")
    p.add_argument("--density", default="sparse", help="density preset of the part 1 scene")
    p.add_argument("--no-splu", action="store_true")
    p.add_argument("--splu-gb", type=int, default=6, help="address-space limit of the splu child")
    p.add_argument("--splu-seconds", type=int, default=300)
    p.add_argument("--cache-mb", type=int, default=1024)
    p.add_argument("--skip", choices=("throughput", "quality"), action="append", default=[])
    p.add_argument("--out", default="bench-out/compensate")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"cpus": os.cpu_count(), "load_average_at_start": os.getloadavg()}
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs "
          "(wall-clock rates scale with the share of the machine this run gets)")
    res = Results(run_name("compensate"), "Compensation: throughput and quality",
                  "python benchmarks/bench_compensate.py " + " ".join(
                      argv if argv is not None else sys.argv[1:]))
    figure = f"{res.name}-scanlines.png"
    if "quality" not in args.skip:
        results["quality"] = quality(args, out, res.figure_path(figure))
        record_quality(res, results["quality"], figure)
    if "throughput" not in args.skip:
        results["throughput"] = throughput(args, out)
        record_throughput(res, results["throughput"])
    (out / "results.json").write_text(json.dumps(results, indent=2, default=str))
    print(f"results -> {out / 'results.json'}")
    res.save()


def record_quality(res: Results, q: dict, figure: str) -> None:
    """Part 2's printed lines and its plot, handed to RESULTS.md."""
    H, W = q["size"]
    res.table("quality", f"a constant target ({q['target']:.3f}) on the {q['scene']} "
              f"{H}x{W} corner, compensated", ["compensation", "relative error",
              "fluctuation (image)", "fluctuation (scan line)", "clipped"],
              [[r["label"], r["rel_error"], r["fluct_image"], r["fluct_scanline"],
                r["clipped"]] for r in q["rows"]],
              note="fluctuation: (max - min) / mean of what the camera sees (the paper's "
                   "measure); clipped: fraction of projector pixels outside [0, 1]")
    res.figure(figure, f"centre scan line seen by the camera, {H}x{W} corner, constant "
               "target: uncompensated, 1-4 terms, exact inverse (the paper's Fig. 10)")


def throughput_rows(t: dict) -> list[list]:
    """Part 1's printed rates as (path, frames/s) rows."""
    rows = []
    for K in (1, 64):
        rows += [[f"one pass over X, batch {K}, read from disk",
                  K / t[f"pass_cold_K{K}_seconds"]],
                 [f"one pass over X, batch {K}, tiles cached",
                  K / t[f"pass_warm_K{K}_seconds"]]]
    rows += [["compensate(), batch 64, end to end, tile cache", t["compensate_batch64_fps"]],
             ["compensate(), batch 64, end to end, X re-read every batch",
              t["compensate_batch64_nocache_fps"]]]
    rows += [[f"matrix-free, 4 terms, batch 64, cache {k.split('cache')[1][:-4]} MiB", v]
             for k, v in t.items() if k.startswith("matrix_free4_batch64_cache")]
    if "splu_solve_fps" in t:
        rows.append([f"scipy splu of T, one solve per frame (factor "
                     f"{t['splu_factor_seconds']:.1f} s)", t["splu_solve_fps"]])
    elif "splu" in t:
        rows.append([f"scipy splu of T: {t['splu']}", None])
    return rows


def record_throughput(res: Results, t: dict) -> None:
    """Part 1's printed rates, handed to RESULTS.md."""
    H, W = t["size"]
    res.table("throughput", f"compensation throughput at {H}x{W}: T {t['T']} "
              f"({t['nnz_T_per_row']:.0f} a row), X {t['X']} ({t['nnz_X_per_row']:.0f} a row)",
              ["path", "frames/s"], throughput_rows(t),
              note=f"auto would take: {t['auto_choice']}")


if __name__ == "__main__":
    main()
