"""The stratified inverse of a colour transport (3 channels, index 3 p + c), against
dense numpy: F = T's 3x3 diagonal blocks (each pixel's colour mixing), inverted per
pixel; every method, tile-major order, resume, the target error, recovery of F, the
refusal (or leaving out) of an ill-conditioned pixel, the spectral radius estimator."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.algorithms import (invert_to_target, recover_first_bounce, resolve_first_bounce,
                             stratified_inverse)
from bigT.algorithms.run_setup import choose_tile_size
from bigT.errors import InvalidMatrixError, ShapeMismatchError
from bigT.schedule import worker

#: Camera sensitivities (rows: R, G, B sensor; columns: bands) and projector primaries
#: (rows: bands; columns: R, G, B primary), with the cross-talk of real devices.
CAMERA = np.array([[0.80, 0.15, 0.05], [0.10, 0.80, 0.10], [0.05, 0.20, 0.75]])
PROJECTOR = np.array([[0.90, 0.10, 0.00], [0.08, 0.85, 0.07], [0.02, 0.10, 0.88]])


def colour_transport(H, W, seed=0, per_pixel=True, density=0.1, gain=0.6):
    """A physical-ish colour transport, dense (3n, 3n): for each band k a grey
    T_k = (I - diag(albedo_k) K)^-1 diag(emission_k) from one random nonnegative K of
    spectral radius < 1, mixed by the camera C (per pixel C_p when ``per_pixel``) and
    the projector P: A[3p+i, 3q+j] = sum_k C_p[i, k] T_k[p, q] P[k, j]."""
    rng = np.random.default_rng(seed)
    n = H * W
    K = sp.random(n, n, density=density, random_state=rng).toarray()
    np.fill_diagonal(K, 0)
    K *= gain / max(K.sum(0).max(), K.sum(1).max())
    C = np.broadcast_to(CAMERA, (n, 3, 3))
    if per_pixel:
        C = C * (1 + 0.1 * rng.standard_normal((n, 3, 3))).clip(0.5)
    A = np.zeros((3 * n, 3 * n))
    for k in range(3):
        albedo = 0.3 + 0.6 * rng.random(n)
        Tk = np.linalg.inv(np.eye(n) - albedo[:, None] * K) * (0.5 + rng.random(n))
        A += np.einsum("pi,pq,j->piqj", C[:, :, k], Tk, PROJECTOR[k]).reshape(3 * n, 3 * n)
    return A


def blocks_of(A, b=3):
    """The b x b diagonal blocks of a dense A, (n/b, b, b)."""
    m = A.shape[0] // b
    return np.stack([A[b * p:b * p + b, b * p:b * p + b] for p in range(m)])


def block_diag(blocks):
    return sp.block_diag(list(blocks)).toarray()


def dense_colour_stratified(A, terms, skip=()):
    """Eq. 13 with F = blockdiag(A): F^-1 sum_{k<=terms} (I - A F^-1)^k (pixels in
    ``skip`` left out: zero blocks of F^-1, zero rows of D)."""
    Finv = blocks_of(A).copy()
    keep = np.ones(len(Finv), bool)
    keep[list(skip)] = False
    Finv[keep] = np.linalg.inv(Finv[keep])
    Finv[~keep] = 0
    Finv = block_diag(Finv)
    D = np.diag(np.repeat(keep, 3).astype(float))
    M = D - D @ A @ Finv
    S, P = np.zeros_like(A), np.eye(len(A))
    for _ in range(terms + 1):
        S += D @ P
        P = M @ P
    return Finv @ S


def store(tmp_path, A, shape, name="T.zarr", order="tile-major", tile_size=24,
          dtype="float64"):
    return bigT.from_scipy(sp.csr_array(A), tmp_path / name, image_shape=shape, channels=3,
                           tile_size=tile_size, pixel_order=order, image_tile=(2, 2),
                           dtype=dtype)


def read(path, order="row-major"):
    return bigT.open(path).to_scipy(output_order=order).toarray()


@pytest.fixture(scope="module")
def scene():
    """A 6 x 8 colour transport with per-pixel camera mixing (144 x 144)."""
    return colour_transport(6, 8)


# horner's 18 terms and newton-schulz's 31 run with make test-all (~13 s): the default
# suite checks each method's terms against eq. 13 exactly in
# test_each_term_is_eq13_with_block_diagonal_F, and the series' limit with power here
@pytest.mark.parametrize("method,terms", [
    ("power", 18), pytest.param("horner", 18, marks=pytest.mark.slow),
    pytest.param("newton-schulz", 31, marks=pytest.mark.slow)])
def test_unpruned_series_reaches_the_exact_inverse(tmp_path, scene, method, terms):
    T = store(tmp_path, scene, (6, 8))
    rep = stratified_inverse(T, tmp_path / "X.zarr", terms=terms, prune=0, method=method,
                             progress=False)
    assert rep.terms == terms
    exact = np.linalg.inv(scene)
    np.testing.assert_allclose(read(tmp_path / "X.zarr"), exact, rtol=0,
                               atol=1e-12 * np.abs(exact).max())


@pytest.mark.parametrize("order", ["row-major", "tile-major"])
def test_term_zero_is_the_per_pixel_inverse(tmp_path, scene, order):
    T = store(tmp_path, scene, (6, 8), order=order)
    stratified_inverse(T, tmp_path / "X.zarr", terms=0, progress=False)
    want = block_diag(np.linalg.inv(blocks_of(scene)))
    np.testing.assert_array_equal(read(tmp_path / "X.zarr"), want)


@pytest.mark.parametrize("method", ["power", "horner", "newton-schulz"])
def test_each_term_is_eq13_with_block_diagonal_F(tmp_path, scene, method):
    T = store(tmp_path, scene, (6, 8))
    terms = 3
    stratified_inverse(T, tmp_path / "X.zarr", terms=terms, prune=0, method=method,
                       progress=False)
    np.testing.assert_allclose(read(tmp_path / "X.zarr"),
                               dense_colour_stratified(scene, terms), atol=1e-12)


def test_pruned_series_stays_close(tmp_path, scene):
    T = store(tmp_path, scene, (6, 8), dtype="float32")
    rep = stratified_inverse(T, tmp_path / "X.zarr", terms=6, prune=1e-4,
                             prune_feed=1e-3, prune_operator=1e-4, progress=False)
    err = np.abs(read(tmp_path / "X.zarr") - dense_colour_stratified(scene, 6)).max()
    assert err < 2e-2 * np.abs(np.linalg.inv(scene)).max()
    assert rep.residual < 0.05


def _colour_m(A):
    """M = I - A F^-1, F = A's diagonal blocks, its diagonal blocks exactly 0."""
    Finv = block_diag(np.linalg.inv(blocks_of(A)))
    M = np.eye(len(A)) - A @ Finv
    return M - block_diag(blocks_of(M))


