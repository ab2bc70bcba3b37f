"""Benchmark of bigT's kernels against scipy, sparse_dot_topn and python-graphblas.

Not a test: prints one table per size, every method timed side by side in the same
run (timings on a shared machine drift; compare only within one table).

Input: M = I - T F^-1 with F = diag(T) of the synthetic corner scene
(``bigT.scenes.corner``). The default density knobs (form-factor cut 2e-4, threshold
1e-6) give about docs/DESIGN.md's 385 nonzeros per row at 96x128.

    python benchmarks/bench_kernels.py --sizes 96x128,192x256 --threshold 1e-5 --repeat 3
"""

from __future__ import annotations

import argparse
import gc
import sys
import time

import numpy as np
import scipy.sparse as sp
from _results import Results, run_name


def corner_M(H, W, ff_cut, threshold):
    """(M, description): M = I - T diag(T)^-1 (the engine's M, zero diagonal) of the
    synthetic corner scene ``bigT.scenes.corner`` at H x W, float32 CSR."""
    import tempfile  # noqa: PLC0415

    from bigT.scenes import corner  # noqa: PLC0415

    with tempfile.TemporaryDirectory(prefix="bigT-bench-") as tmp:
        scene = corner(size=(H, W), path=f"{tmp}/corner.zarr", ff_cut=ff_cut,
                       threshold=threshold, preview=False, progress=False)
        T = sp.csr_array(scene.T.to_scipy(output_order="matrix"), dtype=np.float32)
    d = T.diagonal().astype(np.float32)
    M = sp.csr_array(sp.eye_array(T.shape[0], dtype=np.float32, format="csr")
                     - T @ sp.diags_array(1.0 / d))
    M.eliminate_zeros()
    M.sum_duplicates()
    M.sort_indices()
    return M, f"bigT.scenes.corner (ff_cut {ff_cut:g}, threshold {threshold:g})"


def timed(func, repeat):
    best, out = np.inf, None
    for _ in range(repeat):
        out = None
        gc.collect()
        t = time.perf_counter()
        out = func()
        best = min(best, time.perf_counter() - t)
    return best, out


def scipy_then_prune(M, threshold, product=None):
    """scipy's M @ M (or a given ``product``), then entries below ``threshold`` dropped."""
    C = sp.csr_array(M @ M if product is None else product)
    if threshold > 0:
        C.data[np.abs(C.data) < threshold] = 0
        C.eliminate_zeros()
    C.sort_indices()
    return C


def maxdiff(C, ref):
    D = sp.csr_array(C, dtype=np.float64) - sp.csr_array(ref, dtype=np.float64)
    return float(np.abs(D.data).max()) if D.nnz else 0.0


def profile_spgemm(M, threshold, repeat):
    """Single-thread CPU seconds of the phases of bigT's grouped spgemm on M @ M."""
    from numba import njit  # noqa: PLC0415

    from bigT import kernels  # noqa: PLC0415
    from bigT.kernels import _csr_kernels as K  # noqa: PLC0415
    from bigT.kernels.csr import _as_csr, row_work  # noqa: PLC0415

    @njit(nogil=True)
    def setup_and_scatter(ap, aj, ax, bp, bj, bx, n_cols, scatter):
        # The grouped kernel without its emission: group set-up (+ the scatter).
        G = K.GROUP
        acc = np.zeros(n_cols * G)
        stamp = np.full(bp.shape[0] - 1, -1, np.int64)
        slot = np.zeros(bp.shape[0] - 1, np.int64)
        max_row = np.max(ap[1:] - ap[:-1])
        ulist = np.empty(G * max_row + 1, np.int64)
        avals = np.zeros((G * max_row + 1) * G)
        n = ap.shape[0] - 1
        for g0 in range(0, n, G):
            nu = 0
            for r in range(min(G, n - g0)):
                for p in range(ap[g0 + r], ap[g0 + r + 1]):
                    k = aj[p]
                    if stamp[k] != g0:
                        stamp[k] = g0
                        slot[k] = nu
                        ulist[nu] = k
                        avals[nu * G: nu * G + G] = 0.0
                        nu += 1
                    avals[slot[k] * G + r] += ax[p]
            if scatter:
                K._group_scatter(ulist, nu, avals, bp, bj, bx, acc)
                acc[:] = 0.0
        return acc.sum()

    def cpu(f):
        best = np.inf
        for _ in range(repeat):
            t = time.process_time()
            f()
            best = min(best, time.process_time() - t)
        return best

    a = _as_csr(M, "A")
    args = (a.indptr, a.indices, a.data, a.indptr, a.indices, a.data, M.shape[1])
    setup_and_scatter(*args, False)
    n = M.shape[0]
    t_check = cpu(lambda: _as_csr(M, "A"))
    t_work = cpu(lambda: row_work(a.indptr, a.indices, a.indptr))
    t_setup = cpu(lambda: setup_and_scatter(*args, False))
    t_scatter = cpu(lambda: setup_and_scatter(*args, True)) - t_setup
    t_kernel = cpu(lambda: K.spgemm_grouped_internal(0, n, *args, threshold, 0.25, 1024))
    t_total = cpu(lambda: kernels.spgemm(M, M, threshold=threshold, n_threads=1))
    t_scipy = cpu(lambda: M @ M)
    print("   profile, 1 thread, CPU seconds (process_time, best of %d):" % repeat)
    print(f"     checks {t_check:.3f} | row work {t_work:.3f} | group set-up {t_setup:.3f} | "
          f"scatter {t_scatter:.3f} | emission+prune+buffers "
          f"{t_kernel - t_setup - t_scatter:.3f} | wrapper rest "
          f"{t_total - t_kernel - t_check - t_work:.3f} | total {t_total:.3f} "
          f"(scipy M@M {t_scipy:.3f})")


