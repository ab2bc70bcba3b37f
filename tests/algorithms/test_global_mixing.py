"""The global colour-mixing path (bigT.algorithms.mixing, .global_mixing): a colour T
made in the test from three grey transports and one camera C and projector P,
T[3p+i, 3q+j] = sum_k C[i, k] T_k[p, q] P[k, j], against dense numpy references."""

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.algorithms import global_mixing
from bigT.algorithms.mixing import (choose_colour_path, estimate_mixing, mixing_residue,
                                    mixing_tolerance)
from bigT.cli import main
from bigT.compensation import choose_path
from bigT.compensation.realtime import Compensator
from bigT.errors import BigTError

H, W = 4, 6
N = H * W
#: A camera and a projector with cross-talk, as a rig's (not diagonal-dominant alike).
CAMERA = np.array([[0.90, 0.12, 0.05], [0.15, 0.80, 0.10], [0.03, 0.14, 0.85]])
PROJECTOR = np.array([[0.85, 0.10, 0.04], [0.12, 0.90, 0.10], [0.05, 0.09, 0.80]])


def band_transports(seed=0):
    """Three nonnegative grey transports T_k = diag(d) (I + A_k), rho(M) about 0.2."""
    rng = np.random.default_rng(seed)
    bands = []
    for _ in range(3):
        A = rng.uniform(size=(N, N)) * (rng.uniform(size=(N, N)) < 0.3)
        np.fill_diagonal(A, 0.0)
        A *= 0.2 / np.abs(np.linalg.eigvals(A)).max()
        bands.append(np.diag(rng.uniform(0.5, 1.5, N)) @ (np.eye(N) + A))
    return bands


def mixed(bands, camera=CAMERA, projector=PROJECTOR):
    """The colour T (3N x 3N, index 3p + c) of ``bands`` between ``camera`` and
    ``projector``; either may be a per-pixel (N, 3, 3) stack (camera: by row pixel)."""
    cams = np.broadcast_to(camera, (N, 3, 3))
    T = np.zeros((3 * N, 3 * N))
    for p in range(N):
        for k in range(3):
            T[3 * p:3 * p + 3] += np.kron(bands[k][p], np.outer(cams[p][:, k], projector[k]))
    return T


def colour_store(path, A, metadata=None, tile_size=12):
    return bigT.from_scipy(sp.csr_array(A), path, image_shape=(H, W), channels=3,
                           tile_size=tile_size, dtype="float64", metadata=metadata)


def block_jacobi_stratified(A, n):
    """Eq. 13 with F the 3x3 diagonal blocks of the colour A, densely."""
    F = np.zeros_like(A)
    for p in range(N):
        F[3 * p:3 * p + 3, 3 * p:3 * p + 3] = A[3 * p:3 * p + 3, 3 * p:3 * p + 3]
    Finv = np.linalg.inv(F)
    M = np.eye(len(A)) - A @ Finv
    S, Pk = np.zeros_like(A), np.eye(len(A))
    for _ in range(n + 1):
        S, Pk = S + Pk, M @ Pk
    return Finv @ S


def test_unpruned_global_path_is_the_exact_inverse(tmp_path):
    A = mixed(band_transports())
    T = colour_store(tmp_path / "T.zarr", A)
    report = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=31, prune=0,
                                     method="newton-schulz", progress=False,
                                     colour_path="global")
    assert report.colour_path == "global"
    assert "estimated from T's diagonal blocks" in report.colour_reason
    X = bigT.open(tmp_path / "X.zarr")
    assert X.channels == 3 and X.pixel_order == T.pixel_order and X.tile_size % 3 == 0
    exact = np.linalg.inv(A)
    np.testing.assert_allclose(X.to_scipy().toarray(), exact, atol=1e-12 * np.abs(exact).max())
    assert X.nnz == report.nnz_X
    assert X.metadata["inverse"]["colour_path"] == "global"
    assert not (tmp_path / "X.zarr" / global_mixing.WORK_DIR).exists()  # cleaned