def test_spectral_radius_is_the_abs_bound_and_says_its_estimator(tmp_path):
    """M = I - T F^-1 has positive entries (F^-1 has negative ones): the plain
    Collatz-Wielandt bracket does not apply; the engine takes the cheap rigorous upper
    bound rho(M) <= rho(|M|) (300 unknowns, above the dense limit): at least the dense
    eigenvalues' largest modulus, within 2 % of rho(|M|), which is itself within 15 % of
    rho(M) here (the bands' albedos differ and the camera's mixing varies 10 % from
    pixel to pixel: signs cancel in M that |M| adds)."""
    A = colour_transport(10, 10, seed=3, density=0.05)
    M = _colour_m(A)
    assert M.max() > 0
    rho = np.abs(np.linalg.eigvals(M)).max()
    bound = np.abs(np.linalg.eigvals(np.abs(M))).max()
    T = store(tmp_path, A, (10, 10), tile_size=60)
    rep = stratified_inverse(T, tmp_path / "X.zarr", terms=1, progress=False)
    assert rep.spectral_method == "collatz-wielandt-abs"
    upper = rep.spectral_radius + rep.spectral_uncertainty
    assert rho <= upper <= 1.02 * bound and bound <= 1.15 * rho
    assert rep.spectral_radius - rep.spectral_uncertainty <= bound <= upper
    assert "rho(M) <= rho(|M|)" in rep.table() and "at most" in rep.table()


def test_spectral_radius_near_one_is_arnoldis(tmp_path, monkeypatch):
    """A bound too near 1 to be worth reporting (here: any bound, the threshold set to
    0) hands over to ARPACK, within its uncertainty of the dense eigenvalues."""
    from bigT import config

    monkeypatch.setattr(config, "SPECTRAL_RADIUS_ABS_ACCEPT", 0.0)
    A = colour_transport(10, 10, seed=3, density=0.05)
    rho = np.abs(np.linalg.eigvals(_colour_m(A))).max()
    T = store(tmp_path, A, (10, 10), tile_size=60)
    rep = stratified_inverse(T, tmp_path / "X.zarr", terms=1, progress=False)
    assert rep.spectral_method == "arnoldi"
    assert abs(rep.spectral_radius - rho) <= max(rep.spectral_uncertainty, 1e-9)
    assert "ARPACK" in rep.table()


