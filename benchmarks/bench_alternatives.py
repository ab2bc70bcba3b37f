"""What a user would pick instead of bigT, side by side on the same matrices.

Reported, never asserted.

For each size, one synthetic corner scene (``bigT.scenes.corner(density="dense")``) and
one set of desired camera images (smooth, natural-ish test patterns in [0.1, 0.9], all
scaled by one gain so that the exact compensation F^-1 (I - A) d of the scene's ground
truth stays below 0.95, i.e. so that clipping the projector to [0, 1] does not set the
error floor). Every method runs in a fresh child process (its peak RSS is that
process's VmHWM) and compensates the same frames, l_in = clip(X l_desired, 0, 1):

* ``numpy.linalg.inv`` and ``numpy.linalg.pinv`` of the dense T, then X @ b per frame
  (only where the dense matrices fit in memory and the n^3 time predicted from the
  size before is within ``--setup-budget``);
* ``scipy.sparse.linalg.splu`` of T (SuperLU), then one solve per frame (batch 64: one
  solve with 64 right-hand sides);
* MKL PARDISO through ``pypardiso`` (factor once, then PARDISO's solve phase per frame,
  without iterative refinement, like splu; skipped with the reason when ``pypardiso``
  cannot be imported);
* per-frame GMRES (``scipy.sparse.linalg.gmres``, Jacobi preconditioner F^-1 = diag(T)^-1)
  with the tolerance that reaches the error of bigT's 4-term inverse (within 10 %) on the
  test frames;
* per-frame Jacobi iteration x <- x + F^-1 (b - T x) from x = F^-1 b (Bimber et al.
  2006, Bai et al. 2010; the paper's §2.1), with the fewest iterations that reach that
  error: k iterations from F^-1 b are T_k^-1 b, so this is bigT's matrix-free series on
  a scipy matrix in memory (scipy's sparse products run on one core);
* bigT matrix-free: the 4-term series applied with 4 passes over T streamed from its
  store (``Compensator`` on the matrix-free path, as ``bigT compensate --path
  matrix-free``);
* bigT explicit: ``bigT.stratified_inverse`` (4 terms, default prune), then X held in
  memory and applied per batch (``Compensator``, as ``bigT compensate`` does).

Measured per (size, method): setup (inversion or factorization; reading T from its
store into memory is not included and is printed apart), time per frame at batch 1 and
at batch 64, peak RSS, and the error ||T l_in - d|| / ||d|| over the first four frames
(computed by this process with ``bigT.relight`` for every method alike). The table
``alternatives`` and ``alternatives.png`` go to ``$BIGT_BENCH_OUT`` (default
``bench-out``) through ``_results.Results``; the winners per size (fastest per frame at
batch 1, at batch 64, and to the first compensated frame: reading T + setup + the first,
cold frame) are recorded as ``winner:<size>:<criterion>`` values, and the number of
frames from which bigT's explicit X, its inverse included, is the fastest of all as
``payback:<size>:<batch>``. Timings on a shared 2-core machine drift with its load:
compare within one run.

**Colour** (``--colour-sizes``): the colour Cornell box (``bigT.scenes`` with
``colour=True``, a global mixing rig, form-factor cut 1e-2) at small sizes, its desired
frames what the surfaces show lit directly by colour test patterns (``F l``: in every
pixel's gamut), scaled like the grey ones so the exact compensation stays below 0.95.
The rivals that take a colour T:

* ``splu`` and MKL PARDISO of the 3n x 3n system (T as stored: rows 3 p + camera
  channel, columns 3 q + projector primary);
* per-frame GMRES on the 3n system, block-Jacobi preconditioned (the inverse of each
  pixel's 3x3 diagonal block), to bigT's error like the grey GMRES;
* three grey ``splu`` with per-pixel un-mixing, for a global-mixing rig: T = (I x C) U
  (I x P) with the rig's recorded 3x3 camera C and projector P, U three grey bands, so
  T^-1 d = (I x P^-1) U^-1 (I x C^-1) d: setup un-mixes T and factors the three bands,
  every frame is un-mixed, solved three times and mixed back;
* bigT's colour inverse (4 terms, default prune) on its general path (3x3 blocks, every
  product over 3n x 3n) and on its global-mixing path (three grey inverses between two
  un-mixings), X held in memory (``Compensator``).

Same columns as the grey table, in the table ``alternatives-colour``; the error is the
same ||T l_in - d|| / ||d|| over the first four colour frames.

Run (2 cores shared: nice it)::

    nice -n 10 .venv/bin/python benchmarks/bench_alternatives.py --quick   # 48x64, 96x128
    nice -n 10 .venv/bin/python benchmarks/bench_alternatives.py           # up to 384x512
    nice -n 10 .venv/bin/python benchmarks/bench_alternatives.py --sizes "" --colour-sizes 48x64

``--workdir DIR`` keeps the scenes there (and reuses them on the next run); without it
everything is built in a temporary directory that is removed at the end.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import bigT  # noqa: E402
from _results import Results, run_name  # noqa: E402
from bench_compensate import _size, corner_scene, stratified  # noqa: E402
from bench_scale import peak_rss  # noqa: E402
from bigT.compensation import relative_error, relight  # noqa: E402
from bigT.storage.frames import to_frames, to_vectors  # noqa: E402

#: Method keys in table order, and the label each has in the table and the figure.
METHODS = {
    "inv": "numpy.linalg.inv (dense)",
    "pinv": "numpy.linalg.pinv (dense)",
    "splu": "scipy splu",
    "pardiso": "MKL PARDISO (pypardiso)",
    "gmres": "GMRES per frame (Jacobi prec.)",
    "jacobi": "Jacobi iteration per frame",
    "matrix-free": "bigT matrix-free (4 terms)",
    "explicit": "bigT explicit X (4 terms)",
}
#: The order the methods run in: bigT's inverse first, its error is the others' target.
RUN_ORDER = ("explicit", "matrix-free", "jacobi", "gmres", "splu", "pardiso", "inv", "pinv")
#: The colour Cornell box's methods (the module's docstring), in table order.
COLOUR_METHODS = {
    "splu-3n": "scipy splu of the 3n system",
    "pardiso-3n": "MKL PARDISO of the 3n system",
    "unmix-splu": "3 grey splu + per-pixel un-mixing",
    "gmres-3n": "GMRES per frame, 3n system (3x3 block-Jacobi prec.)",
    "colour-general": "bigT colour X, general path (4 terms)",
    "colour-global": "bigT colour X, global-mixing path (4 terms)",
}
#: bigT's general path first: its error is GMRES's target.
COLOUR_RUN_ORDER = ("colour-general", "colour-global", "gmres-3n", "splu-3n", "unmix-splu",
                    "pardiso-3n")
#: Every method's label, grey and colour.
LABELS = {**METHODS, **COLOUR_METHODS}
#: The colour scene's form-factor cut (the colour demo's and ``bench_colour --quick``'s:
#: a small Cornell box is nearly dense at the density presets' cuts).
COLOUR_FF_CUT = 1e-2
COLUMNS = ["size", "n", "method", "setup s", "frame s (batch 1)", "frame s (batch 64)",
           "peak MiB", "error"]
FRAMES = 64        # frames of the batch-64 timing
ERROR_FRAMES = 4   # the first frames: timed one by one (batch 1) and measured for error
TERMS = 4          # bigT's inverse and matrix-free series
#: GMRES and Jacobi stop at bigT's error times this ("the same error", within 10 %).
TARGET_SLACK = 1.1
#: pinv (an SVD) against inv at the same n, measured here: 9.5x at n = 1024, 21x at 2048.
PINV_OVER_INV = 10.0
MIB = float(1 << 20)


# --- records ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Job:
    """What a child process runs: one method on one scene (JSON on its command line)."""

    method: str
    scene: str
    frames: str
    out: str
    work: str
    target: float | None
    frame_budget: float


@dataclass(frozen=True)
class Measured:
    """What a child reports (seconds, bytes); ``detail`` says how the method ran and
    ``skipped64`` why batch 64 was not timed (None when it was)."""

    load_s: float
    setup_s: float
    first_s: float
    frame1_s: float
    frame64_s: float | None
    peak_bytes: int
    detail: str
    skipped64: str | None = None

    @property
    def to_first_frame(self) -> float:
        """Reading T + setup + the first (cold) frame: T on disk to one compensated frame."""
        return self.load_s + self.setup_s + self.first_s


@dataclass(frozen=True)
class Row:
    """One row of the table; ``measured`` is None for a method skipped at this size."""

    size: str
    n: int
    method: str
    measured: Measured | None
    error: float | None

    def cells(self) -> list:
        m = self.measured
        if m is None:
            return [self.size, self.n, LABELS[self.method], None, None, None, None, None]
        return [self.size, self.n, LABELS[self.method], m.setup_s, m.frame1_s, m.frame64_s,
                m.peak_bytes / MIB, self.error]


# --- desired images -----------------------------------------------------------------------

def _normalise(v: np.ndarray) -> np.ndarray:
    """``v`` mapped affinely onto [0.1, 0.9]."""
    return 0.1 + 0.8 * (v - v.min()) / max(float(np.ptp(v)), 1e-12)


def _texture(u, v, seed: int) -> np.ndarray:
    """A smooth random texture (a 6x8 grid of random values, bicubic), the same image
    at every resolution."""
    from scipy.interpolate import RectBivariateSpline

    grid = np.random.default_rng(seed).uniform(size=(6, 8))
    spline = RectBivariateSpline(np.linspace(0, 1, 6), np.linspace(0, 1, 8), grid)
    return spline(v[:, 0], u[0])


def test_pattern(size, k: int) -> np.ndarray:
    """Frame ``k`` of the desired video, (H, W) in [0.1, 0.9]: a gradient with a moving
    highlight, a grating, moving blobs or a texture (by k mod 4), drifting with k."""
    H, W = size
    v, u = np.mgrid[0:H, 0:W]
    u, v = (u + 0.5) / W, (v + 0.5) / H
    t = k / FRAMES
    kind = k % 4
    if kind == 0:
        img = u + 0.6 * np.exp(-((u - 0.3 - 0.4 * t) ** 2 + (v - 0.4) ** 2) / 0.02)
    elif kind == 1:
        img = np.sin(2 * np.pi * (3 * u + 2 * v + t)) * (0.6 + 0.4 * v)
    elif kind == 2:
        img = sum(np.exp(-((u - cx) ** 2 + (v - cy) ** 2) / 0.01)
                  for cx, cy in ((0.25 + t / 2, 0.3), (0.7, 0.6 - t / 3), (0.4, 0.8)))
    else:
        img = _texture(u, v, seed=k)
    return _normalise(img)


def desired_frames(scene) -> tuple[np.ndarray, float, float]:
    """(FRAMES, H, W) desired images, the gain applied to the [0.1, 0.9] patterns, and
    the share of pixels the exact compensation would clip even so (below 0)."""
    size = tuple(scene.summary["image_shape"])
    patterns = np.stack([test_pattern(size, k) for k in range(FRAMES)])
    order = scene.T.pixel_order
    B = to_vectors(patterns, order, np.float64)
    exact = (B - scene.A.matmul(B, order="matrix")) / scene.F_stored[:, None]  # F^-1 (I - A) d
    gain = min(1.0, 0.95 / float(exact.max()))
    return patterns * gain, gain, float(np.mean(exact < 0))


def desired_colour_frames(scene) -> tuple[np.ndarray, float, float]:
    """(FRAMES, H, W, 3) desired colour images: what the surfaces show lit directly
    (``F l``) by projector images whose channels are three of the grey test patterns,
    times the gain that keeps the exact compensation T^-1 d (splu, here) below 0.95;
    and that gain and the share of values the exact compensation would clip below 0."""
    from scipy.sparse.linalg import splu

    from bigT.cli.demo_cmd import direct_view  # the colour demo's targets

    size = tuple(scene.summary["image_shape"])
    light = np.stack([np.stack([test_pattern(size, k + c) for c in range(3)], -1)
                      for k in range(FRAMES)])
    frames = np.stack([direct_view(scene.F, f) for f in light])
    order = scene.T.pixel_order
    Ts = scene.T.to_scipy(output_order="matrix").astype(np.float64).tocsc()
    exact = splu(Ts).solve(to_vectors(frames, order, np.float64))
    gain = min(1.0, 0.95 / float(exact.max()))
    return frames * gain, gain, float(np.mean(exact < 0))


# --- the methods (in the child) -----------------------------------------------------------

def _load_T(store):
    """T from its store into memory: (scipy csr float64, seconds)."""
    t0 = time.perf_counter()
    Ts = store.to_scipy(output_order="matrix").astype(np.float64).tocsr()
    Ts.sort_indices()
    return Ts, time.perf_counter() - t0


def _framewise(apply, order):
    """(K, H, W) desired -> (K, H, W) clipped projector frames, through ``apply`` on
    (n, K) float64 batches in T's pixel order."""
    def compensate(frames):
        return to_frames(apply(to_vectors(frames, order, np.float64)), order, clip=(0, 1))
    return compensate


