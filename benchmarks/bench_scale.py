"""How the cost of a 4-term stratified inverse grows with n, up to a full-HD projector
(reported, not asserted).

For each size the wall-corner scene is built with its form-factor cut and threshold
scaled so that T keeps about the same nonzeros per row (~84, the dense preset at
1080x1920; measured: A's entries per row go as cut^-1.5 n^-0.5 and T's as n^-0.5 at a
fixed threshold, so the cut scales as n^-1/3 and the threshold as n^-1/2). Then, each
in a fresh child process:

* the scene build: time and peak RSS;
* ``bigT.stratified_inverse`` (power form, 4 terms, the README's recommended prune
  3e-6, feed 1e-4 and operator 1e-5, ``--memory-limit``):
  time per term, peak RSS, X's nonzeros and bytes on disk;
* the error of X against the exact inverse F^-1 (I - A) on a random sample of rows
  (``Scene.inverse_error(X, sample=...)``), and the residual estimate;
* ``bigT compensate --simulate`` of one image of the projector's size, streamed: time
  and the compensated error.

The fitted exponent of time against n (least squares in log-log) is printed, and a
log-log plot is written beside the record RESULTS.md is made from (``_results``:
``$BIGT_BENCH_OUT``, default bench-out/)::

    python benchmarks/bench_scale.py --max-size 49152    # make bench --quick: ~1 min
    python benchmarks/bench_scale.py --max-size 2073600  # the full-HD point: ~30 min

A ``--workdir`` that already holds a scene reuses it.

``--cluster-model`` checks and plots the model of a cluster run instead
(``cluster_model.py``): ``bigT invert`` of one scene (default 192x256, out of core) on
local threads, ``--scheduler local:1`` and ``local:2``, each ``--repeats`` times
interleaved (the best kept); the model built from the threads run and from the
1-worker run predicts the others (error per configuration), then full HD and 4K on
N = 1..128 workers on a shared filesystem and an object store::

    python benchmarks/bench_scale.py --cluster-model [--size 192x256] [--repeats 2]

On a machine with more cores, ``--workers 16,8,4,2 --measure-only`` makes the runs and
keeps their reports (``cluster_curve.sh`` does it at full HD), and ``--from-reports
DIR --bases local:2,threads`` checks the model on them anywhere. The 16-core run of
``benchmarks/results/cluster-h200/`` (an accelerator machine's CPUs, no GPU used)::

    python benchmarks/bench_scale.py --cluster-model --size 1080x1920 --repeats 1 \
        --from-reports benchmarks/results/cluster-h200 --bases local:2,threads
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from typing import Sequence

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from _results import Results, run_name  # noqa: E402

#: (H, W) of the sizes measured: n = 12288 (for a quick fit), 49152, 196608, 786432,
#: 2073600, and 4K UHD's 8294400 (its own run, ``--min-size 8294400 --max-size
#: 8294400``, with ``--ff-cut``: see ``main``'s help).
SIZES = [(96, 128), (192, 256), (384, 512), (768, 1024), (1080, 1920), (2160, 3840)]
#: The dense preset at full HD anchors the scaled densities.
ANCHOR_N, ANCHOR_CUT, ANCHOR_THRESHOLD = 1080 * 1920, 1e-4, 1e-7


def density_for(n: int) -> tuple[float, float]:
    """(form-factor cut, threshold) keeping T's nonzeros per row about constant."""
    ratio = n / ANCHOR_N
    return ANCHOR_CUT * ratio ** (-1 / 3), ANCHOR_THRESHOLD * ratio ** (-1 / 2)


