"""Benchmark of the stratified inverse on a synthetic wall-corner scene (reported, not
asserted).

For each setting (default: power and horner side by side at ``--prune``) a fresh
child process runs ``bigT.stratified_inverse`` on the scene's T and reports: time per
term (its residual estimate's share), nnz of P and X, the residual estimate, the
multiply-adds of the term's products with two rates per core (over the term's wall
time, everything a user waits for, and inside the product kernel only, the bare
kernel on the same tiles), the error against the known true inverse F^-1 (I - A)
(relative Frobenius, tile row by tile row, on ``--sample`` rows or all) and the
child's peak RSS.

    python benchmarks/bench_inverse.py --size 192x256 --terms 4 --prune 1e-5 \
        --method power,horner
    python benchmarks/bench_inverse.py --size 384x512 --density dense \
        --settings power:1e-5,power:1e-5:1e-4,horner:4e-5 --sample 2048

A setting is ``method:prune``, ``power:prune:prune_feed`` (the power form feeding
on P_k pruned at ``prune_feed``, see ``bigT.algorithms.stratified``, "Carrying") or
``power:prune:prune_feed:prune_operator`` (and M pruned at ``prune_operator`` in the
products after the first term).

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

from _results import Results, run_name  # noqa: E402

TERM_COLUMNS = ["term", "time s", "residual s", "nnz(P)", "nnz(X)", "residual",
                "multiply-adds", "rate/core (wall)", "kernel rate/core", "kernel share"]
SETTING_COLUMNS = ["setting", "total s", "spectral radius s", "terms s (residuals included)",
                   "multiply-adds", "error vs F^-1(I-A)", "nnz(X)/row", "peak RSS GiB"]


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
                                  prune_feed=args.prune_feed,
                                  prune_operator=args.prune_operator, method=args.method,
                                  memory_limit=args.memory_limit, progress=False)
    wall = time.perf_counter() - t0
    peak = peak_rss()
    X = bigT.open(out)
    err = scene.inverse_error(X, sample=args.sample)
    res = {"method": args.method, "setting": args.setting, "wall_s": wall,
           "peak_rss_bytes": peak,
           "error_vs_true_inverse": err, "nnz_X": int(X.nnz), "n": int(X.shape[0]),
           "report": rep.to_dict()}
    print(json.dumps(res, default=str))


def run_setting(setting: str, scene_path: str, workdir: str, args) -> dict:
    """One setting in a fresh child; prints its per-term table and returns its result."""
    method, prune, *thresholds = setting.split(":")
    cmd = [sys.executable, os.path.abspath(__file__), "--_child", "--scene", scene_path,
           "--workdir", workdir, "--method", method, "--terms", str(args.terms),
           "--prune", prune, "--setting", setting]
    for flag, value in zip(("--prune-feed", "--prune-operator"), thresholds):
        cmd += [flag, value]
    cmd += ["--memory-limit", args.memory_limit] if args.memory_limit else []
    cmd += ["--sample", str(args.sample)] if args.sample else []
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        print(proc.stderr, file=sys.stderr)
        raise SystemExit(f"{setting}: child failed")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    rep = r["report"]
    print(f"\n== {setting}: {r['wall_s']:.1f} s (spectral radius estimate "
          f"{rep['seconds_spectral_radius']:.1f} s), peak RSS "
          f"{r['peak_rss_bytes'] / 2**30:.2f} GiB, nnz(X)/row {r['nnz_X'] / r['n']:.0f}, "
          f"relative error vs F^-1(I-A) {r['error_vs_true_inverse']:.3e}, "
          f"rho(M) {rep['spectral_radius']:.3f}, load {os.getloadavg()[0]:.1f}")
    print_terms(rep)
    return r


def term_rows(rep: dict) -> list[list]:
    """The per-term rows of a report (as a dict): ``TERM_COLUMNS``."""
    threads = rep.get("threads", 1)
    rows = []
    for h in rep["history"]:
        madds, kern = h.get("multiply_adds", 0), h.get("kernel_seconds", 0.0)
        wall_rate = madds / (h["seconds"] * threads) if madds else 0.0
        kern_rate = madds / kern if madds and kern else 0.0
        share = kern / (h["seconds"] * threads) if h["seconds"] else 0.0
        rows.append([h["term"], h["seconds"], h.get("residual_seconds", 0.0), h["nnz_P"],
                     h["nnz_X"], h["residual"], madds, wall_rate, kern_rate, share])
    return rows


def print_terms(rep: dict) -> None:
    """The per-term table of a report (as a dict), multiply-adds and rates per core."""
    print("| " + " | ".join(TERM_COLUMNS) + " |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for term, secs, rsecs, nnz_p, nnz_x, resid, madds, wall_rate, kern_rate, share in \
            term_rows(rep):
        print(f"| {term} | {secs:.2f} | {rsecs:.2f} | {nnz_p} | {nnz_x} | {resid:.3e} | "
              f"{madds:.3g} | {wall_rate:.3g} | {kern_rate:.3g} | {share:.0%} |")


def setting_row(r: dict) -> list:
    """One setting's totals: ``SETTING_COLUMNS``."""
    rep = r["report"]
    return [r["setting"], r["wall_s"], rep["seconds_spectral_radius"],
            sum(h["seconds"] for h in rep["history"]),
            sum(h.get("multiply_adds", 0) for h in rep["history"]),
            r["error_vs_true_inverse"], r["nnz_X"] / r["n"], r["peak_rss_bytes"] / 2**30]


