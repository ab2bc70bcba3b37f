"""Colour scenes: the stored T against an independent dense construction (three grey
radiosity solves mixed by the rig with numpy), the rig's global mixing recorded only
when it holds, the colour ground truth (F's blocks, the exact inverse, rho(M), the
bounce shares per channel), colour bleeding in the Cornell box, the out-of-core build
and its resumption, and the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT import scenes
from bigT.cli import main
from bigT.scenes import geometry, radiosity
from bigT.scenes.palette import PALETTES
from bigT.scenes.rig import ColourRig

SIZE = (8, 10)


def dense(store, order="row-major") -> np.ndarray:
    return store.to_scipy(output_order=order).toarray().astype(np.float64)


def reference_T(name: str, size, rig: ColourRig, white: float = 0.6,
                blur: float = 0.0) -> np.ndarray:
    """The colour T of scene ``name`` made here, row-major (index 3 (y W + x) + c): each
    band's grey T_k = (I - diag(a_k) FF)^-1 diag(a_k gain) [G] by a dense solve, mixed
    with numpy by the rig's blocks."""
    P = geometry.cornell_box(size) if name == "cornell" else geometry.wall_corner(size)
    FF = radiosity.form_factors(P, 0.0, progress=False).toarray()
    albedo = np.full((P.n, 3), white)
    for face, rgb in PALETTES[name].items():
        albedo[P.face == face] = rgb
    bands = [np.linalg.solve(np.eye(P.n) - albedo[:, k, None] * FF,
                             np.diag(albedo[:, k] * P.first_bounce_gain())) for k in range(3)]
    if blur:
        G = radiosity.gaussian_blur_matrix(size, blur, np.arange(P.n)).toarray()
        bands = [T_k @ G for T_k in bands]
    C, Pq = rig.blocks(size)
    T = np.einsum("pik,kpq,qkj->piqj", C, np.array(bands), Pq)
    return T.reshape(3 * P.n, 3 * P.n)


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    """The exact colour Cornell box, float64, one of each mixing."""
    tmp = tmp_path_factory.mktemp("colour")
    return {mixing: scenes.cornell(SIZE, tmp / f"{mixing}.zarr", colour=True, mixing=mixing,
                                   dtype="float64", density="exact", tile_size=60,
                                   progress=False)
            for mixing in ("global", "per-pixel")}


@pytest.mark.parametrize("mixing", ["global", "per-pixel"])
def test_colour_T_is_the_three_bands_mixed_by_the_rig(cornell, mixing):
    sc = cornell[mixing]
    assert sc.channels == 3 and sc.T.channels == 3 and sc.T.shape == (240, 240)
    assert sc.T.tile_size % 3 == 0 and sc.T.grid[0] == 4  # tile rows really cut T
    assert sc.rig == ColourRig.named(mixing)
    want = reference_T("cornell", SIZE, sc.rig)
    np.testing.assert_allclose(dense(sc.T), want, rtol=1e-10, atol=1e-14)


def test_the_corner_has_two_coloured_walls(tmp_path):
    sc = scenes.corner((6, 8), tmp_path / "k.zarr", colour=True, dtype="float64",
                       preview=False, progress=False)
    np.testing.assert_allclose(dense(sc.T), reference_T("corner", (6, 8), sc.rig),
                               rtol=1e-10, atol=1e-14)
    left, right = (np.array(sc.summary["surface_albedo"][k]) for k in (0, 1))
    assert left[0] > 3 * left[2] and right[2] > 3 * right[0]  # orange and blue


def test_blur_acts_on_each_band_and_noise_on_the_stored_entries(tmp_path):
    kw = dict(colour=True, dtype="float64", preview=False, progress=False, density="exact")
    blurred = scenes.cornell((6, 8), tmp_path / "b.zarr", blur=0.8, **kw)
    np.testing.assert_allclose(dense(blurred.T),
                               reference_T("cornell", (6, 8), blurred.rig, blur=0.8),
                               rtol=1e-10, atol=1e-14)
    clean = scenes.cornell((6, 8), tmp_path / "c.zarr", **kw)
    noisy = scenes.cornell((6, 8), tmp_path / "n.zarr", noise=1e-4, seed=3, **kw)
    T, T0 = dense(noisy.T), dense(clean.T)
    kept = T != 0
    assert (T[kept] >= 3e-4).all()  # the default floor, 3 noise, on the stored entries
    assert 0 < np.abs(T[kept] - T0[kept]).max() < 1e-3 and kept.sum() < T0.size
    again = scenes.cornell((6, 8), tmp_path / "m.zarr", noise=1e-4, seed=3, **kw)
    assert (dense(again.T) == T).all()  # seeded