def test_recorded_mixing_auto_path_matches_the_block_jacobi_series(tmp_path):
    """Without pruning, the global path's n terms are the general path's n terms with F
    the 3x3 diagonal blocks (the two series are similar through C)."""
    A = mixed(band_transports(1))
    recorded = {"camera": CAMERA.tolist(), "projector": PROJECTOR.tolist()}
    T = colour_store(tmp_path / "T.zarr", A, metadata={"mixing": recorded})
    report = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=2, prune=0,
                                     progress=False)
    assert report.colour_path == "global" and "recorded with T" in report.colour_reason
    assert report.mixing_residual <= mixing_tolerance(np.float64)
    X = bigT.open(tmp_path / "X.zarr").to_scipy().toarray()
    np.testing.assert_allclose(X, block_jacobi_stratified(A, 2), atol=1e-12)


@pytest.mark.parametrize("order, scale", [((0, 1, 2), (1.0, 1.0, 1.0)),
                                          ((2, 0, 1), (3.0, 0.2, 1.5))])
def test_estimate_recovers_a_verified_mixing(tmp_path, order, scale):
    """The camera's channels permuted and the bands scaled: the estimate's columns are
    the true C's up to order and scale, and it verifies over all of T."""
    camera = (CAMERA * np.array(scale))[list(order)]
    T = colour_store(tmp_path / "T.zarr", mixed(band_transports(2), camera))
    found = estimate_mixing(T)
    assert mixing_residue(T, found) < 1e-12
    unit = lambda m: m / np.linalg.norm(m, axis=0)  # noqa: E731
    cosines = np.abs(unit(found.camera).T @ unit(camera))
    np.testing.assert_allclose(np.sort(cosines.max(axis=1)), 1.0, atol=1e-9)


def test_per_pixel_mixing_is_not_global(tmp_path):
    rng = np.random.default_rng(3)
    cameras = CAMERA * (1 + 0.05 * rng.standard_normal((N, 3, 3)))
    T = colour_store(tmp_path / "T.zarr", mixed(band_transports(3), cameras))
    choice = choose_colour_path(T)
    assert choice.path == "general"
    assert choice.reason.startswith("general: per-pixel mixing varies")
    assert choice.mixing.residual > 1e-3 and f"{choice.mixing.residual:.2g}" in choice.reason
    with pytest.raises(BigTError, match="global colour-mixing path does not apply"):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", colour_path="global", progress=False)
    assert not (tmp_path / "X.zarr").exists()


def test_a_wrong_recorded_mixing_is_caught(tmp_path):
    wrong = {"camera": np.eye(3).tolist(), "projector": PROJECTOR.tolist()}
    T = colour_store(tmp_path / "T.zarr", mixed(band_transports(4)),
                     metadata={"mixing": wrong})
    choice = choose_colour_path(T)
    assert choice.path == "general"
    assert "recorded with T; cross-channel residue" in choice.reason
    assert choice.mixing.residual > 0.01


def test_a_resumed_run_publishes_x_once_the_grey_inverse_is_held(tmp_path, monkeypatch):
    A = mixed(band_transports(5))
    T = colour_store(tmp_path / "T.zarr", A)
    out = tmp_path / "X.zarr"

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(global_mixing, "factored_inverse", killed)
        with pytest.raises(KeyboardInterrupt):
            bigT.stratified_inverse(T, out, terms=2, prune=0, progress=False)
    assert (out / global_mixing.WORK_DIR / "U_inverse").is_dir()  # kept for the rerun
    report = bigT.stratified_inverse(T, out, terms=2, prune=0, progress=False)
    assert report.stopped == "already held term 2"  # the grey inverse was not redone
    np.testing.assert_allclose(bigT.open(out).to_scipy().toarray(),
                               block_jacobi_stratified(A, 2), atol=1e-12)
    again = bigT.stratified_inverse(T, out, terms=2, prune=0, progress=False)
    assert again.stopped == "already held term 2" and again.colour_path == "global"