def _clipped_error(Ts, B, Y) -> float:
    """||T clip(Y) - B||_F / ||B||_F (the benchmark's error, in memory)."""
    return float(np.linalg.norm(Ts @ np.clip(Y, 0, 1) - B) / np.linalg.norm(B))


def setup_dense(Ts, order, pseudo: bool):
    """X = inv(T) or pinv(T) as a dense float64 array; apply X @ b."""
    dense = Ts.toarray()
    X = np.linalg.pinv(dense) if pseudo else np.linalg.inv(dense)
    del dense
    return _framewise(lambda B: X @ B, order), f"dense X {X.nbytes / MIB:.0f} MiB"


def setup_splu(Ts, order):
    """SuperLU of T (scipy defaults: COLAMD ordering); solve per batch."""
    from scipy.sparse.linalg import splu

    lu = splu(Ts.tocsc())
    return _framewise(lu.solve, order), f"nnz(L+U) = {lu.L.nnz + lu.U.nnz:,}"


def setup_pardiso(Ts, order):
    """PARDISO factorization (phases 11-22, MKL's defaults for a nonsymmetric matrix);
    per batch its solve phase 33, called directly: ``PyPardisoSolver.solve`` would first
    compare A with its stored copy (or hash it), an O(nnz(T)) cost per call that a
    per-frame loop need not pay. Iterative refinement is turned off after the
    factorization (iparm(8) = 0; MKL fills in 2 steps, and an iparm set before the
    first call is overwritten by the defaults): like splu, which does none; with it a
    frame took 10x longer at 48x64 for the same error, at rounding level either way."""
    import pypardiso

    solver = pypardiso.PyPardisoSolver()
    solver.factorize(Ts)
    solver.set_iparm(8, 0)

    def apply(B):
        solver.set_phase(33)
        return solver._call_pardiso(Ts, np.asfortranarray(B))  # noqa: SLF001

    return _framewise(apply, order), f"nnz(L+U) = {int(solver.get_iparm(18)):,}"