def test_crash_mid_term_then_resume(tmp_path, scene, monkeypatch):
    T = store(tmp_path, scene, (6, 8))  # 6 tile rows of 24 values
    ref = tmp_path / "ref.zarr"
    stratified_inverse(T, ref, terms=3, prune=1e-8, progress=False)
    out = tmp_path / "X.zarr"
    calls = {"n": 0}

    class Crash(Exception):
        pass

    def hook(op, i):
        if op == "power":
            calls["n"] += 1
            if calls["n"] == 6 + 4:  # term 1 passes; the 4th row block of term 2 fails
                raise Crash

    monkeypatch.setattr(worker, "task_hook", hook)
    with pytest.raises(Crash):
        stratified_inverse(T, out, terms=3, prune=1e-8, progress=False)
    monkeypatch.setattr(worker, "task_hook", None)
    assert bigT.open(out).metadata["inverse"]["term"] == 1
    done = []
    monkeypatch.setattr(worker, "task_hook", lambda op, i: done.append(op))
    rep = stratified_inverse(T, out, terms=3, prune=1e-8, progress=False)
    monkeypatch.setattr(worker, "task_hook", None)
    assert rep.resumed_from == 1 and rep.terms == 3
    assert done.count("power") < 12  # the rows finished before the crash were kept
    np.testing.assert_array_equal(read(out), read(ref))


def test_target_error_is_met_on_colour_images(tmp_path, scene):
    T = store(tmp_path, scene, (6, 8), dtype="float32")
    target = 1e-3
    rep = invert_to_target(T, tmp_path / "X.zarr", target, progress=False)
    assert rep.met
    X = read(tmp_path / "X.zarr")
    rng = np.random.default_rng(1)
    for _ in range(3):  # fresh colour images, row-major (H, W, 3) raveled
        d = rng.uniform(0.2, 0.8, 6 * 8 * 3)
        assert np.linalg.norm(d - scene @ (X @ d)) / np.linalg.norm(d) <= target


@pytest.mark.parametrize("order", ["row-major", "tile-major"])
def test_recover_first_bounce_inverts_the_diagonal_blocks(tmp_path, scene, order):
    T = store(tmp_path, scene, (6, 8), order=order)
    stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0, progress=False)
    X = read(tmp_path / "X.zarr")
    F = recover_first_bounce(tmp_path / "X.zarr")
    assert F.shape == (48, 3, 3)
    np.testing.assert_allclose(F, np.linalg.inv(blocks_of(X)), rtol=1e-12)
    # in the stored order, as the engine and bounce separation use it
    stored = recover_first_bounce(tmp_path / "X.zarr", output_order="matrix")
    perm = bigT.open(tmp_path / "X.zarr").pixel_order.pixel_permutation
    np.testing.assert_array_equal(stored, F[perm])
    # the exact inverse gives back the true first bounce... and a second run takes it
    rep = stratified_inverse(T, tmp_path / "X2.zarr", terms=0, first_bounce=F,
                             progress=False)
    assert rep.first_bounce == "blocks"
    np.testing.assert_allclose(read(tmp_path / "X2.zarr"),
                               block_diag(np.linalg.inv(F)), rtol=1e-12, atol=1e-15)


def test_first_bounce_blocks_from_a_file_and_wrong_shapes(tmp_path, scene):
    T = store(tmp_path, scene, (6, 8))
    F = blocks_of(scene) * 1.1
    np.save(tmp_path / "F.npy", F)
    fb = resolve_first_bounce(T, tmp_path / "F.npy")
    assert fb.kind == "blocks" and fb.channels == 3 and fb.finv.shape == (48, 3, 3)
    perm = T.pixel_order.pixel_permutation
    np.testing.assert_allclose(fb.finv, np.linalg.inv(F[perm]))
    with pytest.raises(ShapeMismatchError, match=r"\(48, 3, 3\)"):
        resolve_first_bounce(T, np.ones(144))


def _ill_conditioned(scene, pixel=13):
    """``scene`` with pixel ``pixel``'s camera unable to tell green from blue: its
    diagonal block's last two rows made equal."""
    A = scene.copy()
    A[3 * pixel + 2] = A[3 * pixel + 1]
    return A