def test_cli_global_path_line_then_info_and_verify(tmp_path, capsys):
    T = colour_store(tmp_path / "T.zarr", mixed(band_transports(6)))
    X = tmp_path / "X.zarr"
    assert main(["invert", str(T.path), "-o", str(X), "--colour-path", "global",
                 "--terms", "2", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("colour path: global colour mixing (estimated from T's diagonal "
                          "blocks; cross-channel residue ")
    assert "): three grey inverses" in out.splitlines()[0]
    assert main(["info", str(X)]) == 0
    info = capsys.readouterr().out
    assert "colour (3 channels, index 3p+c)" in info
    assert any(line.split()[:2] == ["colour_path", "global"] for line in info.splitlines())
    assert main(["verify", str(X)]) == 0
    assert "(term 2 of" in capsys.readouterr().out


def test_the_global_path_keeps_x_factored_and_every_reader_applies_it(tmp_path):
    """X = (I (x) P^-1) U^-1 (I (x) C^-1) is stored as U^-1 (channel-diagonal: 3 N^2
    entries, where composed 3x3 blocks would hold 9 N^2) with its ``mixing`` attribute;
    every product of X equals the dense inverse of T (a tile-major T: the mixing
    commutes with its pixel permutation)."""
    A = mixed(band_transports(4))
    T = bigT.from_scipy(sp.csr_array(A), tmp_path / "T.zarr", image_shape=(H, W), channels=3,
                        tile_size=12, dtype="float64", pixel_order="tile-major",
                        image_tile=(2, 3))
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=31, prune=0,
                            method="newton-schulz", progress=False, colour_path="global")
    X = bigT.open(tmp_path / "X.zarr")
    exact = np.linalg.inv(A)
    tol = 1e-12 * np.abs(exact).max()
    assert X.mixing is not None and X.nnz == 3 * N * N
    assert np.count_nonzero(exact) == 9 * N * N  # what composing would have stored

    S = X.get_rows(0, 3 * N).toarray()  # the stored tiles: U^-1, channel-diagonal
    rows, cols = np.nonzero(S)
    assert np.all(rows % 3 == cols % 3)
    L, R = X.mixing
    perm = T.pixel_order.permutation  # matrix index -> row-major value
    stored_exact = exact[np.ix_(perm, perm)]
    np.testing.assert_allclose(np.kron(np.eye(N), L) @ S @ np.kron(np.eye(N), R),
                               stored_exact, atol=tol)

    np.testing.assert_allclose(X.to_scipy().toarray(), exact, atol=tol)
    np.testing.assert_allclose(X.to_scipy(output_order="matrix").toarray(), stored_exact,
                               atol=tol)
    np.testing.assert_allclose(X.diagonal(), np.diag(exact), atol=tol)
    image = np.random.default_rng(5).uniform(size=(H, W, 3))
    want = (exact @ image.ravel()).reshape(H, W, 3)
    np.testing.assert_allclose((X @ image.ravel()).reshape(H, W, 3), want, atol=tol)

    streamed = bigT.compensate(X, image, clip=None, path="explicit")
    np.testing.assert_allclose(streamed, want, atol=1e-10)
    resident = Compensator(X, None, choose_path(X=X, path="explicit"), clip=None)
    assert resident.matrix is not None  # X held in memory, float32
    np.testing.assert_allclose(resident(image[None])[0], want, rtol=1e-5,
                               atol=1e-5 * np.abs(want).max())

    blocks = np.stack([exact[3 * p:3 * p + 3, 3 * p:3 * p + 3] for p in range(N)])
    np.testing.assert_allclose(bigT.recover_first_bounce(X), np.linalg.inv(blocks),
                               atol=1e-9)
    parts = bigT.separate_bounces(T, X, image)
    np.testing.assert_allclose(parts.sum(axis=0), (A @ image.ravel()).reshape(H, W, 3),
                               atol=1e-10)


def test_a_grey_tiling_of_u_that_splits_pixels_is_rewritten_in_t_tiles(tmp_path, monkeypatch):
    """The grey engine may halve U's tile size to one that is not whole pixels (12 -> 8
    here, forced): X is then U^-1's rows in T's tiles, still factored and exact."""
    from bigT.algorithms import run_setup

    monkeypatch.setattr(run_setup, "choose_tile_size", lambda n, ts, threads, channels=1:
                        8 if channels == 1 else ts)
    A = mixed(band_transports(6))
    T = colour_store(tmp_path / "T.zarr", A)
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=31, prune=0,
                            method="newton-schulz", progress=False, colour_path="global")
    X = bigT.open(tmp_path / "X.zarr")
    exact = np.linalg.inv(A)
    assert X.tile_size == T.tile_size and X.mixing is not None and X.nnz == 3 * N * N
    np.testing.assert_allclose(X.to_scipy().toarray(), exact, atol=1e-12 * np.abs(exact).max())