def _jacobi(Ts, finv, B, iterations: int):
    """``iterations`` Jacobi steps x <- x + F^-1 (b - T x) from x = F^-1 b."""
    X = finv * B
    for _ in range(iterations):
        X += finv * (B - Ts @ X)
    return X


def setup_jacobi(Ts, job, frames, order):
    """F^-1 = 1 / diag(T); the iterations that reach ``job.target`` on the test frames
    are found first (not timed: a user fixes them once)."""
    finv = (1.0 / Ts.diagonal())[:, None]
    B = to_vectors(frames[:ERROR_FRAMES], order, np.float64)
    X, k = finv * B, 0
    while _clipped_error(Ts, B, X) > job.target and k < 100:
        X += finv * (B - Ts @ X)
        k += 1
    return _framewise(lambda V: _jacobi(Ts, finv, V, k), order), f"{k} iterations"


def _gmres_batch(Ts, M, B, rtol, counts):
    """One GMRES solve per column of B (scipy's gmres takes one right-hand side)."""
    from scipy.sparse.linalg import gmres

    out = np.empty_like(B)
    for c in range(B.shape[1]):
        steps = []  # one callback per inner iteration
        out[:, c], _ = gmres(Ts, B[:, c], rtol=rtol, atol=0.0, M=M, restart=50, maxiter=20,
                             callback=steps.append, callback_type="pr_norm")
        counts.append(len(steps))
    return out


def setup_gmres(Ts, job, frames, order, M=None):
    """Jacobi preconditioner M = diag(T)^-1 (or ``M``: a colour T's block Jacobi); rtol
    starts at ``job.target`` and is halved until the test frames reach it (not timed)."""
    from scipy.sparse.linalg import LinearOperator

    if M is None:
        finv = 1.0 / Ts.diagonal()
        M = LinearOperator(Ts.shape, matvec=lambda x: finv * x.ravel(), dtype=np.float64)
    B = to_vectors(frames[:ERROR_FRAMES], order, np.float64)
    rtol, counts = job.target, []
    for _ in range(8):
        if _clipped_error(Ts, B, _gmres_batch(Ts, M, B, rtol, [])) <= job.target:
            break
        rtol /= 2
    compensate = _framewise(lambda V: _gmres_batch(Ts, M, V, rtol, counts), order)
    return compensate, (lambda: f"rtol {rtol:.2g}, {np.mean(counts):.1f} iterations/frame")


