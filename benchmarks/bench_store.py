"""Write/read throughput and peak memory: bigT block-CSR store vs scipy save_npz/load_npz.

Every case runs in its own subprocess, so its peak RSS (``ru_maxrss``) is its own.
Throughput is MB/s of CSR payload (float32 data + int32 indices + indptr of the
in-memory matrix), the same number of bytes for every case.

    python benchmarks/bench_store.py                    # 196608 x 196608, ~50 nnz/row
    python benchmarks/bench_store.py --n 20000 --nnz-per-row 20
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
import scipy.sparse as sp

CASES = {
    # name: (what it does, bytes-moved direction)
    "bigt_write": "bigT from_scipy (zstd + crc32c tiles)",
    "bigt_read": "bigT open + to_scipy",
    "bigt_stream": "bigT open + get_tile_row, one at a time",
    "bigt_matvec": "bigT open + A @ x (streamed)",
    "npz_write": "scipy save_npz (compressed=True)",
    "npz_read": "scipy load_npz (compressed)",
    "npz_raw_write": "scipy save_npz (compressed=False)",
    "npz_raw_read": "scipy load_npz (uncompressed)",
}


def make_matrix(n: int, per_row: int, seed: int = 0) -> sp.csr_array:
    """Banded-ish random float32 matrix: per_row entries per row within +-n/48 of the diagonal."""
    rng = np.random.default_rng(seed)
    half = max(per_row, n // 48)
    rows = np.repeat(np.arange(n, dtype=np.int64), per_row)
    cols = (rows + rng.integers(-half, half + 1, size=rows.size)) % n
    data = rng.random(rows.size, dtype=np.float32)
    A = sp.csr_array((data, (rows, cols)), shape=(n, n))
    A.sum_duplicates()
    idx = np.int32 if max(n, A.nnz) < 2**31 else np.int64
    return sp.csr_array((A.data, A.indices.astype(idx), A.indptr.astype(idx)), shape=(n, n))


def _rss_mb() -> float:
    """Peak RSS of this process in MiB.

    VmHWM is per address space and starts afresh at exec; ru_maxrss on Linux keeps the
    parent's peak across fork+exec, so it is only the fallback.
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _load_input(workdir):
    z = np.load(os.path.join(workdir, "input.npz"))
    return sp.csr_array((z["data"], z["indices"], z["indptr"]), shape=tuple(z["shape"]))


def run_case(case: str, workdir: str, tile_size: int) -> dict:
    import bigT.storage as storage

    store = os.path.join(workdir, "bigt.zarr")
    npz = os.path.join(workdir, "scipy.npz")
    raw = os.path.join(workdir, "scipy_raw.npz")
    base = 0.0
    if case.endswith("write"):
        A = _load_input(workdir)
        base = _rss_mb()
        t = time.perf_counter()
        if case == "bigt_write":
            storage.from_scipy(A, store, tile_size=tile_size, dtype="float32", overwrite=True)
        else:
            sp.save_npz(npz if case == "npz_write" else raw, A, compressed=case == "npz_write")
        seconds = time.perf_counter() - t
        nnz = A.nnz  # what was written
    else:
        if case == "bigt_matvec":  # JIT warm-up of the kernels layer, outside the timing
            S = storage.open(store)
            S.get_tile(0, 0) @ np.ones(S.tile_shape(0, 0)[1], dtype=np.float32)
            (S.get_tile(0, 0) @ np.ones((S.tile_shape(0, 0)[1], 1), dtype=np.float32))
            try:
                from bigT.kernels import spmm_dense
                spmm_dense(sp.csr_array(np.eye(2, dtype=np.float32)), np.ones(2, np.float32))
            except ImportError:
                pass
        t = time.perf_counter()
        if case == "bigt_read":
            B = storage.open(store).to_scipy(max_bytes=1 << 40)
            nnz = B.nnz
        elif case == "bigt_stream":
            S = storage.open(store)
            nnz = sum(S.get_tile_row(i).nnz for i in range(S.grid[0]))
        elif case == "bigt_matvec":
            S = storage.open(store)
            y = S @ np.ones(S.shape[1], dtype=np.float32)
            nnz = S.nnz if np.isfinite(y).all() else -1
        else:
            nnz = sp.load_npz(npz if case == "npz_read" else raw).nnz
        seconds = time.perf_counter() - t
    return {"seconds": seconds, "peak_rss_mb": _rss_mb(), "base_rss_mb": base, "nnz": nnz}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=196608)
    p.add_argument("--nnz-per-row", type=int, default=50)
    p.add_argument("--tile-size", type=int, default=None, help="default config.DEFAULT_TILE_SIZE")
    p.add_argument("--workdir", default=None, help="scratch directory (default: a temp dir)")
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of " + ",".join(CASES))
    p.add_argument("--case", help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    from bigT import config
    tile_size = args.tile_size or config.DEFAULT_TILE_SIZE
    if args.case:  # child process
        print(json.dumps(run_case(args.case, args.workdir, tile_size)))
        return 0

    workdir = args.workdir or tempfile.mkdtemp(prefix="bench_store-")
    os.makedirs(workdir, exist_ok=True)
    try:
        A = make_matrix(args.n, args.nnz_per_row)
        payload = A.data.nbytes + A.indices.nbytes + A.indptr.nbytes
        np.savez(os.path.join(workdir, "input.npz"), data=A.data, indices=A.indices,
                 indptr=A.indptr, shape=np.array(A.shape))
        nnz = A.nnz
        del A
        print(f"matrix {args.n} x {args.n}, nnz {nnz} ({nnz / args.n:.1f}/row), float32, "
              f"CSR payload {payload / 1e6:.1f} MB, bigT tile size {tile_size}, "
              f"{os.cpu_count()} CPUs")
        print(f"{'case':<44} {'time s':>8} {'MB/s':>8} {'peak RSS MiB':>12} {'(input) MiB':>11} {'disk MB':>8}")
        sizes = {"bigt": "bigt.zarr", "npz": "scipy.npz", "npz_raw": "scipy_raw.npz"}
        for case in [c for c in args.cases.split(",") if c]:
            if case not in CASES:
                raise SystemExit(f"unknown case {case!r}")
            out = subprocess.run([sys.executable, os.path.abspath(__file__), "--case", case,
                                  "--workdir", workdir, "--n", str(args.n),
                                  "--tile-size", str(tile_size)],
                                 capture_output=True, text=True, check=False)
            if out.returncode:
                print(f"{case}: failed\n{out.stderr}", file=sys.stderr)
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            target = os.path.join(workdir, sizes[case.rsplit("_", 1)[0]])
            disk = (_dir_bytes(target) if os.path.isdir(target) else os.path.getsize(target)) / 1e6
            base = f"{r['base_rss_mb']:.0f}" if r["base_rss_mb"] else "-"
            print(f"{CASES[case]:<44} {r['seconds']:8.2f} {payload / 1e6 / r['seconds']:8.1f} "
                  f"{r['peak_rss_mb']:12.0f} {base:>11} {disk:8.1f}")
    finally:
        if not args.workdir:
            shutil.rmtree(workdir, ignore_errors=True)
    return 0


def _dir_bytes(path):
    return sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(path) for f in fs)


if __name__ == "__main__":
    sys.exit(main())