def test_global_mixing_is_recorded_only_when_it_holds(cornell):
    glob, varied = cornell["global"], cornell["per-pixel"]
    mixing = glob.T.metadata["mixing"]
    assert mixing == {"camera": [list(r) for r in glob.rig.camera],
                      "projector": [list(r) for r in glob.rig.projector]}
    assert "mixing" not in varied.T.metadata and varied.summary["mixing"] == "per-pixel"
    # the global mixing factors T: un-mixed, T is the bands' block diagonal
    n = glob.T.shape[0] // 3
    C, P = np.array(mixing["camera"]), np.array(mixing["projector"])
    bands = (np.kron(np.eye(n), np.linalg.inv(C)) @ dense(glob.T)
             @ np.kron(np.eye(n), np.linalg.inv(P))).reshape(n, 3, n, 3)
    off_band = bands.copy()
    for k in range(3):
        off_band[:, k, :, k] = 0
    assert np.abs(off_band).max() < 1e-12 * np.abs(bands).max()
    # per pixel, each block differs from the global mixing's by a few percent
    Cg, _ = glob.rig.blocks(SIZE)
    dC = np.abs(varied.camera / Cg - 1)
    assert 0.001 < dC.max() <= varied.rig.variation
    assert not np.allclose(dense(varied.T), dense(glob.T), rtol=1e-3)


@pytest.mark.parametrize("mixing", ["global", "per-pixel"])
def test_colour_ground_truth(cornell, mixing):
    sc = cornell[mixing]
    T = dense(sc.T, "matrix")
    X = sp.vstack([sc.exact_inverse_rows(i) for i in range(sc.T.grid[0])]).toarray()
    np.testing.assert_allclose(X, np.linalg.inv(T), rtol=1e-8, atol=1e-10 * np.abs(X).max())
    # F's blocks: the inverses of X's diagonal blocks (eq. 33), C_p diag(f_p) P_p
    n = T.shape[0] // 3
    Xb = X.reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]
    np.testing.assert_allclose(np.linalg.inv(Xb), sc.F_stored, rtol=1e-9)
    P = geometry.cornell_box(SIZE)
    albedo = np.full((P.n, 3), 0.6)
    for face, rgb in PALETTES["cornell"].items():
        albedo[P.face == face] = rgb
    f = albedo * P.first_bounce_gain()[:, None]
    np.testing.assert_allclose(sc.F, np.einsum("pik,pk,pkj->pij", sc.camera, f, sc.projector),
                               rtol=1e-12)
    # rho(M), M = I - T F^-1 with F the 3x3 diagonal blocks of T (not sign-definite)
    D = T.reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]
    Finv = sp.block_diag(list(np.linalg.inv(D))).toarray()
    M = np.eye(3 * n) - T @ Finv
    assert (M < -1e-9).any() and (M > 1e-9).any()
    assert sc.spectral_radius == pytest.approx(np.abs(np.linalg.eigvals(M)).max(), rel=1e-9)
    # what share of each channel's light a white projector image sends comes from
    # bounce 0 (the light of F) and from bounce 1
    seen = T @ np.ones(3 * n)
    first = sp.block_diag(list(sc.F_stored)).toarray() @ np.ones(3 * n)
    A = dense(sc.A, "matrix")
    Cb = sp.block_diag(list(sc.camera_stored)).toarray()
    second = Cb @ A @ np.linalg.inv(Cb) @ first
    shares = np.array([s[:2] for s in sc.bounce_shares_per_channel])  # (3, 2)
    for c in range(3):
        assert sum(sc.bounce_shares_per_channel[c]) == pytest.approx(1.0, abs=1e-12)
        assert shares[c, 0] == pytest.approx(first[c::3].sum() / seen[c::3].sum(), rel=1e-3)
        assert shares[c, 1] == pytest.approx(second[c::3].sum() / seen[c::3].sum(), rel=1e-2)
    # the exact inverse scores 0 against itself, the per-pixel (term 0) inverse does not
    assert sc.inverse_error(np.linalg.inv(sc.F)) == pytest.approx(
        np.linalg.norm(sp.block_diag(list(np.linalg.inv(sc.F_stored))).toarray() - X)
        / np.linalg.norm(X), rel=1e-9)


