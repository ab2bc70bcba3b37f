"""Numerical stability of the stratified inverse (reported, never asserted; the
assertions are in tests/stability/).

Six sweeps, each printed as a markdown table (and written to ``--out``/tables.md with
the raw numbers in results.json):

1. rho(M) from 0.1 to 1.05 (T = (I + N) F, rho(N) set by construction; above 256
   pixels the engine estimates rho with Arnoldi): the estimate and its uncertainty
   against the true rho, the error after each term against the exact inverse (dense
   numpy) next to rho^(k+1), the fitted rate, refused or not; plus issue 17's
   reproducer (2000 x 2000, a crowded spectrum topped at 1.02 and 1.05).
2. ``tol`` on a slow series (rho = 0.99): where the run stops, where the true residual
   crosses tol, and the residual estimate against the truth there.
3. Noisy transport (noise, a noise floor, negative entries left by black-level
   subtraction): inverse error, compensation error, refusals, against the noise.
4. T scaled by 1e-30 .. 1e30 (float64, float32): X(cT) c against X(T).
5. float32 against float64 term by term, in float32 ulps times cond(T).
6. Near-singular T: refused or run, and the reported residual against the truth.

The matrices are built by tests/stability/stability_helpers.py, so the tables show the
cases the tests check, at larger sizes.

Run:  nice -n 10 .venv/bin/python benchmarks/bench_stability.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "stability"))

import bigT  # noqa: E402
from bigT.testing import clustered_spectrum  # noqa: E402
from stability_helpers import (  # noqa: E402
    UNIT,
    bipartite_matrix,
    first_bounce,
    fitted_rate,
    invert,
    measured_transport,
    perron_matrix,
    power_form,
    read_dense,
    relative_error,
    relative_residual,
    scratch_dir,
    spectral_radius,
    term_by_term,
    transport,
    write_store,
)


# --- output ------------------------------------------------------------------------------

def table(title, header, rows):
    """A markdown table with a bold title line."""
    lines = [f"**{title}**", "", "| " + " | ".join(header) + " |",
             "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def refusal_estimate(message):
    """The 'rho +- uncertainty' a DivergenceError message states."""
    m = re.search(r"is (\S+ \+- \S+)", message)
    return m.group(1).replace("+-", "±") if m else "?"


def refusal_text(err):
    """What a refusal said: the estimate of a DivergenceError, else the error's class
    and the first clause of its message."""
    if isinstance(err, bigT.DivergenceError):
        return f"DivergenceError, {refusal_estimate(str(err))}"
    return f"{type(err).__name__}, {err.problem.split(';')[0]}"


def rho_of(T):
    """The true rho(I - T diag(T)^-1), dense (inf for a zero diagonal entry)."""
    d = np.diag(T)
    if not d.all():
        return float("inf")
    return spectral_radius(np.eye(len(d)) - T / d[None, :])


# --- 1. the rho sweep ------------------------------------------------------------------

def sweep_one(work, T, terms, tile_size):
    """Term by term, or the refusal: a dict for the tables."""
    store = write_store(T, work / "T.zarr", tile_size=tile_size)
    t0 = time.perf_counter()
    try:
        reports, Xs = term_by_term(store, work / "X.zarr", terms)
    except bigT.DivergenceError as e:
        return {"refused": True, "estimate": refusal_estimate(str(e)),
                "seconds": time.perf_counter() - t0}
    exact = np.linalg.inv(T)
    errors = [relative_error(X, exact) for X in Xs]
    rep = reports[-1]
    return {"refused": False, "estimate": f"{rep.spectral_radius:.6f} ± "
            f"{rep.spectral_uncertainty:.1e}", "errors": errors,
            "seconds": time.perf_counter() - t0, "estimate_seconds": rep.seconds_spectral_radius}


def rho_sweep(args):
    rhos = [0.1, 0.5, 0.9, 0.99, 1.02, 1.05]
    n, tile = (24, 16) if args.quick else (400, 128)
    results = {}
    for rho in rhos:
        with scratch_dir() as work:
            N = perron_matrix(n, rho, 2, density=1.0 if args.quick else 0.02)
            results[rho] = sweep_one(work, transport(N, first_bounce(n, 2)), args.terms, tile)
    seeds = range(1) if args.quick else range(6)
    for top in (1.02, 1.05):
        for seed in seeds:
            N, _ = clustered_spectrum(seed, top)
            with scratch_dir() as work:
                r = sweep_one(work, np.eye(N.shape[0]) + N.toarray(), 4, 512)
            results[f"crowded {top} seed {seed}"] = r
    return results, n


def shown_terms(terms):
    """The terms a per-term table shows: the first four, then every fourth."""
    return [k for k in range(terms + 1) if k <= 3 or k % 4 == 0 or k == terms]


def crowded_rows(results):
    """One row per top radius of issue 17's reproducer: how many seeds were refused,
    and the range of the estimates' uncertainties."""
    rows = []
    for top in (1.02, 1.05):
        runs = [r for key, r in results.items() if str(key).startswith(f"crowded {top} ")]
        refused = [r for r in runs if r["refused"]]
        values = sorted({r["estimate"].split(" ± ")[0] for r in refused})
        uncs = [float(r["estimate"].split(" ± ")[1]) for r in refused if " ± " in r["estimate"]]
        rows.append([f"{top} (crowded, {len(runs)} seeds)", 2000,
                     f"{'/'.join(values)} ± ≤{max(uncs, default=float('nan')):.1e}", 0, "-",
                     "-", f"**refused {len(refused)}/{len(runs)}**"])
    return rows