def disk_bytes(path: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def peak_rss() -> int:
    from bigT.schedule.memory import peak_resident_bytes

    return peak_resident_bytes()


def child_build(args) -> dict:
    import bigT.scenes as scenes

    H, W = args.size
    cut, thr = density_for(H * W)
    cut = cut if args.ff_cut is None else args.ff_cut
    thr = thr if args.threshold is None else args.threshold
    t0 = time.perf_counter()
    sc = scenes.corner((H, W), args.scene, ff_cut=cut, threshold=thr, preview=False,
                       progress=False, memory_limit=args.scene_memory)
    return {"seconds": time.perf_counter() - t0, "peak_rss_bytes": peak_rss(),
            "summary": sc.summary}


def child_invert(args) -> dict:
    import bigT

    scene = bigT.scenes.load(args.scene)
    out = os.path.join(os.path.dirname(args.scene), "X.zarr")
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    rep = bigT.stratified_inverse(scene.T, out, terms=args.terms, prune=args.prune,
                                  prune_feed=args.prune_feed, prune_operator=args.prune_operator,
                                  memory_limit=args.memory_limit, progress=False)
    wall = time.perf_counter() - t0
    peak = peak_rss()  # before the error is measured: that reads X and A again
    X = bigT.open(out)
    t0 = time.perf_counter()
    err = scene.inverse_error(X, sample=args.sample, seed=0)
    return {"seconds": wall, "peak_rss_bytes": peak, "nnz_X": int(X.nnz),
            "X_disk_bytes": disk_bytes(out), "sampled_error": err,
            "sample_rows": args.sample, "error_seconds": time.perf_counter() - t0,
            "report": rep.to_dict()}


def compensate(scene_path: str, size) -> dict:
    """``bigT compensate X.zarr image --simulate T.zarr``: wall time and the printed
    line with the compensated error."""
    import numpy as np
    from bigT.images import write_image

    H, W = size
    work = os.path.dirname(scene_path)
    y, x = np.mgrid[0:H, 0:W]
    image = 0.25 + 0.2 * np.sin(x / W * 6 * np.pi) * np.cos(y / H * 4 * np.pi)
    src = os.path.join(work, "desired.png")
    write_image(src, image, bits=16)
    out = os.path.join(work, "compensated.png")
    cmd = [sys.executable, "-m", "bigT.cli", "compensate", os.path.join(work, "X.zarr"), src,
           "--simulate", scene_path, "-o", out, "--no-progress"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"compensate failed: {proc.stderr.strip()}")
    text = proc.stdout
    error = re.search(r"([0-9.e-]+) compensated, ([0-9.e-]+) uncompensated", text)
    products = re.search(r"frame\(s\) in ([0-9.]+) s of products", text)
    return {"seconds": wall, "products_s": float(products[1]) if products else None,
            "error": float(error[1]) if error else None,
            "uncompensated_error": float(error[2]) if error else None}


def warm_up() -> None:
    """Build and invert a tiny scene here first, so numba's on-disk cache holds every
    kernel before the timed children start (else the first child's term 2 would
    include the compilation, ~8 s)."""
    import tempfile

    import bigT

    with tempfile.TemporaryDirectory(prefix="bench_scale_warm_") as tmp:
        sc = bigT.scenes.corner((24, 32), os.path.join(tmp, "T.zarr"), density="dense",
                                preview=False, progress=False, tile_size=256)
        bigT.stratified_inverse(sc.T, os.path.join(tmp, "X.zarr"), terms=2, progress=False)


def run_child(kind: str, args, size, scene: str) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--_child", kind, "--scene", scene,
           "--size", f"{size[0]}x{size[1]}", "--terms", str(args.terms),
           "--prune", str(args.prune), "--memory-limit", args.memory_limit,
           "--sample", str(args.sample), "--scene-memory", str(args.scene_memory)]
    cmd += [] if args.prune_feed is None else ["--prune-feed", str(args.prune_feed)]
    cmd += [] if args.prune_operator is None else ["--prune-operator", str(args.prune_operator)]
    cmd += [] if args.ff_cut is None else ["--ff-cut", str(args.ff_cut)]
    cmd += [] if args.threshold is None else ["--threshold", str(args.threshold)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        print(proc.stderr, file=sys.stderr)
        raise SystemExit(f"{kind} {size}: child failed")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def fit_exponent(xs, ys) -> float:
    """Slope of log y against log x (least squares); nan with fewer than 2 points."""
    if len(xs) < 2:
        return math.nan
    lx = [math.log(x) for x in xs]
    ly = [math.log(y) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    sxx = sum((a - mx) ** 2 for a in lx)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sxx


def exponents(rows) -> dict[str, tuple[float, str]]:
    """The fitted exponents (least squares in log-log), each with what it measures."""
    ns, secs = [r["n"] for r in rows], [r["invert_s"] for r in rows]
    return {
        "time": (fit_exponent(ns, secs), "exponent of the inverse's time in n"),
        "time-nnz": (fit_exponent([r["nnz_T"] for r in rows], secs),
                     "exponent of the inverse's time in nnz(T)"),
        "peak": (fit_exponent(ns, [r["peak_gib"] for r in rows]),
                 "exponent of the inverse's peak RSS in n"),
        "build": (fit_exponent(ns, [r["build_s"] for r in rows]),
                  "exponent of the scene build's time in n"),
    }


def settings(args) -> str:
    """The series' thresholds, as a user gives them."""
    words = [f"prune {args.prune:g}"]
    words += [] if args.prune_feed is None else [f"feed {args.prune_feed:g}"]
    words += [] if args.prune_operator is None else [f"operator {args.prune_operator:g}"]
    return ", ".join(words)


#: The scale table's columns and the row keys they show (a record's rows are read back
#: by them: :func:`own_run_rows`).
TABLE_COLUMNS = [("size", "size"), ("n", "n"), ("T nnz/row", "nnz_T_per_row"),
                 ("build s", "build_s"), ("build peak GiB", "build_peak_gib"),
                 ("inverse s", "invert_s"), ("terms s", "term_s"), ("peak GiB", "peak_gib"),
                 ("X on disk GiB", "X_disk_gib"), ("error", "sampled_error"),
                 ("residual", "residual"), ("compensate s", "compensate_s"),
                 ("compensated error", "compensated_error")]


def own_run_rows(path: str, measured_here: set[str]) -> tuple[list[dict], str]:
    """The rows of an earlier ``bench_scale.py`` run's record (its own run at a size the
    full plan leaves out: full HD, 4K), less the sizes this run measured, each marked
    with the run's commit and date; and a line saying what was used (or why not).

    Parameters
    ----------
    path : a ``scale.json`` record (``_results.Results``) of that run
    measured_here : sizes ("HxW") this run measured: theirs are not taken

    Returns
    -------
    (rows, line) : row dicts with :data:`TABLE_COLUMNS`' keys and ``measured``
    """
    if not os.path.exists(path):
        return [], f"{path}: not found (no own run)"
    with open(path) as fh:
        record = json.load(fh)
    code = record.get("code") or {}
    when = time.strftime("%Y-%m-%d", time.localtime(record.get("started", 0)))
    source = (f"own run, {code.get('commit', '?')}"
              f"{'' if code.get('clean', False) else '+changes'}, {when}")
    rows = []
    for table in record.get("tables", []):
        if table.get("key") != "scale":
            continue
        keys = dict(TABLE_COLUMNS)
        for values in table["rows"]:
            row = {keys[c]: v for c, v in zip(table["columns"], values) if c in keys}
            if row.get("size") in measured_here:
                continue
            row["term_s"] = [float(t) for t in str(row.get("term_s", "")).split()]
            rows.append({**row, "measured": source})
    return rows, f"{path}: {len(rows)} row(s) ({source}: `{record.get('command', '?')}`)"


def record_rows(res, rows, args, own_lines: Sequence[str] = ()) -> None:
    """The printed table, handed to RESULTS.md (``_results.Results``); rows from own
    runs (``measured`` set) say so in the last column."""
    res.table("scale", f"{args.terms}-term inverse ({settings(args)}, memory limit "
              f"{args.memory_limit}) against n, the corner at ~constant nonzeros per row",
              [c for c, _ in TABLE_COLUMNS] + ["measured"],
              [[" ".join(f"{t:.1f}" for t in r["term_s"]) if key == "term_s" else r[key]
                for _, key in TABLE_COLUMNS] + [r.get("measured", "this run")]
               for r in rows],
              note=f"error: against the exact inverse F^-1 (I - A) on {args.sample} "
                   "sampled rows; peak GiB: the inverse's process; compensate: "
                   "`bigT compensate --simulate` of one image, streamed (time and error). "
                   "Rows of an own run (full HD and 4K take tens of minutes each, out of "
                   "the full plan) were measured by that run, with its commit's code: "
                   + ("; ".join(own_lines) if own_lines else "none given") + ".")


def plot(rows, path: str, own: Sequence[dict] = ()) -> str:
    """Time (s) and peak memory (GiB) against n, each on its own labelled log axis: this
    run's rows joined (slopes fitted on them), an own run's rows (``own``) as hollow
    markers of the same colour, labelled with their run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401 (matplotlib.ticker below)

    n = [r["n"] for r in rows]
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(10.5, 4.4))
    series = ((ax_t, "invert_s", "4-term inverse", "o"), (ax_t, "build_s", "scene build", "s"),
              (ax_m, "peak_gib", "inverse: peak RSS", "^"),
              (ax_m, "build_peak_gib", "scene build: peak RSS", "v"))
    for ax, key, label, marker in series:
        ys = [r[key] for r in rows]
        line, = ax.loglog(n, ys, marker=marker,
                          label=f"{label}, slope {fit_exponent(n, ys):.2f}")
        for r in own:
            ax.loglog([r["n"]], [r[key]], marker=marker, ls="none", mfc="none",
                      color=line.get_color(), ms=9)
    for r in own:  # one label per own run's size, beside its inverse time
        ax_t.annotate(f"{r['size']}: {r['measured']}", (r["n"], r["invert_s"]), fontsize=7,
                      xytext=(-6, 8), textcoords="offset points", ha="right")
    ref = [rows[0]["invert_s"] * x / n[0] for x in n + [r["n"] for r in own]]
    ax_t.loglog(n + [r["n"] for r in own], ref, "k:", lw=1, label="slope 1 (linear in n)")
    ax_t.set_ylabel("wall time (s)")
    ax_t.set_title("time" + (" (hollow: own runs)" if own else ""), fontsize=10)
    ax_m.set_ylabel("peak resident memory (GiB)")
    ax_m.set_title("memory" + (" (hollow: own runs)" if own else ""), fontsize=10)
    # 0.25 ... 8 GiB written plainly, not 6 x 10^0
    ax_m.yaxis.set_major_locator(matplotlib.ticker.LogLocator(base=2))
    ax_m.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax_m.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    for ax in (ax_t, ax_m):
        ax.set_xlabel("n (projector pixels)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="lower right")  # the own runs' labels sit top right
    fig.suptitle("bigT: cost against n at ~constant nonzeros per row (2 cores)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def invert_report(scene: str, out: str, scheduler, args, threads: int | None = None) -> dict:
    """One out-of-core ``bigT invert`` in a fresh process (on ``threads`` local threads
    when no ``scheduler``; bigT's default otherwise); its JSON report."""
    report = out + ".json"
    cmd = [sys.executable, "-m", "bigT.cli", "invert", scene, "-o", out, "--terms",
           str(args.terms), "--prune", str(args.prune), "--memory-limit", args.memory_limit,
           "--no-progress", "--overwrite", "--json", report]
    cmd += [] if args.prune_feed is None else ["--prune-feed", str(args.prune_feed)]
    cmd += [] if args.prune_operator is None else ["--prune-operator", str(args.prune_operator)]
    if scheduler:
        cmd += ["--scheduler", scheduler]
    elif threads:
        cmd += ["--threads", str(threads)]
    env = {**os.environ, "BIGT_IN_MEMORY": "0"}  # a cluster run is out of core: so is this
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env,
                          timeout=getattr(args, "run_timeout", None))
    if proc.returncode:
        raise SystemExit(f"invert on {scheduler or 'threads'} failed: {proc.stderr.strip()}")
    with open(report) as fh:
        return json.load(fh)


def store_bandwidth(path: str) -> tuple[float, float]:
    """(bytes/s, seconds per file) reading every file of the store at ``path``, as the
    run met it (read once to warm the page cache, then timed)."""
    files = [os.path.join(d, f) for d, _, fs in os.walk(path) for f in fs]
    for f in files:
        open(f, "rb").read()
    t0 = time.perf_counter()
    nbytes = sum(len(open(f, "rb").read()) for f in files)
    wall = time.perf_counter() - t0
    return nbytes / wall, wall / max(1, len(files))


def cluster_configs(workers: list[int], threads: int) -> list[tuple[str, str | None, int, int]]:
    """(label, --scheduler, worker processes, threads each) of the runs to make: local
    threads (one per core) first, then ``local:N`` for each N asked for."""
    return [("threads", None, 1, threads)] + [(f"local:{n}", f"local:{n}", n, 1)
                                              for n in workers]


def measure_configs(args, scene: str, work: str, configs) -> dict:
    """Each configuration's best run (``--repeats``, interleaved) as ``{label: (seconds,
    report)}``; a configuration that fails or outlasts ``--run-timeout`` is left out (the
    model is checked on those that ran). Each report stays beside its X as
    ``X-<label>.zarr.json`` and ``runs.json`` lists them (``--from-reports`` reads it); a
    later ``--measure-only`` call in the same ``--workdir`` adds to it, skipping the runs
    it holds (a call that reports starts anew: :func:`cluster_model`)."""
    best: dict = {}
    runs = []
    saved = os.path.join(work, "runs.json")
    if os.path.exists(saved):  # an earlier call's runs, kept: those configurations are done
        with open(saved) as fh:
            old = json.load(fh)
        runs = old["runs"]
        best = {label: (min(r["seconds"] for r in runs if r["label"] == label), report)
                for label, report in old["best"].items()}
    for rep in range(args.repeats):
        for label, scheduler, workers, threads in configs:
            if label in best and rep < sum(r["label"] == label for r in runs):
                continue
            t0 = time.perf_counter()
            try:
                r = invert_report(scene, os.path.join(work, f"X-{label}.zarr"), scheduler,
                                  args, threads)
            except (SystemExit, subprocess.TimeoutExpired) as exc:
                print(f"run {rep + 1} {label}: left out ({exc})", flush=True)
                continue
            wall = time.perf_counter() - t0
            total = sum(h["seconds"] for h in r["history"]) + r["seconds_spectral_radius"]
            print(f"run {rep + 1} {label}: {total:.2f} s (terms and spectral radius), "
                  f"{wall:.1f} s the whole process", flush=True)
            runs.append({"label": label, "workers": workers, "threads": threads,
                         "seconds": total, "process_seconds": wall, "repeat": rep + 1})
            if label not in best or total < best[label][0]:
                best[label] = (total, r)
            with open(os.path.join(work, "runs.json"), "w") as fh:
                json.dump({"cpus": os.cpu_count(), "runs": runs,
                           "best": {k: v[1] for k, v in best.items()}}, fh)
    return best


def cluster_model(args) -> None:
    import cluster_model as cm

    H, W = args.size
    work = os.path.join(args.workdir, f"corner-{H}x{W}")
    configs = cluster_configs(args.workers, args.threads or os.cpu_count() or 1)
    if args.from_reports:
        saved = json.load(open(os.path.join(args.from_reports, "runs.json")))
        best = {label: (None, r) for label, r in saved["best"].items()}
        storage = json.load(open(os.path.join(args.from_reports, "storage.json")))
        bandwidth, per_file = storage["bandwidth"], storage["per_file"]
        cpus = saved["cpus"]
        configs = [c for c in cluster_configs(
            sorted({r["workers"] for r in saved["runs"] if r["label"] != "threads"}),
            int(best["threads"][1]["threads"]) if "threads" in best else cpus)
            if c[0] in best]  # the threads run's own count (its report's)
    else:
        os.makedirs(work, exist_ok=True)
        scene = os.path.join(work, "T.zarr")
        if not os.path.exists(os.path.join(work, "build.json")):  # else built (the
            # builder resumes a scene an earlier call left unfinished)
            built = run_child("build", args, (H, W), scene)
            print(f"scene built: {built['seconds']:.0f} s, peak "
                  f"{built['peak_rss_bytes'] / 2**30:.2f} GiB", flush=True)
            with open(os.path.join(work, "build.json"), "w") as fh:
                json.dump(built, fh, default=str)
        warm_up()
        if not args.measure_only:  # a run that reports measures anew: an earlier call's
            # runs (another commit, another load) are kept only to resume --measure-only
            with contextlib.suppress(FileNotFoundError):
                os.unlink(os.path.join(work, "runs.json"))
        best = measure_configs(args, scene, work, configs)
        bandwidth, per_file = store_bandwidth(scene)
        with open(os.path.join(work, "storage.json"), "w") as fh:
            json.dump({"bandwidth": bandwidth, "per_file": per_file}, fh)
        cpus = os.cpu_count()
    if args.measure_only:
        print(f"reports in {work}: runs.json, storage.json")
        return
    local = cm.local_storage(bandwidth, per_file)
    # the local cluster's vectors cross loopback: pickled and copied, ~2 GB/s
    sched = {"threads": cm.DASK_THREADS,
             "cluster": replace_network(cm.DASK_DISTRIBUTED, 2e9)}
    bases = [b for b in args.bases.split(",") if b in best]
    if not bases:
        raise SystemExit(f"none of the base runs {args.bases} was made: {sorted(best)}")
    rows, checks = [], {}
    for base in bases:
        run = cm.RecordedRun.from_report(best[base][1], local)
        checks[base] = run
        for label, _, workers, threads in configs:
            if label == base or label not in best:
                continue
            p = cm.predict(run, H * W, workers, local,
                           sched["threads" if label == "threads" else "cluster"],
                           threads=threads, tile_size=best[label][1]["tile_size"])
            m = cm.measured_from_report(label, workers, best[label][1])
            m = cm.Measured(m.label, m.workers, m.seconds_terms, m.seconds_spectral,
                            m.peak_per_worker, p)
            rows.append([base, label, p.seconds, m.seconds_terms + m.seconds_spectral,
                         100 * m.error, p.memory_per_worker / 2**20,
                         m.peak_per_worker / 2**20, 100 * m.memory_error])
    print(f"\nstorage: {bandwidth / 1e9:.2f} GB/s, {per_file * 1e6:.0f} us per file "
          f"(page cache); {cpus} cores")
    print(f"{'from':>8} {'predicts':>8} {'pred s':>7} {'meas s':>7} {'err %':>6} "
          f"{'pred MiB':>8} {'meas MiB':>8} {'err %':>6}")
    for r in rows:
        print(f"{r[0]:>8} {r[1]:>8} {r[2]:>7.2f} {r[3]:>7.2f} {r[4]:>+6.0f} {r[5]:>8.0f} "
              f"{r[6]:>8.0f} {r[7]:>+6.0f}")
    base = next((b for b in bases if b.startswith("local:")), bases[0])
    table = cm.prediction_table(checks[base])
    print(f"\n{'n':>9} {'storage':>18} " + " ".join(f"{'N=' + str(n):>8}" for n in cm.WORKERS))
    out_rows = []
    for n in (cm.FULL_HD, cm.UHD_4K):
        for st in (cm.SHARED_FS, cm.OBJECT_STORE):
            ps = [p for p in table if p.n == n and p.storage == st.name]
            print(f"{n:>9} {st.name:>18} " + " ".join(f"{p.seconds:>8.0f}" for p in ps))
            print(f"{'':>9} {'GiB per worker':>18} "
                  + " ".join(f"{p.memory_per_worker / 2**30:>8.2f}" for p in ps))
            out_rows += [[n, st.name, p.workers, p.seconds, p.memory_per_worker / 2**30,
                          p.batched] for p in ps]
    where = f"{cpus} cores" + (f", reports of {args.from_reports}" if args.from_reports else "")
    res = Results(run_name("cluster-model"), "The cluster run, predicted and checked",
                  "python benchmarks/bench_scale.py " + " ".join(sys.argv[1:]))
    res.table("check", f"the model against the runs made ({H}x{W} corner, {where}, "
              f"{args.terms} terms, out of core, best of {args.repeats})",
              ["from", "predicts", "predicted s", "measured s", "error %",
               "predicted MiB/worker", "measured MiB/worker", "memory error %"], rows,
              note="seconds: the spectral radius and the terms (set-up and the cluster's "
                   f"start left out); storage {bandwidth / 1e9:.2f} GB/s (page cache)")
    res.table("predicted", "predicted inverse (spectral radius and 4 terms) on N dask "
              f"workers of 1 thread, 8 GiB each, from the {base} run",
              ["n", "storage", "workers", "seconds", "GiB per worker", "batched"], out_rows,
              note=f"{cm.SHARED_FS.name}: {cm.SHARED_FS.source}; {cm.OBJECT_STORE.name}: "
                   f"{cm.OBJECT_STORE.source}; scheduler: {cm.DASK_DISTRIBUTED.source}")
    name = f"{res.name}.png"
    print("plot:", plot_cluster(table, rows, H * W, cpus, base, str(res.figure_path(name))))
    res.figure(name, f"left: predicted time against workers at full HD and 4K, shared "
               f"filesystem and object store, from the {base} run; right: the runs made, "
               "measured and predicted")
    res.save()


def replace_network(scheduler, network: float):
    from dataclasses import replace

    return replace(scheduler, network=network)


def plot_cluster(table, checks, n_here: int, cpus: int, base: str, path: str) -> str:
    """Left: predicted seconds against N (log-log) for full HD and 4K, shared filesystem
    (solid) and object store (dashed), from the ``base`` run. Right: the runs made, as
    measured against N workers (black), beside what each base run predicts for them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import cluster_model as cm

    fig, (ax, ax_c) = plt.subplots(1, 2, figsize=(11, 4.4),
                                   gridspec_kw={"width_ratios": [3, 2]})
    for n, colour, name in ((cm.FULL_HD, "C0", "full HD"), (cm.UHD_4K, "C3", "4K UHD")):
        for st, style in ((cm.SHARED_FS, "-"), (cm.OBJECT_STORE, "--")):
            ps = [p for p in table if p.n == n and p.storage == st.name]
            ax.loglog([p.workers for p in ps], [p.seconds for p in ps], style, color=colour,
                      marker="o", ms=3, label=f"{name}, {st.name}")
    ax.set_xlabel("dask workers N (1 thread each)")
    ax.set_ylabel("predicted wall time of the inverse (s)")
    ax.set_title(f"predicted: spectral radius + 4 terms, from the {base} run", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    workers_of = lambda label: int(label.split(":")[1])  # noqa: E731 ("local:N")
    measured = sorted({(workers_of(r[1]), r[3]) for r in checks if r[1] != "threads"})
    ax_c.plot([m[0] for m in measured], [m[1] for m in measured], "ko-", lw=2,
              label="measured")
    for i, b in enumerate(dict.fromkeys(r[0] for r in checks)):
        ps = sorted((workers_of(r[1]), r[2]) for r in checks
                    if r[0] == b and r[1] != "threads")
        ax_c.plot([p[0] for p in ps], [p[1] for p in ps], "--", marker="s", ms=4,
                  color=f"C{i + 2}", label=f"predicted from the {b} run")
    ax_c.set_xscale("log", base=2)
    ax_c.set_xlabel("dask workers N (local:N, 1 thread each)")
    ax_c.set_ylabel("wall time of the inverse (s)")
    ax_c.set_ylim(bottom=0)
    ax_c.set_title(f"checked: n = {n_here:,} on {cpus} cores", fontsize=10)
    ax_c.grid(alpha=0.3, which="both")
    ax_c.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--max-size", type=int, default=196608,
                   help="largest n to run (default 196608; 2073600 for full HD)")
    p.add_argument("--min-size", type=int, default=0, help="smallest n to run")
    p.add_argument("--terms", type=int, default=4)
    # the README's recommended thresholds (issue #30's full-HD figure): P_k pruned at
    # 1e-4 keeps the products of a dense 4K T within minutes
    p.add_argument("--prune", type=float, default=3e-6)
    p.add_argument("--prune-feed", type=float, default=1e-4)
    p.add_argument("--prune-operator", type=float, default=1e-5)
    p.add_argument("--memory-limit", default="4GiB")
    p.add_argument("--scene-memory", type=int, default=2 << 30,
                   help="memory_limit of the scene builds, bytes")
    p.add_argument("--ff-cut", type=float, default=None,
                   help="the scene's form-factor cut instead of the scaled one (the 4K point: "
                        "7e-5 with --threshold 1e-7, the dense preset's, for > 50 entries per "
                        "row at about 60%% of the scaled density's entries)")
    p.add_argument("--threshold", type=float, default=None,
                   help="the scene's threshold instead of the scaled one")
    p.add_argument("--sample", type=int, default=2048,
                   help="rows of the sampled error against the exact inverse")
    p.add_argument("--no-compensate", action="store_true")
    p.add_argument("--workdir", default="bench-out/scale")
    p.add_argument("--json", default=None)
    p.add_argument("--own-runs", default="",
                   help="comma-separated scale.json records of earlier runs of this script "
                        "at sizes the run leaves out (full HD, 4K: each its own run, "
                        "--min-size N --max-size N); their rows join the table and the "
                        "plot, marked with their commit and date (a missing file is noted)")
    p.add_argument("--cluster-model", action="store_true",
                   help="check the cluster model on threads, local:1 and local:2 and plot "
                        "its predictions (see the module's docstring)")
    p.add_argument("--repeats", type=int, default=2, help="runs of each configuration "
                   "(--cluster-model; the best kept)")
    p.add_argument("--workers", default="1,2",
                   help="--cluster-model: the local:N clusters to run, e.g. 1,2,4,8,16")
    p.add_argument("--threads", type=int, default=None,
                   help="--cluster-model: threads of the local-threads run (default: cores)")
    p.add_argument("--run-timeout", type=float, default=None,
                   help="--cluster-model: seconds after which a run is stopped and left out")
    p.add_argument("--bases", default="threads,local:1",
                   help="--cluster-model: the runs the model is built from, each predicting "
                        "the others (the first local:N also gives the N = 1..128 table)")
    p.add_argument("--measure-only", action="store_true",
                   help="--cluster-model: make the runs, keep their reports, skip the model; "
                        "a later --measure-only call adds the runs this one left undone "
                        "(without it, every run is made anew)")
    p.add_argument("--from-reports", default=None,
                   help="--cluster-model: the model checked on the runs.json and storage.json "
                        "a --measure-only run left in this folder (another machine's)")
    p.add_argument("--_child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--scene", default=None, help=argparse.SUPPRESS)
    p.add_argument("--size", default=None,
                   help="HxW of the --cluster-model scene (default 192x256)")
    args = p.parse_args(argv)
    if args.cluster_model:
        args.size = tuple(int(s) for s in (args.size or "192x256").split("x"))
        args.workers = [int(n) for n in args.workers.split(",")]
        cluster_model(args)
        return
    if args._child:
        args.size = tuple(int(s) for s in args.size.split("x"))
        res = child_build(args) if args._child == "build" else child_invert(args)
        print(json.dumps(res, default=str))
        return
    warm_up()
    rows = []
    for size in [s for s in SIZES if args.min_size <= s[0] * s[1] <= args.max_size]:
        n = size[0] * size[1]
        work = os.path.join(args.workdir, f"corner-{size[0]}x{size[1]}")
        os.makedirs(work, exist_ok=True)
        scene = os.path.join(work, "T.zarr")
        built = json.load(open(os.path.join(work, "build.json"))) if os.path.exists(
            os.path.join(work, "build.json")) and os.path.exists(scene) else None
        if built is None:
            built = run_child("build", args, size, scene)
            json.dump(built, open(os.path.join(work, "build.json"), "w"), default=str)
        inv = run_child("invert", args, size, scene)
        comp = None if args.no_compensate else compensate(scene, size)
        s = built["summary"]
        row = {"size": f"{size[0]}x{size[1]}", "n": n, "nnz_T": s["nnz_T"],
               "nnz_T_per_row": s["nnz_T"] / n, "nnz_A_per_row": s["nnz_A"] / n,
               "rho": s["spectral_radius"], "build_s": built["seconds"],
               "build_peak_gib": built["peak_rss_bytes"] / 2**30,
               "invert_s": inv["seconds"], "peak_gib": inv["peak_rss_bytes"] / 2**30,
               "term_s": [h["seconds"] for h in inv["report"]["history"]],
               "nnz_X": inv["nnz_X"], "X_disk_gib": inv["X_disk_bytes"] / 2**30,
               "sampled_error": inv["sampled_error"], "sample_rows": inv["sample_rows"],
               "residual": inv["report"]["history"][-1]["residual"],
               "compensate_s": comp["seconds"] if comp else None,
               "compensate_products_s": comp["products_s"] if comp else None,
               "compensated_error": comp["error"] if comp else None,
               "uncompensated_error": comp["uncompensated_error"] if comp else None}
        rows.append(row)
        print(json.dumps(row, default=str), flush=True)
    print(f"\n{'size':>10} {'n':>9} {'T/row':>6} {'build s':>8} {'build GiB':>9} "
          f"{'inverse s':>9} {'per term s':>24} {'peak GiB':>8} {'X GiB':>6} "
          f"{'error':>9} {'comp s':>7} {'comp err':>8}")
    for r in rows:
        terms = " ".join(f"{t:.1f}" for t in r["term_s"])
        comp = (f"{r['compensate_s']:>7.1f} {r['compensated_error']:>8.4f}"
                if r["compensate_s"] is not None else f"{'-':>7} {'-':>8}")
        print(f"{r['size']:>10} {r['n']:>9} {r['nnz_T_per_row']:>6.1f} {r['build_s']:>8.1f} "
              f"{r['build_peak_gib']:>9.2f} {r['invert_s']:>9.1f} {terms:>24} "
              f"{r['peak_gib']:>8.2f} {r['X_disk_gib']:>6.2f} {r['sampled_error']:>9.2e} "
              f"{comp}")
    res = Results(run_name("scale"), "Cost of a 4-term inverse against n",
                  "python benchmarks/bench_scale.py " + " ".join(sys.argv[1:]))
    own, own_lines = [], []
    for path in [p for p in args.own_runs.split(",") if p]:
        taken, line = own_run_rows(path, {r["size"] for r in rows} | {r["size"] for r in own})
        own += taken
        own_lines.append(line)
        print("own run:", line, flush=True)
    record_rows(res, sorted(rows + own, key=lambda r: r["n"]), args, own_lines)
    if len(rows) > 1:
        exps = exponents(rows)
        print(f"fitted exponent of the inverse's time in n: {exps['time'][0]:.2f}; in nnz(T): "
              f"{exps['time-nnz'][0]:.2f}; of its peak RSS in n: {exps['peak'][0]:.2f}; "
              f"of the build's time: {exps['build'][0]:.2f}")
        for key, (value, what) in exps.items():
            res.value(f"exponent:{key}", value, what)
        print("plot:", plot(rows, str(res.figure_path(f"{res.name}.png")), own))
        res.figure(f"{res.name}.png", "time and peak memory of the 4-term inverse and the "
                   "scene build against n (log-log, slopes fitted on this run's sizes in "
                   "the legend; hollow markers: own runs at larger sizes, with their "
                   "commit and date)")
    res.save()
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1, default=str)


if __name__ == "__main__":
    main()