def bench_size(H, W, threshold, repeat, n_threads, methods, profile=False, ff_cut=2e-4,
               scene_threshold=1e-6, res=None):
    """Time M @ M (and A @ X) at H x W, print the tables and hand them to ``res``."""
    from bigT import kernels  # noqa: PLC0415

    M, source = corner_M(H, W, ff_cut, scene_threshold)
    n = M.shape[0]
    print(f"\n== {H}x{W}  n={n}  nnz/row={M.nnz / n:.0f}  dtype={M.dtype}  input: {source}")
    print(f"   M @ M, threshold {threshold:g}, best of {repeat}, {n_threads} threads")

    kernels.spgemm(M[:64], M, threshold=threshold)  # compile / load the numba cache
    t_ref, ref = timed(lambda: scipy_then_prune(M, threshold), repeat)
    rows = [("scipy M@M + prune", t_ref, ref)]
    t_raw, raw = timed(lambda: M @ M, repeat)
    print(f"   (scipy M@M alone {t_raw:.2f} s, {raw.nnz / n:.0f} nnz/row unpruned; "
          f"pruned {ref.nnz / n:.0f} nnz/row)")
    # sparse_dot_topn allocates n_rows x top_n up front: give it the largest row.
    top_n = max(int(np.diff(raw.indptr).max()), 1)
    del raw
    t, C = timed(lambda: kernels.spgemm(M, M, threshold=threshold, n_threads=n_threads), repeat)
    rows.append((f"bigT spgemm ({n_threads} thr)", t, C))
    if n_threads != 1:
        t, C = timed(lambda: kernels.spgemm(M, M, threshold=threshold, n_threads=1), repeat)
        rows.append(("bigT spgemm (1 thr)", t, C))
    t, C = timed(
        lambda: kernels.spgemm(M, M, threshold=threshold, n_threads=n_threads, method="rows"),
        repeat,
    )
    rows.append((f"bigT spgemm rows ({n_threads} thr)", t, C))
    if "bsr" in methods:
        # docs/DESIGN.md's micro-block variant: M is in image-tile-major order with 8x8 image
        # tiles, so 8x8 blocks of M are pairs of image tiles. scipy's BSR product (1
        # thread) + prune, to see whether a BSR inner format would pay.
        for bs in (4, 8):
            Mb = sp.bsr_array(M, blocksize=(bs, bs))
            fill = M.nnz / max(Mb.data.size, 1)

            def bsr_prod(Mb=Mb):
                return scipy_then_prune(None, threshold, product=Mb @ Mb)

            t, C = timed(bsr_prod, repeat)
            rows.append((f"scipy BSR {bs}x{bs} ({100 * fill:.0f}% fill) + prune", t, C))
    if "topn" in methods:
        try:
            from sparse_dot_topn import sp_matmul_topn  # noqa: PLC0415

            Ms = sp.csr_matrix(M)
            t, C = timed(
                lambda: sp_matmul_topn(
                    Ms, Ms, top_n=top_n, threshold=threshold, sort=False, n_threads=n_threads
                ),
                repeat,
            )
            rows.append((f"sparse_dot_topn ({n_threads} thr)", t, C))
        except ImportError as exc:
            print(f"   sparse_dot_topn unavailable: {exc}")
    if "graphblas" in methods:
        try:
            import graphblas as gb  # noqa: PLC0415

            G = gb.io.from_scipy_sparse(sp.csr_matrix(M))

            def gb_prod():
                P = (G @ G).new()
                if threshold > 0:
                    # The thunk must carry the matrix dtype (a Python float is not
                    # taken as one: nothing would be selected away).
                    t = M.dtype.type(threshold)
                    keep = P.apply(gb.unary.abs).new().select(gb.select.valuege, t).new()
                    Q = gb.Matrix(P.dtype, P.nrows, P.ncols)
                    Q(keep.S) << P
                    P = Q
                return P

            t, P = timed(gb_prod, repeat)
            rows.append(("python-graphblas + select", t, gb.io.to_scipy_sparse(P, format="csr")))
        except ImportError as exc:
            print(f"   python-graphblas unavailable: {exc}")

    print("   (sparse_dot_topn top_n = largest row of the unpruned product, %d)" % top_n)
    print(f"   {'method':<30} {'time [s]':>9} {'scipy/x':>8} {'nnz/row':>8} {'max|diff|':>10}")
    table = [[name, t, t_ref / t, C.nnz / n, maxdiff(C, ref)] for name, t, C in rows]
    for name, t, ratio, per_row, diff in table:
        print(f"   {name:<30} {t:9.3f} {ratio:8.2f} {per_row:8.0f} {diff:10.2e}")
    if res is not None:
        res.table(f"spgemm:{H}x{W}", f"pruned product M @ M at {H}x{W} (n = {n:,}, "
                  f"{M.nnz / n:.0f} nonzeros a row), threshold {threshold:g}, best of "
                  f"{repeat}", ["method", "time s", "scipy/x", "nnz/row", "max|diff|"], table,
                  note=f"input: {source}; scipy/x: scipy's M@M + prune time over this one's")
        res.value(f"speedup:{H}x{W}", t_ref / rows[1][1],
                  f"bigT's pruned product M·M ({n_threads} threads) against scipy's M@M + "
                  f"prune at {H}x{W} ({M.nnz / n:.0f} nonzeros a row), scipy's time over "
                  "bigT's")

    if profile:
        profile_spgemm(M, threshold, repeat)

    print(f"   spmm_dense: A @ X, X of shape (n, k), {M.dtype}")
    print(f"   {'k':>4} {'scipy [s]':>10} {'bigT [s]':>9} {'scipy/bigT':>10} {'max|diff|':>10}")
    rng = np.random.default_rng(1)
    dense = []
    for k in (1, 64):
        X = rng.random((n, k)).astype(M.dtype)
        reps = max(repeat, 20 if k == 1 else 5)
        kernels.spmm_dense(M[:64], X)
        ts, Ys = timed(lambda: M @ X, reps)
        tb, Yb = timed(lambda: kernels.spmm_dense(M, X, n_threads=n_threads), reps)
        dense.append([k, ts, tb, ts / tb, float(np.abs(Ys - Yb).max())])
        print(f"   {k:>4} {ts:10.4f} {tb:9.4f} {ts / tb:10.2f} {dense[-1][-1]:10.2e}")
    if res is not None:
        res.table(f"spmm:{H}x{W}", f"A @ X at {H}x{W}, X of shape (n, k), {M.dtype}",
                  ["k", "scipy s", "bigT s", "scipy/bigT", "max|diff|"], dense)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="96x128,192x256", help="HxW[,HxW...]")
    ap.add_argument("--threshold", type=float, default=1e-5)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--methods", default="topn,graphblas,bsr",
                    help="rivals to run besides scipy (topn, graphblas, bsr)")
    ap.add_argument("--profile", action="store_true", help="CPU time of spgemm's phases")
    ap.add_argument("--ff-cut", type=float, default=2e-4, help="scene form-factor cut")
    ap.add_argument("--scene-threshold", type=float, default=1e-6, help="scene threshold on T")
    args = ap.parse_args(argv)
    methods = set(filter(None, args.methods.split(",")))
    res = Results(run_name("kernels"), "Kernels: the pruned product against scipy and rivals",
                  "python benchmarks/bench_kernels.py " + " ".join(argv or sys.argv[1:]))
    for size in args.sizes.split(","):
        H, W = (int(v) for v in size.lower().split("x"))
        bench_size(H, W, args.threshold, args.repeat, args.threads, methods, args.profile,
                   args.ff_cut, args.scene_threshold, res)
    res.save()


if __name__ == "__main__":
    main()