def rho_tables(results, n, terms):
    rows = []
    for rho, r in results.items():
        if not isinstance(rho, float):
            continue
        label, size = f"{rho}", n
        if r["refused"]:
            rows.append([label, size, r["estimate"], 0, "-", "-", "**refused**"])
            continue
        e = r["errors"]
        tail = [x for x in e[min(6, len(e) // 2):] if x > 1e-12]
        rows.append([label, size, r["estimate"], len(e) - 1, f"{e[0]:.2e} → {e[-1]:.2e}",
                     f"{fitted_rate(tail):.4f}" if len(tail) >= 3 else "-", "no"])
    rows += crowded_rows(results)
    out = table(f"1a. spectral radius sweep ({terms} terms; rate fitted from term "
                f"{min(6, terms // 2)} on, errors above 1e-12)",
                ["ρ true", "n", "ρ estimated ± uncertainty", "terms", "error term 0 → last",
                 "fitted rate", "refused"], rows)
    kept = [(rho, r) for rho, r in results.items() if isinstance(rho, float) and not r["refused"]]
    head = ["k"] + [h for rho, _ in kept for h in (f"error, ρ = {rho}", f"{rho}^(k+1)")]
    rows = [[k] + [c for rho, r in kept for c in (f"{r['errors'][k]:.2e}",
                                                  f"{rho ** (k + 1):.2e}")]
            for k in shown_terms(terms)]
    return out + "\n" + table("1b. relative error ||X_k - T^-1||_F / ||T^-1||_F per term "
                              "against ρ^(k+1)", head, rows)


# --- 2. tol ----------------------------------------------------------------------------

def tol_sweep(args):
    n, rho = 24, 0.99
    T = transport(perron_matrix(n, rho, 3), first_bounce(n, 3))
    truth = [relative_residual(T, power_form(T, k)) for k in range(400)]
    rows = []
    for target in ([40] if args.quick else [20, 60, 150]):
        tau = truth[target]
        with scratch_dir() as work:
            rep = invert(write_store(T, work / "T.zarr"), work / "X.zarr", 1000, tol=tau)
            true = relative_residual(T, read_dense(work / "X.zarr"))
        rows.append([f"{tau:.3e}", target, rep.terms, rep.stopped, f"{rep.residual:.3e}",
                     f"{true:.3e}", f"{true / rep.residual:.2f}"])
    return table("2. tol on a slow series (ρ = 0.99, n = 24, 4 probes)",
                 ["tol", "first term truly under tol", "stopped at term", "why",
                  "estimate there", "true residual there", "true / estimate"], rows)


# --- 3. noise --------------------------------------------------------------------------

def noise_sweep(args):
    H, W = (6, 6) if args.quick else (16, 16)
    n = H * W
    T = transport(perron_matrix(n, 0.6, 5, density=0.3), first_bounce(n, 5))
    G = np.random.default_rng(6).standard_normal((n, n))
    yy, xx = np.mgrid[0:H, 0:W]
    desired = 0.3 + 0.2 * np.sin(xx / 2.0) * np.cos(yy / 3.0)
    exact = np.linalg.inv(T)
    rows = []
    for sigma in [0.0, 1e-4, 1e-3, 1e-2, 3e-2, 0.1, 0.2, 0.3]:
        Tm = measured_transport(T, G, sigma)
        neg = f"{100 * (Tm < 0).mean():.1f}"
        with scratch_dir() as work:
            try:
                rep = invert(write_store(Tm, work / "T.zarr", image_shape=(H, W), tile_size=512),
                             work / "X.zarr", args.terms)
            except bigT.BigTError as e:
                rows.append([sigma, neg, f"{rho_of(Tm):.3f}", refusal_text(e),
                             "**refused**", "-", "-", "-", "-"])
                continue
            X = read_dense(work / "X.zarr")
            light = bigT.compensate(work / "X.zarr", desired, clip=None)
            clipped = bigT.compensate(work / "X.zarr", desired)
        d = desired.ravel()
        err = np.linalg.norm(T @ light.ravel() - d) / np.linalg.norm(d)
        ideal = np.linalg.norm(T @ np.linalg.solve(Tm, d) - d) / np.linalg.norm(d)
        edge = 100 * ((clipped <= 0) | (clipped >= 1)).mean()
        rows.append([sigma, neg, f"{rho_of(Tm):.3f}", f"{rep.spectral_radius:.3f}", "no",
                     f"{relative_error(X, exact):.2e}", f"{err:.2e}", f"{ideal:.2e}",
                     f"{edge:.0f}"])
    return table(f"3. noisy transport ({H}x{W} pixels, ρ = 0.6, {args.terms} terms; noise σ "
                 "relative to the mean first bounce, floor 2σ)",
                 ["σ", "negative entries %", "ρ(M~) true", "ρ estimated", "refused",
                  "‖X~ − T⁻¹‖/‖T⁻¹‖", "compensation error", "same with exact T~⁻¹",
                  "clipped %"], rows)


# --- 4. scaling ------------------------------------------------------------------------

def scaling_sweep(args):
    T = transport(perron_matrix(24, 0.5, 9), first_bounce(24, 9))
    kappa = np.linalg.cond(T)
    exps = [-30, 0, 30] if args.quick else list(range(-30, 31, 10))
    rows = []
    for dtype in ("float64", "float32"):
        with scratch_dir() as work:
            base = {}
            for e in exps:
                c = 10.0**e
                rep = invert(write_store(T * c, work / f"T{e}.zarr", dtype=dtype),
                             work / f"X{e}.zarr", 4, prune=1e-6)
                base[e] = (read_dense(work / f"X{e}.zarr").astype(np.float64) * c, rep)
        X0, rep0 = base[0]
        for e in exps:
            Xc, rep = base[e]
            dev = np.abs(Xc - X0).max() / np.abs(X0).max()
            rows.append([f"1e{e:+d}", dtype, f"{dev:.1e}", f"{dev / (UNIT[dtype] * kappa):.2f}",
                         bool(np.array_equal(Xc != 0, X0 != 0)), f"{rep.spectral_radius:.9f}",
                         f"{rep.residual:.6e}"])
    return table(f"4. T scaled by c: max|c X(cT) − X(T)| / max|X(T)| (4 terms, prune 1e-6, "
                 f"cond(T) = {kappa:.1f})",
                 ["c", "dtype", "deviation", "in u·cond", "same nonzeros", "ρ estimated",
                  "residual"], rows)


# --- 5. float32 against float64 ----------------------------------------------------------

def precision_sweep(args):
    out = []
    for label, N in (("Perron, ρ = 0.5", perron_matrix(24, 0.5, 3)),
                     ("±ρ pair, ρ = 0.9", bipartite_matrix(24, 0.9, 3))):
        T = transport(N, first_bounce(24, 3))
        kappa = np.linalg.cond(T)
        exact = np.linalg.inv(T)
        per = {}
        for dtype in ("float64", "float32"):
            with scratch_dir() as work:
                _, Xs = term_by_term(write_store(T, work / "T.zarr", dtype=dtype),
                                     work / "X.zarr", args.terms)
            per[dtype] = [X.astype(np.float64) for X in Xs]
        rows = []
        for k in shown_terms(args.terms):
            a, b = per["float32"][k], per["float64"][k]
            diff = relative_error(a, b)
            rows.append([k, f"{relative_error(b, exact):.2e}", f"{relative_error(a, exact):.2e}",
                         f"{diff:.2e}", f"{diff / (UNIT['float32'] * kappa):.3f}"])
        out.append(table(f"5. float32 against float64 per term ({label}, cond(T) = {kappa:.1f})",
                         ["k", "error float64", "error float32", "‖X32 − X64‖/‖X64‖",
                          "in u32·cond"], rows))
    return "\n".join(out)


# --- 6. near-singular ------------------------------------------------------------------

def near_singular_cases():
    f = first_bounce(24, 11)
    base = transport(perron_matrix(24, 0.5, 11), f)
    tiny = base.copy()
    tiny[[4, 17], [4, 17]] = 1e-8
    dim = np.ones(24)
    dim[[2, 11, 19]] = 1e-6
    zero = base.copy()
    zero[7, 7] = 0.0
    return [
        ("ρ = 0.999 (Perron)", transport(perron_matrix(24, 0.999, 11), f)),
        ("ρ = 0.999 (±ρ pair, T near singular)", transport(bipartite_matrix(24, 0.999, 11), f)),
        ("ρ = 1 − 1e-9 (±ρ pair, cond ~1e9)", transport(bipartite_matrix(24, 1 - 1e-9, 11), f)),
        ("ρ = 1 − 1e-15 (Perron)", transport(perron_matrix(24, 1 - 1e-15, 11), f)),
        ("3 dim pixels (row, column × 1e-6)", dim[:, None] * base * dim[None, :]),
        ("T_ii = 1e-8 under bright neighbours", tiny),
        ("T_77 = 0 (lit pixel)", zero),
    ]


def near_singular_sweep(args):
    rows = []
    for label, T in near_singular_cases():
        with scratch_dir() as work:
            try:
                rep = invert(write_store(T, work / "T.zarr"), work / "X.zarr", args.terms)
            except bigT.BigTError as e:
                rows.append([label, f"{np.linalg.cond(T):.1e}", f"{rho_of(T):.6g}",
                             f"**refused**: {refusal_text(e)}", "-", "-"])
                continue
            true = relative_residual(T, read_dense(work / "X.zarr"))
        rows.append([label, f"{np.linalg.cond(T):.1e}", f"{rho_of(T):.10g}",
                     f"ran, ρ {rep.spectral_radius:.10g} ± {rep.spectral_uncertainty:.1e}",
                     f"{rep.residual:.3e}", f"{true:.3e}"])
    return table(f"6. near-singular T (n = 24, {args.terms} terms)",
                 ["case", "cond(T)", "ρ true", "outcome", "residual reported",
                  "true residual"], rows)


# --- main ------------------------------------------------------------------------------

def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="small sizes (about a minute)")
    p.add_argument("--terms", type=int, default=None,
                   help="terms of the sweeps (default 8 quick, 20 full)")
    p.add_argument("--out", default=str(ROOT / "bench-out" / "stability"))
    args = p.parse_args(argv)
    args.terms = args.terms or (8 if args.quick else 20)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    t0 = time.perf_counter()
    rho_results, n = rho_sweep(args)
    sections = [rho_tables(rho_results, n, args.terms), tol_sweep(args), noise_sweep(args),
                scaling_sweep(args), precision_sweep(args), near_singular_sweep(args)]
    text = "\n".join(sections)
    print(text)
    print(f"total {time.perf_counter() - t0:.0f} s")
    (out / "tables.md").write_text(text)
    (out / "results.json").write_text(json.dumps(
        {str(k): v for k, v in rho_results.items()}, indent=1, default=str))
    print(f"tables -> {out / 'tables.md'}")


if __name__ == "__main__":
    main()