def test_ill_conditioned_pixel_is_refused_naming_it(tmp_path, scene):
    A = _ill_conditioned(scene, pixel=13)  # row-major pixel 13 = (1, 5) of 6 x 8
    T = store(tmp_path, A, (6, 8))
    with pytest.raises(InvalidMatrixError) as err:
        stratified_inverse(T, tmp_path / "X.zarr", terms=2, progress=False)
    msg = str(err.value)
    assert "\n" not in msg
    assert "pixel (1, 5)" in msg and "condition number" in msg
    assert "first_bounce='diag-skip-ill'" in msg
    assert not (tmp_path / "X.zarr").exists()


def test_ill_conditioned_pixel_left_out_on_request(tmp_path, scene):
    A = _ill_conditioned(scene, pixel=13)
    T = store(tmp_path, A, (6, 8))
    fb = resolve_first_bounce(T, "diag-skip-ill")
    assert fb.excluded == 1 and fb.ill_conditioned == 1
    rep = stratified_inverse(T, tmp_path / "X.zarr", terms=4, prune=0,
                             first_bounce="diag-skip-ill", progress=False)
    assert rep.excluded_pixels == 1
    X = read(tmp_path / "X.zarr")
    np.testing.assert_allclose(X, dense_colour_stratified(A, 4, skip=[13]), atol=1e-12)
    assert not X[39:42].any() and not X[:, 39:42].any()


def test_unlit_pixel_is_left_out(tmp_path, scene):
    A = scene.copy()
    A[3 * 7:3 * 7 + 3] = 0
    A[:, 3 * 7:3 * 7 + 3] = 0
    T = store(tmp_path, A, (6, 8))
    rep = stratified_inverse(T, tmp_path / "X.zarr", terms=31, prune=0,
                             method="newton-schulz", progress=False)
    assert rep.excluded_pixels == 1
    keep = np.ones(len(A), bool)
    keep[21:24] = False
    X = read(tmp_path / "X.zarr")
    np.testing.assert_allclose(X[np.ix_(keep, keep)], np.linalg.inv(A[np.ix_(keep, keep)]),
                               atol=1e-12)


def test_colour_tile_sizes_stay_multiples_of_three():
    assert choose_tile_size(3 * 384 * 512, 12288, 16, channels=3) == 6144
    # 3075 = 3 x 1025: its half is no multiple of 3, so colour keeps it, grey halves it
    assert choose_tile_size(3 * 10**6, 3075, 1024, channels=3) == 3075
    assert choose_tile_size(3 * 10**6, 3075, 1024) == 1537


def test_on_worker_processes(tmp_path, scene):
    """The cluster path (two dask worker processes): F's blocks reach the workers."""
    T = store(tmp_path, scene, (6, 8))
    stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0, scheduler="local:2",
                       progress=False)
    np.testing.assert_allclose(read(tmp_path / "X.zarr"),
                               dense_colour_stratified(scene, 3), atol=1e-12)