def block_jacobi(Ts):
    """The inverse of T's 3x3 diagonal blocks (one per pixel) as a sparse (3n, 3n)
    matrix: the colour first bounce F^-1, GMRES's preconditioner."""
    from scipy.sparse import bsr_array

    coo = Ts.tocoo()
    own = coo.row // 3 == coo.col // 3
    blocks = np.zeros((Ts.shape[0] // 3, 3, 3))
    np.add.at(blocks, (coo.row[own] // 3, coo.row[own] % 3, coo.col[own] % 3), coo.data[own])
    count = len(blocks)
    return bsr_array((np.linalg.inv(blocks), np.arange(count), np.arange(count + 1)),
                     shape=Ts.shape).tocsr()


def setup_unmix_splu(Ts, store, order):
    """Three grey splu between two per-pixel un-mixings, for a global-mixing rig:
    T = (I x C) U (I x P), C and P the 3x3 camera and projector mixing recorded with T,
    U the three grey bands (U[3p+k, 3q+k]); T^-1 = (I x P^-1) U^-1 (I x C^-1)."""
    from scipy.sparse import identity, kron
    from scipy.sparse.linalg import splu

    from bigT.algorithms.mixing import recorded_mixing

    mixing = recorded_mixing(store)
    n = Ts.shape[0] // 3
    c_inv, p_inv = np.linalg.inv(mixing.camera), np.linalg.inv(mixing.projector)
    U = (kron(identity(n), c_inv) @ Ts @ kron(identity(n), p_inv)).tocsr()
    bands = [U[k::3][:, k::3] for k in range(3)]
    cross = math.sqrt(max(sp_norm2(U) - sum(sp_norm2(b) for b in bands), 0.0) / sp_norm2(U))
    lus = [splu(b.tocsc()) for b in bands]

    def apply(B):  # (3n, K) in T's order: un-mix, three grey solves, mix back
        K = B.shape[1]
        V = np.einsum("ij,pjk->pik", c_inv, B.reshape(n, 3, K))
        Y = np.stack([lus[k].solve(np.ascontiguousarray(V[:, k])) for k in range(3)], 1)
        return np.einsum("ij,pjk->pik", p_inv, Y).reshape(3 * n, K)

    fill = sum(lu.L.nnz + lu.U.nnz for lu in lus)
    return _framewise(apply, order), (f"nnz(L+U) = {fill:,} over 3 bands; cross-channel "
                                      f"residue of U {cross:.1e} (dropped)")


def sp_norm2(M) -> float:
    """||M||_F^2 of a sparse matrix."""
    return float(np.sum(np.square(M.data)))


def setup_colour_bigT(store, job, path: str):
    """bigT's colour inverse on ``path`` ("general" or "global"), X held in memory."""
    from bigT.compensation import choose_path
    from bigT.compensation.realtime import Compensator

    out = os.path.join(job.work, "X.zarr")
    bigT.stratified_inverse(store, out, terms=TERMS, colour_path=path, overwrite=True,
                            progress=False)
    X = bigT.open(out)
    comp = Compensator(X, None, choose_path(X, None, None, "explicit"))
    return ((lambda frames: np.asarray(comp(frames), np.float64)),
            f"nnz(X) = {X.nnz:,}; {comp.residency.describe(1)}")


def setup_bigT(store, job, path: str):
    """bigT's :class:`Compensator` (what ``bigT compensate`` runs) on the explicit path
    (after ``stratified_inverse``: X held in memory) or the matrix-free path (T
    streamed with the default tile cache)."""
    from bigT.compensation import choose_path
    from bigT import config
    from bigT.compensation.core import first_bounce_diag
    from bigT.compensation.realtime import Compensator

    if path == "explicit":
        X, _ = stratified(store, os.path.join(job.work, "X.zarr"), TERMS)
        comp = Compensator(X, None, choose_path(X, None, None, "explicit"))
        detail = f"nnz(X) = {X.nnz:,}; {comp.residency.describe(1)}"
    else:
        first_bounce_diag(store)
        cache = config.COMPENSATE_CACHE_BYTES  # the tile cache of `bigT compensate`
        comp = Compensator(None, store, choose_path(None, store, TERMS, "matrix-free"),
                           cache_bytes=cache)
        detail = f"{TERMS} passes over T, tile cache {cache / MIB:.0f} MiB"
    return (lambda frames: np.asarray(comp(frames), np.float64)), detail


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def setup_method(job, store, frames):
    """(compensate, load seconds, setup seconds, detail) for ``job.method``."""
    if job.method in ("explicit", "matrix-free"):
        (comp, detail), setup = _timed(setup_bigT, store, job, job.method)
        return comp, 0.0, setup, detail
    if job.method in ("colour-general", "colour-global"):
        path = job.method.split("-", 1)[1]
        (comp, detail), setup = _timed(setup_colour_bigT, store, job, path)
        return comp, 0.0, setup, detail
    Ts, load = _load_T(store)
    order = store.pixel_order
    builders = {"inv": lambda: setup_dense(Ts, order, False),
                "pinv": lambda: setup_dense(Ts, order, True),
                "splu": lambda: setup_splu(Ts, order),
                "pardiso": lambda: setup_pardiso(Ts, order),
                "splu-3n": lambda: setup_splu(Ts, order),
                "pardiso-3n": lambda: setup_pardiso(Ts, order),
                "unmix-splu": lambda: setup_unmix_splu(Ts, store, order)}
    if job.method in builders:
        (comp, detail), setup = _timed(builders[job.method])
        return comp, load, setup, detail
    if job.method == "gmres-3n":  # setup: the 3x3 blocks inverted (timed); rtol search not
        M, setup = _timed(block_jacobi, Ts)
        comp, detail = setup_gmres(Ts, job, frames, order, M)
        return comp, load, setup, detail
    # the iterative ones: setup is F^-1 = 1 / diag(T) (timed); the tolerance search is not
    setup = _timed(Ts.diagonal)[1]
    search = setup_jacobi if job.method == "jacobi" else setup_gmres
    comp, detail = search(Ts, job, frames, order)
    return comp, load, setup, detail


def time_frames(comp, frames, budget: float, sequential: bool):
    """(first frame s, per-frame s at batch 1, per frame at batch 64 or None, why not,
    the ERROR_FRAMES outputs). Batch 1: each test frame on its own, repeated until
    0.5 s have been timed (median); batch 64: one call (the faster of two when the
    first took under a quarter of ``budget``), skipped for a ``sequential`` method (one
    solve per frame whatever the batch) when 64 batch-1 frames would take over
    ``budget`` seconds."""
    first_out, first = _timed(comp, frames[:1])
    outs, times = [first_out[0]] + [None] * (ERROR_FRAMES - 1), []
    while sum(times) < 0.5 and len(times) < 200:
        for i in range(ERROR_FRAMES):
            out, dt = _timed(comp, frames[i:i + 1])
            outs[i] = out[0]
            times.append(dt)
    per1 = statistics.median(times)
    if sequential and FRAMES * per1 > budget:
        why = (f"batch 64 not timed: 64 solves would take {FRAMES * per1:.0f} s, over "
               f"--frame-budget {budget:.0f} s (one solve per frame: batch 1's time per frame)")
        return first, per1, None, why, outs
    runs = [_timed(comp, frames)[1]]
    if 4 * runs[0] < budget:
        runs.append(_timed(comp, frames)[1])
    return first, per1, min(runs) / FRAMES, None, outs


def run_child(job: Job) -> Measured:
    """One method, start to end, in this (fresh) process; the test frames' outputs
    go to ``job.out``."""
    store = bigT.open(job.scene)
    frames = np.load(job.frames)
    comp, load, setup, detail = setup_method(job, store, frames)
    first, per1, per64, why, outs = time_frames(comp, frames, job.frame_budget,
                                                job.method in ("gmres", "gmres-3n"))
    np.save(job.out, np.stack(outs))
    detail = detail() if callable(detail) else detail
    return Measured(load, setup, first, per1, per64, peak_rss(), detail, why)


# --- the parent ---------------------------------------------------------------------------

def memory_limit() -> int:
    """Address space a child may take (a runaway factorization fails instead of
    swapping): 3/4 of the memory available now."""
    from bigT.schedule.memory import available_memory

    return int(0.75 * (available_memory() or 8 << 30))


def pardiso_missing() -> str | None:
    """Why pypardiso cannot run here, or None."""
    try:
        import pypardiso  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any import failure means unavailable
        return f"pypardiso cannot be imported ({type(exc).__name__}: {exc})"
    return None


@dataclass
class History:
    """What earlier sizes showed: the last setup time of each method at its n, and the
    methods that ran out of time or memory (not tried again at a larger n)."""

    setups: dict
    failed: dict


def dense_skip(method: str, n: int, history: History, args) -> str | None:
    """Why the dense inverse is not tried at this n (memory or predicted time)."""
    need = 3 * 8 * n * n  # T, its inverse and LAPACK's work arrays, float64
    if need > args.mem_limit:
        return (f"dense T is {8 * n * n / 2**30:.1f} GiB in float64 and {method} needs about "
                f"3 such arrays ({need / 2**30:.0f} GiB > {args.mem_limit / 2**30:.0f} GiB)")
    predicted, how = predicted_dense(method, n, history)
    if predicted is not None and predicted > args.setup_budget:
        return f"predicted {predicted:.0f} s ({how}), over --setup-budget {args.setup_budget:.0f} s"
    return None


def predicted_dense(method: str, n: int, history: History) -> tuple[float | None, str]:
    """Seconds the dense inverse should take at n, from its own time at a smaller n
    (times (n/n0)^3), else for pinv from inv's (times ``PINV_OVER_INV``)."""
    for source, factor in ((method, 1.0), ("inv", PINV_OVER_INV)):
        if source in history.setups:
            n0, s0 = history.setups[source]
            scale = f"{factor:g} x " if factor != 1 else ""
            return (factor * s0 * (n / n0) ** 3,
                    f"{scale}{source}'s {s0:.1f} s at n = {n0} times (n/{n0})^3")
    return None, ""


def skip_reason(method: str, n: int, history: History, target, args) -> str | None:
    """Why ``method`` is not run at this n, or None."""
    if method in history.failed:
        return history.failed[method]
    if method in ("pardiso", "pardiso-3n") and args.pardiso_missing:
        return args.pardiso_missing
    if method in ("gmres", "jacobi", "gmres-3n") and target is None:
        return "no error of bigT's inverse to match at this size"
    if method in ("inv", "pinv"):
        return dense_skip(method, n, history, args)
    return None


def launch(job: Job, args) -> tuple[Measured | None, str | None, bool]:
    """Run ``job`` in a child process: (what it measured, None, False), or (None, why
    not, whether a larger n would fail too: out of time or of memory)."""
    limit = (args.mem_limit if job.method not in ("explicit", "matrix-free", "colour-general",
                                                  "colour-global") else None)

    def cap():  # in the child, before exec: its address space only
        if limit:
            resource.setrlimit(resource.RLIMIT_AS, (limit, resource.RLIM_INFINITY))

    cmd = [sys.executable, str(Path(__file__).resolve()), "--_child", json.dumps(asdict(job))]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.child_timeout,
                              preexec_fn=cap)
    except subprocess.TimeoutExpired:
        return None, f"did not finish in {args.child_timeout:.0f} s (--child-timeout)", True
    if proc.returncode:
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        memory = proc.returncode < 0 or "MemoryError" in last
        return None, f"failed (exit {proc.returncode}: {last[:200]})", memory
    return Measured(**json.loads(proc.stdout.strip().splitlines()[-1])), None, False


def run_size(size, work: Path, history: History, res: Results, args) -> list[Row]:
    """Every method at one size: the table's rows (skips and failures noted in ``res``)."""
    H, W = size
    label, n = f"{H}x{W}", H * W
    t0 = time.perf_counter()
    scene = corner_scene(size, work / f"corner_{label}.zarr", args.density)
    print(f"\n[{label}] n = {n:,}: corner scene ({args.density}) ready in "
          f"{time.perf_counter() - t0:.1f} s; T {scene.T.nnz / n:.0f} nonzeros/row, "
          f"rho(M) {scene.spectral_radius:.3f}", flush=True)
    frames, gain, neg = desired_frames(scene)
    np.save(work / "desired.npy", frames)
    uncomp = relative_error(relight(scene.T, frames[:ERROR_FRAMES]), frames[:ERROR_FRAMES])
    res.value(f"uncompensated error:{label}", uncomp, "error with l_in = l_desired")
    res.value(f"gain:{label}", gain, "desired images = [0.1, 0.9] test patterns x gain")
    print(f"  desired: [0.1, 0.9] patterns x {gain:.3f}; the exact compensation is below 0 "
          f"on {100 * neg:.2f} % of pixels; uncompensated error {uncomp:.4f}")
    rows, target = {}, None
    for method in RUN_ORDER:
        rows[method] = run_method(method, scene, work, target, history, res, args)
        if method == "explicit" and rows[method].error is not None:
            target = TARGET_SLACK * rows[method].error
    return [rows[m] for m in METHODS]


def colour_scene(size, path: Path):
    """The colour Cornell box (global mixing, form factors cut at COLOUR_FF_CUT) at
    ``path``, reused when an earlier run left it there."""
    from bigT import scenes

    if not path.exists():
        scenes.build("cornell", size=size, path=path, density="sparse", ff_cut=COLOUR_FF_CUT,
                     colour=True, mixing="global", preview=False, progress=False)
    return scenes.load(path)


def run_colour_size(size, work: Path, history: History, res: Results, args) -> list[Row]:
    """The colour methods at one size (the module's docstring)."""
    H, W = size
    label = f"{H}x{W}"
    t0 = time.perf_counter()
    scene = colour_scene(size, work / f"cornell_colour_{label}_cut{COLOUR_FF_CUT:g}.zarr")
    n = H * W
    print(f"\n[colour {label}] n = {n:,} pixels, a {3 * n:,} x {3 * n:,} system: colour "
          f"Cornell box ready in {time.perf_counter() - t0:.1f} s; T "
          f"{scene.T.nnz / (3 * n):.0f} nonzeros/row", flush=True)
    frames, gain, neg = desired_colour_frames(scene)
    np.save(work / "desired.npy", frames)
    uncomp = relative_error(relight(scene.T, frames[:ERROR_FRAMES]), frames[:ERROR_FRAMES])
    res.value(f"colour uncompensated error:{label}", uncomp, "colour: error with l_in = "
              "l_desired")
    res.value(f"colour clipped:{label}", neg, "colour: share of the exact compensation's "
              "values below 0 (clipped by every method: an error floor for all)")
    print(f"  desired: direct views of colour test patterns x {gain:.3f}; the exact "
          f"compensation is below 0 on {100 * neg:.2f} % of values; uncompensated error "
          f"{uncomp:.4f}")
    rows, target = {}, None
    for method in COLOUR_RUN_ORDER:
        rows[method] = run_method(method, scene, work, target, history, res, args)
        if method == "colour-general" and rows[method].error is not None:
            target = TARGET_SLACK * rows[method].error
    return [rows[m] for m in COLOUR_METHODS]


def run_method(method, scene, work: Path, target, history: History, res: Results, args) -> Row:
    """One method at one size: skipped, failed or measured (and its error computed here,
    alike for every method, from the test frames' outputs)."""
    size = tuple(scene.summary["image_shape"])
    label, n = f"{size[0]}x{size[1]}", size[0] * size[1]
    why = skip_reason(method, n, history, target, args)
    measured = None
    if why is None:
        job = Job(method, str(scene.path), str(work / "desired.npy"),
                  str(work / f"out_{method}.npy"), str(work / f"child_{method}"), target,
                  args.frame_budget)
        measured, why = measure(job, label, history, args)
    if measured is None:
        res.note(f"{label}, {LABELS[method]}: skipped: {why}.")
        print(f"  {LABELS[method]:<32} skipped: {why}", flush=True)
        return Row(label, n, method, None, None)
    desired = np.load(work / "desired.npy")[:ERROR_FRAMES]
    error = relative_error(relight(scene.T, np.load(job.out)), desired)
    os.remove(job.out)
    history.setups[method] = (n, measured.setup_s)
    row = Row(label, n, method, measured, error)
    record_row(row, res)
    return row


def measure(job: Job, label: str, history: History, args) -> tuple[Measured | None, str | None]:
    """``job`` in a child process with its own scratch folder; a method out of time or
    memory is remembered in ``history``."""
    os.makedirs(job.work, exist_ok=True)
    measured, why, lasting = launch(job, args)
    shutil.rmtree(job.work, ignore_errors=True)
    if lasting:
        history.failed[job.method] = f"{why} at {label}"
    return measured, why


def record_row(row: Row, res: Results) -> None:
    """A measured row's notes and values into ``res``, and its line printed."""
    m, name = row.measured, LABELS[row.method]
    if m.skipped64:
        res.note(f"{row.size}, {name}: {m.skipped64}.")
    if row.method in ("gmres", "jacobi", "gmres-3n"):
        res.value(f"{row.method}:{row.size}", m.detail,
                  f"{name}: how it reached bigT's error (within 10 %) on the test frames")
    print(f"  {name:<32} setup {m.setup_s:8.3f} s  batch 1 {m.frame1_s:9.5f} s  batch 64 "
          f"{_fmt(m.frame64_s, '9.5f')} s/frame  peak {m.peak_bytes / MIB:6.0f} MiB  error "
          f"{row.error:.2e}  (read T {m.load_s:.2f} s, first frame {m.first_s:.3f} s; "
          f"{m.detail})", flush=True)


# --- output -------------------------------------------------------------------------------

def _fmt(x, spec: str = ".3g") -> str:
    return "–" if x is None else format(x, spec)


def markdown(rows: list[Row]) -> str:
    """The table as markdown (3 significant digits, '–' where skipped)."""
    specs = [None, None, None, ".3g", ".3g", ".3g", ".0f", ".2e"]
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        cells = [c if s is None else _fmt(c, s) for c, s in zip(r.cells(), specs)]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines)


CRITERIA = {
    "batch1": ("fastest per frame at batch 1", lambda m: m.frame1_s),
    "batch64": ("fastest per frame at batch 64", lambda m: m.frame64_s),
    "first-frame": ("fastest to the first compensated frame (reading T + setup + first frame)",
                    lambda m: m.to_first_frame),
}


def winners(rows: list[Row]) -> dict:
    """{(size, criterion): (method, seconds)} over the methods measured."""
    out = {}
    for size in dict.fromkeys(r.size for r in rows):
        for crit, (_, key) in CRITERIA.items():
            timed = [(key(r.measured), r.method) for r in rows
                     if r.size == size and r.measured is not None and key(r.measured) is not None]
            if timed:
                secs, method = min(timed)
                out[size, crit] = (method, secs)
    return out


def record_winners(wins: dict, res: Results) -> list[str]:
    """``winner:<size>:<criterion>`` values, and one sentence per size."""
    sentences = []
    for size in dict.fromkeys(s for s, _ in wins):
        parts = []
        for crit, (what, _) in CRITERIA.items():
            if (size, crit) in wins:
                method, secs = wins[size, crit]
                res.value(f"winner:{size}:{crit}", f"{METHODS[method]} ({secs:.3g} s)", what)
                parts.append(f"{what.split(' (')[0]}: {METHODS[method]} ({secs:.3g} s)")
        sentences.append(f"At {size}, " + "; ".join(parts) + ".")
    return sentences


def where_each_wins(wins: dict) -> list[str]:
    """One sentence per method: the (size, criterion) it wins, or that it wins none."""
    lines = []
    for method, label in METHODS.items():
        won = [f"{size} {crit}" for (size, crit), (m, _) in wins.items() if m == method]
        lines.append(f"{label} wins " + (", ".join(won) if won else "nothing here") + ".")
    return lines


def payback(rows: list[Row], size: str, attr: str) -> float | None:
    """Frames after which bigT's explicit X, setup included, has compensated them all
    sooner than every other method measured at ``size`` (per-frame time ``attr``;
    batch 1's where a method has no batch-64 time); None when some method stays ahead."""
    here = {r.method: r.measured for r in rows if r.size == size and r.measured is not None}
    ex = here.pop("explicit", None)
    if ex is None or getattr(ex, attr) is None:
        return None
    worst = 1.0
    for m in here.values():
        f_m, f_ex = getattr(m, attr) or m.frame1_s, getattr(ex, attr)
        lead = ex.to_first_frame - m.to_first_frame  # seconds the other is ahead at frame 1
        if lead > 0:
            if f_m <= f_ex:
                return None
            worst = max(worst, 1 + math.ceil(lead / (f_m - f_ex)))
    return worst


def payback_sentences(rows: list[Row], res: Results) -> list[str]:
    """One sentence per size: when bigT's explicit inverse pays back its setup (and
    ``payback:<size>:<batch>`` values)."""
    lines = []
    for size in dict.fromkeys(r.size for r in rows):
        k1, k64 = payback(rows, size, "frame1_s"), payback(rows, size, "frame64_s")
        for crit, k in (("batch1", k1), ("batch64", k64)):
            res.value(f"payback:{size}:{crit}", k, "frames from which bigT's explicit X, "
                      "inverse included, is the fastest of all (None: never)")
        if k1 is None and k64 is None:
            continue
        lines.append(f"At {size}, bigT's explicit X, its inverse included, is the fastest way "
                     f"to compensate {_from(k1, 'batch 1')} and {_from(k64, 'batch 64')}.")
    return lines


def _from(k, batch: str) -> str:
    """"1,713 frames or more at batch 64", or "at batch 1 never" (no frame count)."""
    return f"at {batch} never" if k is None else f"{k:,.0f} frames or more at {batch}"


def plot(rows: list[Row], path: Path) -> Path:
    """Log-log: time per frame (batch 1 solid, batch 64 dashed) and setup time against n,
    one colour per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 5.2))
    for i, (method, label) in enumerate(METHODS.items()):
        mine = [r for r in rows if r.method == method and r.measured is not None]
        if not mine:
            continue
        colour = f"C{i}"
        for attr, style in (("frame1_s", "-o"), ("frame64_s", "--s")):
            pts = [(r.n, getattr(r.measured, attr)) for r in mine
                   if getattr(r.measured, attr) is not None]
            if pts:
                ax1.loglog(*zip(*pts), style, color=colour, ms=4,
                           label=label if attr == "frame1_s" else None)
        pts = [(r.n, max(r.measured.setup_s, 1e-4)) for r in mine]
        ax2.loglog(*zip(*pts), "-o", color=colour, ms=4)
    ax1.set(xlabel="n (projector pixels)", ylabel="seconds per frame",
            title="time per frame: one at a time (solid), 64 at once (dashed)")
    ax2.set(xlabel="n (projector pixels)", ylabel="seconds, once",
            title="setup: the inverse or factorization, before any frame")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3, which="both")
    fig.legend(loc="lower center", bbox_to_anchor=(0.5, 0.04), ncol=4, fontsize=8,
               frameon=False)
    # the method names are the table's; what bigT's two differ in, said once
    fig.text(0.5, 0.01, "bigT explicit X: the inverse X computed once, then one product "
             "per frame; bigT matrix-free: no inverse stored, T's series applied to every "
             "frame", ha="center", fontsize=8, color="0.3")
    fig.suptitle("compensating a frame: bigT against the alternatives a user would pick, "
                 "dense wall-corner scenes (2 cores)", fontsize=10)
    fig.tight_layout(rect=(0, 0.13, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def report_colour(rows: list[Row], res: Results) -> None:
    """The colour table into ``res``, and printed."""
    if not rows:
        return
    res.table("alternatives-colour", "Colour: bigT's colour inverse against the rivals that "
              "take a colour T, per size", COLUMNS, [r.cells() for r in rows],
              note="The colour Cornell box (global mixing rig, form factors cut at "
                   f"{COLOUR_FF_CUT:g}); n counts pixels, the system is 3n x 3n; desired "
                   "frames: direct views of colour test patterns; error = ||T l_in - d|| / "
                   "||d|| over 4 frames, l_in clipped to [0, 1]; GMRES is tuned to reach the "
                   "error of bigT's general path; 3 grey splu: the rig's recorded mixing "
                   "un-mixed per pixel, one splu per colour band; empty = skipped (notes).")
    print("\ncolour:\n" + markdown(rows) + "\n")


def report(rows: list[Row], res: Results) -> None:
    """Table, figure, winners into ``res``; the markdown table and sentences printed."""
    if not rows:
        return
    res.table("alternatives", "bigT against the alternatives a user would pick, per size",
              COLUMNS, [r.cells() for r in rows],
              note="Same T (dense corner scene) and the same desired frames for every method; "
                   "setup excludes reading T from its store (bigT's inverse reads it itself); "
                   "error = ||T l_in - d|| / ||d|| over 4 frames, l_in clipped to [0, 1]; "
                   "GMRES and Jacobi are tuned to reach the error of bigT's 4-term inverse; "
                   "each method in a fresh process (peak = its VmHWM); empty = skipped (notes).")
    if rows:
        plot(rows, res.figure_path("alternatives.png"))
        res.figure("alternatives.png", "time per frame (batch 1 solid, batch 64 dashed) and "
                   "setup time against n, per method (log-log)")
    wins = winners(rows)
    print("\n" + markdown(rows) + "\n")
    lines = record_winners(wins, res) + payback_sentences(rows, res) + where_each_wins(wins)
    for line in lines:
        print(line)


# --- main ---------------------------------------------------------------------------------

def _sizes(text: str) -> list[tuple[int, int]]:
    """"48x64,96x128" -> [(48, 64), (96, 128)]; "" -> []."""
    return [_size(s) for s in text.split(",") if s.strip()]


def parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="48x64 and 96x128, small budgets")
    p.add_argument("--sizes", default=None,
                   help="comma-separated HxW (default 48x64,96x128,192x256,384x512; quick: "
                        "48x64,96x128)")
    p.add_argument("--colour-sizes", default=None,
                   help="comma-separated HxW of the colour Cornell box (default 48x64,96x128; "
                        "quick: 48x64; '' for none)")
    p.add_argument("--density", default="dense", help="corner scene density preset")
    p.add_argument("--workdir", default=None,
                   help="keep (and reuse) the scenes here; default: a temporary directory")
    p.add_argument("--setup-budget", type=float, default=None,
                   help="skip a dense inverse whose predicted time exceeds this (s; "
                        "default 150, quick 10)")
    p.add_argument("--frame-budget", type=float, default=None,
                   help="skip GMRES's batch 64 (64 solves) where it would exceed this (s; "
                        "default 60, quick 10)")
    p.add_argument("--child-timeout", type=float, default=None,
                   help="a method's whole run at one size (s; default 420, quick 60)")
    p.add_argument("--_child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    quick = args.quick
    grey = "48x64,96x128" if quick else "48x64,96x128,192x256,384x512"
    args.sizes = _sizes(grey if args.sizes is None else args.sizes)
    colour = "48x64" if quick else "48x64,96x128"
    args.colour_sizes = _sizes(colour if args.colour_sizes is None else args.colour_sizes)
    args.setup_budget = args.setup_budget or (10.0 if quick else 150.0)
    args.frame_budget = args.frame_budget or (10.0 if quick else 60.0)
    args.child_timeout = args.child_timeout or (60.0 if quick else 420.0)
    return args


def main(argv=None) -> None:
    args = parse(argv)
    if args._child:
        print(json.dumps(asdict(run_child(Job(**json.loads(args._child))))))
        return
    args.mem_limit = memory_limit()
    args.pardiso_missing = pardiso_missing()
    res = Results(run_name("alternatives"), "bigT against dense inverses, sparse LU, PARDISO and "
                  "per-frame iterations", " ".join(["bench_alternatives.py", *sys.argv[1:]]))
    from bigT.warm import warm

    print(f"numba kernels ready in {warm():.1f} s; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} CPUs; children limited to {args.mem_limit / 2**30:.1f} GiB")
    if args.pardiso_missing:
        res.note(f"MKL PARDISO: {args.pardiso_missing}.")
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_alternatives_"))
    work.mkdir(parents=True, exist_ok=True)
    rows, colour_rows, history = [], [], History({}, {})
    try:
        for size in args.sizes:
            rows += run_size(size, work, history, res, args)
        for size in args.colour_sizes:
            colour_rows += run_colour_size(size, work, history, res, args)
    finally:
        report(rows, res)
        report_colour(colour_rows, res)
        print(f"results -> {res.save()}")
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)
        else:
            (work / "desired.npy").unlink(missing_ok=True)


if __name__ == "__main__":
    main()