def record(results: list[dict], args, scene_text: str) -> None:
    """The printed tables, handed to RESULTS.md (``_results.Results``)."""
    res = Results(run_name("inverse"), f"The stratified inverse term by term, "
                  f"{args.size[0]}x{args.size[1]} {args.density} corner",
                  "python benchmarks/bench_inverse.py " + " ".join(sys.argv[1:]))
    res.table("settings", f"{args.terms} terms per setting (method:prune[:prune_feed[:prune_operator]])",
              SETTING_COLUMNS, [setting_row(r) for r in results],
              note=f"{scene_text}; error: relative Frobenius against F^-1 (I - A)"
                   + (f" on {args.sample} sampled rows" if args.sample else ""))
    for r in results:
        res.table(f"terms:{r['setting']}", f"per term, {r['setting']}", TERM_COLUMNS,
                  term_rows(r["report"]),
                  note="rates are multiply-adds per second per core: over the term's wall "
                       "time, and inside the product kernel")
    res.save()


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=_size, default=(96, 128), help="HxW (default 96x128)")
    p.add_argument("--density", default="sparse",
                   help="scene density preset (exact, sparse, dense) or a form-factor cut")
    p.add_argument("--terms", type=int, default=4)
    p.add_argument("--prune", type=float, default=1e-5)
    p.add_argument("--method", default="power,horner",
                   help="comma-separated: power, horner, newton-schulz (at --prune)")
    p.add_argument("--settings", default=None,
                   help="comma-separated method:prune[:prune_feed[:prune_operator]] "
                        "(instead of --method)")
    p.add_argument("--sample", type=int, default=None,
                   help="measure the error on this many random rows (default: all)")
    p.add_argument("--memory-limit", default=None)
    p.add_argument("--workdir", default=None)
    p.add_argument("--json", default=None)
    p.add_argument("--_child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--scene", default=None, help=argparse.SUPPRESS)
    p.add_argument("--setting", default=None, help=argparse.SUPPRESS)
    p.add_argument("--prune-feed", type=float, default=None, help=argparse.SUPPRESS)
    p.add_argument("--prune-operator", type=float, default=None, help=argparse.SUPPRESS)
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
        scene_text = f"built in {t_scene:.1f} s: " + sc.describe()
    else:
        scene_text = "reused: " + bigT.scenes.load(scene_path).describe()
    print(scene_text)
    settings = (args.settings.split(",") if args.settings
                else [f"{m}:{args.prune:g}" for m in args.method.split(",")])
    results = [run_setting(setting, scene_path, workdir, args) for setting in settings]
    print("\n| setting | total s | spectral radius s | terms s (residuals included) | multiply-adds | "
          "error vs F^-1(I-A) | nnz(X)/row | peak RSS GiB |")
    print("|---|---|---|---|---|---|---|---|")
    for setting, wall, rho_s, terms_s, madds, err, per_row, peak in map(setting_row, results):
        print(f"| {setting} | {wall:.1f} | {rho_s:.1f} | {terms_s:.1f} | {madds:.3g} | "
              f"{err:.2e} | {per_row:.0f} | {peak:.2f} |")
    record(results, args, scene_text)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1, default=str)


if __name__ == "__main__":
    main()