@pytest.mark.parametrize("zero_diagonal", [True, False])
def test_m_operand_rows_and_matvec(tmp_path, scene, zero_diagonal):
    """M = D - T F^-1 from its cached rows and from T's rows (no cache room) against
    dense, F = T's diagonal blocks (zero diagonal blocks) or another block diagonal."""
    from bigT.schedule.cache import TileCache
    from bigT.schedule.operators import MOperand

    T = store(tmp_path, scene, (6, 8), order="row-major")
    F = blocks_of(scene) if zero_diagonal else blocks_of(scene) * 1.2 + 0.01
    Finv = np.linalg.inv(F)
    active = np.ones(len(scene), bool)
    M_dense = np.eye(len(scene)) - scene @ block_diag(Finv)
    V = np.random.default_rng(2).standard_normal((len(scene), 2))
    for cache in (TileCache(1 << 30), TileCache(0)):
        M = MOperand(T, Finv, active, zero_diagonal, cache)
        for a, b in [(0, 24), (24, 72), (120, 144)]:
            np.testing.assert_allclose(M.matvec_rows(a, b, V), M_dense[a:b] @ V, atol=1e-12)
            rows = M.rows(a, b).toarray()
            np.testing.assert_allclose(rows, M_dense[a:b], atol=1e-12)
            if zero_diagonal:  # dropped exactly, not left as rounding
                assert not any(rows[3 * k:3 * k + 3, a + 3 * k:a + 3 * k + 3].any()
                               for k in range((b - a) // 3))


def test_matrix_free_apply_and_first_bounce_shapes(tmp_path, scene):
    from bigT.compensation import first_bounce_from_inverse, matrix_free_apply
    from bigT.compensation.core import first_bounce_diag

    T = store(tmp_path, scene, (6, 8))
    perm = T.pixel_order.permutation  # values: matrix index -> row-major value index
    finv = first_bounce_diag(T)
    assert finv.shape == (48, 3, 3)
    A_stored = scene[np.ix_(perm, perm)]
    np.testing.assert_allclose(finv, np.linalg.inv(blocks_of(A_stored)), rtol=1e-12)
    B = np.random.default_rng(3).uniform(0, 1, (144, 2))
    want = dense_colour_stratified(A_stored, 3) @ B
    np.testing.assert_allclose(matrix_free_apply(T, B, 3), want, atol=1e-12)
    np.testing.assert_allclose(matrix_free_apply(T, B, 3, F=blocks_of(A_stored)), want,
                               atol=1e-12)
    stratified_inverse(T, tmp_path / "X.zarr", terms=2, prune=0, progress=False)
    F = first_bounce_from_inverse(bigT.open(tmp_path / "X.zarr"))
    X_stored = read(tmp_path / "X.zarr", order="matrix")
    np.testing.assert_allclose(F, np.linalg.inv(blocks_of(X_stored)), rtol=1e-12)


def test_memory_sizes_of_colour_operands_bound_what_they_hold(tmp_path):
    """The memory plan's sizes of S = F X and of M's rows (a colour F mixes each
    pixel's 3 rows, so they hold up to 3x the stored entries per row) are at least
    what the operands hold once read: a row of X per channel with its own columns is
    the worst case (F X's pixel rows take the union)."""
    from bigT.schedule.cache import TileCache
    from bigT.schedule.memory import stored_bytes
    from bigT.schedule.operators import MOperand, StoreOperand

    rng = np.random.default_rng(2)
    H, W = 4, 6
    n = 3 * H * W
    X = sp.random(n, n, density=0.1, random_state=rng, format="csr")  # rows differ
    X.setdiag(1.0)
    blocks = np.linalg.inv(np.eye(3) + 0.2 * rng.random((n // 3, 3, 3)))
    Xs = store(tmp_path, X.toarray(), (H, W), "X.zarr", order="row-major", tile_size=24)
    S = StoreOperand(Xs, row_scale=blocks)
    whole = S.whole()
    assert whole.nnz > X.nnz  # the union: F X holds more than X
    assert S.nbytes >= stored_bytes(whole.nnz, n, whole.dtype.itemsize)
    for j in range(Xs.grid[0]):
        row = S.row(j)
        assert S.row_bytes(j) >= stored_bytes(row.nnz, row.shape[0], row.dtype.itemsize)
    # M = D - T F^-1 from T's rows: T F^-1 spreads each entry over its pixel's columns
    T = store(tmp_path, X.toarray(), (H, W), "T.zarr", order="row-major", tile_size=24)
    M = MOperand(T, blocks, np.ones(n, bool), True, TileCache(1 << 30))
    for a in range(0, n, 24):
        rows = M.rows(a, a + 24)
        assert rows.nnz > sp.csr_array(X)[a:a + 24].nnz
        assert M.row_bytes(a, a + 24) >= stored_bytes(rows.nnz, 24, rows.dtype.itemsize)


def test_memory_limit_holds_a_colour_run(tmp_path, scene):
    """A limit the process can meet runs a colour inverse to the dense result; its plan
    counts M's rows as 3x T's entries (one tile row of M, in the refusal's words)."""
    from bigT.errors import MemoryLimitError
    from bigT.schedule.memory import resident_bytes

    T = store(tmp_path, scene, (6, 8))
    enough = resident_bytes() + (256 << 20)
    stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0, memory_limit=enough,
                       progress=False)
    np.testing.assert_allclose(read(tmp_path / "X.zarr"), dense_colour_stratified(scene, 3),
                               atol=1e-12)
    widest = max(T.get_tile_row(j).nnz for j in range(T.grid[0]))
    with pytest.raises(MemoryLimitError, match=rf"one tile row of M, {3 * widest} entries"):
        stratified_inverse(T, tmp_path / "Y.zarr", terms=2, memory_limit="64MiB",
                           progress=False)