def test_the_red_wall_tints_the_white_back_wall(cornell):
    """Light the red (green) wall alone with white: the back-wall pixels next to it see
    more red than green (more green than red)."""
    sc = cornell["global"]
    T = dense(sc.T)
    face = geometry.cornell_box(SIZE).face
    back = np.flatnonzero(face == 0)
    for wall, (more, less) in ((1, (0, 1)), (2, (1, 0))):
        lit = np.zeros((face.size, 3))
        lit[face == wall] = 1.0  # every primary on the wall's projector pixels
        seen = (T @ lit.ravel()).reshape(-1, 3)[back]
        assert (seen[:, more] > 1.5 * seen[:, less]).all()
    # without the wall's colour (a grey scene's rig), no such tint
    white = (T @ np.ones(3 * face.size)).reshape(-1, 3)[back]
    assert 0.7 < white[:, 0].sum() / white[:, 1].sum() < 1.4


def test_the_preview_is_colour(cornell):
    matplotlib = pytest.importorskip("matplotlib.image")
    image = matplotlib.imread(cornell["global"].preview)
    assert image.ndim == 3 and image.shape[2] in (3, 4)
    rgb = image[..., :3]
    assert (np.abs(rgb[..., 0] - rgb[..., 1]) > 0.1).any()  # coloured pixels drawn


SMALL = 1 << 19  # bytes: A's tile rows come in batches, T is read again for each product
OOC = dict(density=5e-4, threshold=1e-6, tile_size=96, preview=False, progress=False,
           colour=True, mixing="per-pixel")


def test_out_of_core_build_equals_the_in_memory_one(tmp_path):
    big = scenes.cornell((12, 16), tmp_path / "big.zarr", **OOC)
    small = scenes.cornell((12, 16), tmp_path / "small.zarr", memory_limit=SMALL, **OOC)
    assert big.A.nnz * 12 > SMALL // 2  # half the small budget holds no whole A
    assert (dense(big.T) != dense(small.T)).sum() == 0
    assert small.spectral_radius == pytest.approx(big.spectral_radius, rel=1e-9)
    np.testing.assert_allclose(small.bounce_shares_per_channel,
                               big.bounce_shares_per_channel, rtol=1e-9)


class Interrupt(BaseException):
    """Stands for Ctrl-C (not an Exception: nothing may catch it)."""


def test_an_interrupted_colour_build_resumes(tmp_path, monkeypatch):
    reference = scenes.cornell((12, 16), tmp_path / "ref.zarr", **OOC)
    real, calls = radiosity.mix_bands, []

    def mix_then_interrupt(*args):
        if len(calls) == 3:
            raise Interrupt
        calls.append(1)
        return real(*args)

    path = tmp_path / "c.zarr"
    with monkeypatch.context() as m:
        m.setattr(radiosity, "mix_bands", mix_then_interrupt)
        with pytest.raises(Interrupt):
            scenes.cornell((12, 16), path, **OOC)
    assert not path.exists()
    again = []
    with monkeypatch.context() as m:
        m.setattr(radiosity, "mix_bands", lambda *a: again.append(1) or real(*a))
        scene = scenes.cornell((12, 16), path, **OOC)
    assert len(again) == reference.T.grid[0] - 3 and scene.summary["resumed"] is True
    assert (dense(scene.T) != dense(reference.T)).sum() == 0
    np.testing.assert_array_equal(scene.camera, reference.camera)


def test_colour_refusals(tmp_path):
    with pytest.raises(bigT.ShapeMismatchError, match="multiple of 3"):
        scenes.cornell((4, 6), tmp_path / "a.zarr", colour=True, tile_size=20)
    with pytest.raises(bigT.BigTError, match="mixing"):
        scenes.cornell((4, 6), tmp_path / "b.zarr", colour=True, mixing="local")
    with pytest.raises(bigT.ShapeMismatchError, match=r"\(H, W, 3\)"):
        scenes.cornell((4, 6), tmp_path / "c.zarr", colour=True, albedo=np.full((4, 6), 0.5))
    with pytest.raises(bigT.BigTError, match="singular"):
        ColourRig(camera=[[1, 1, 0], [1, 1, 0], [0, 0, 1]])


def test_scene_cli_colour(tmp_path, capsys):
    out = tmp_path / "cornell.zarr"
    assert main(["scene", "cornell", "--colour", "--mixing", "per-pixel", "--size", "6x8",
                 "-o", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "mixing per pixel" in text and "bounce shares in G" in text
    sc = scenes.load(out)
    assert sc.T.shape == (144, 144) and sc.summary["channels"] == 3
    assert main(["scene", "cornell", "--mixing", "global", "-o", str(tmp_path / "g.zarr")]) == 2
    assert "--colour" in capsys.readouterr().err
    assert main(["scene", "cornell", "--colour", "--size", "6x8", "--json", "-o",
                 str(tmp_path / "j.zarr")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["mixing"] == "global" and len(summary["bounce_shares_per_channel"]) == 3
