"""Synthetic scenes against independent references: the paper's eq. 34, dense
(I - A)^-1 F, physics identities (reciprocity, no transport on convex/flat surfaces,
occlusion), and the stored ground truth reopened."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT import scenes
from bigT.errors import BigTError, InvalidMatrixError, ShapeMismatchError, StoreError
from bigT.scenes import geometry, radiosity

# Paper eq. 34, typed in again here (not imported from bigT) as the reference.
EQ34 = np.array([
    [1.7713, 0.0213, 0.1835, 0.0675],
    [0.0213, 1.7713, 0.1835, 0.0675],
    [0.1835, 0.1835, 1.7875, 0.0137],
    [0.0675, 0.0675, 0.0137, 1.7550],
])


def dense(store) -> np.ndarray:
    """The store in its matrix order, the order of ``scene.F_stored`` and of the geometry."""
    return store.to_scipy(output_order="matrix").toarray().astype(np.float64)


def dense_transport(scene) -> np.ndarray:
    """(I - A)^-1 F from the stored ground truth, by a dense solve."""
    A = dense(scene.A)
    return np.linalg.solve(np.eye(A.shape[0]) - A, np.diag(scene.F_stored))


def test_dihedral4_is_eq34(tmp_path):
    sc = scenes.dihedral4(path=tmp_path / "d4.zarr")
    np.testing.assert_allclose(np.round(dense(sc.T), 4), EQ34, rtol=0, atol=0)
    np.testing.assert_array_equal(sc.F, np.full(4, 1.75))
    # the stored A reproduces T through T = (I - A)^-1 F
    np.testing.assert_allclose(dense_transport(sc), EQ34, atol=1e-12)
    assert sc.preview.exists()
    # spectral radius of M = I - T diag(T)^-1 against numpy's eigenvalues
    M = np.eye(4) - EQ34 / np.diag(EQ34)[None, :]
    assert sc.spectral_radius == pytest.approx(max(abs(np.linalg.eigvals(M))), rel=1e-12)


@pytest.mark.parametrize("name,size", [
    ("corner", (8, 12)), ("convex", (8, 12)), ("flat", (6, 8)), ("cornell", (8, 10)),
    ("hemispheres", (12, 16)),
])
def test_untruncated_scene_equals_dense_transport(tmp_path, name, size):
    # tile size 32: several tile rows (and ragged ones), so row offsets are exercised
    sc = scenes.make(name, size, tmp_path / f"{name}.zarr", density="exact", dtype="float64",
                     preview=False, tile_size=32)
    n = size[0] * size[1]
    assert sc.exact and sc.T.shape == (n, n) and sc.T.grid[0] >= 2
    np.testing.assert_allclose(dense(sc.T), dense_transport(sc), rtol=0, atol=1e-6)
    # F^-1 (I - A) is the exact inverse; inverse_error measures a stored matrix against it
    X = np.diag(1.0 / sc.F_stored) @ (np.eye(n) - dense(sc.A))
    np.testing.assert_allclose(dense(sc.T) @ X, np.eye(n), atol=1e-9)
    po = sc.pixel_order
    kw = dict(tile_size=32, dtype="float64", input_order="matrix", image_shape=po.image_shape,
              pixel_order=po.order, image_tile=po.image_tile)
    assert sc.inverse_error(bigT.from_scipy(sp.csr_array(X), tmp_path / "X.zarr", **kw)) < 1e-12
    # a perturbed inverse: the tile-row sum equals the dense relative Frobenius error
    Y = X + np.random.default_rng(0).normal(0, 1e-3, X.shape) * (np.abs(X) > 0)
    ref = np.linalg.norm(Y - X) / np.linalg.norm(X)
    got = sc.inverse_error(bigT.from_scipy(sp.csr_array(Y), tmp_path / "Y.zarr", **kw))
    assert got == pytest.approx(ref, rel=1e-9) and got > 0
    # on a sample of rows: the same rows drawn here, measured densely
    rows = np.sort(np.random.default_rng(5).choice(n, n // 3, replace=False))
    ref_rows = np.linalg.norm((Y - X)[rows]) / np.linalg.norm(X[rows])
    Ys = bigT.from_scipy(sp.csr_array(Y), tmp_path / "Ys.zarr", **kw)
    assert sc.inverse_error(Ys, sample=n // 3, seed=5) == pytest.approx(ref_rows, rel=1e-9)
    assert sc.inverse_error(Ys, sample=n) == pytest.approx(ref, rel=1e-9)
    # a diagonal X (F^-1 alone) given as a vector
    # (row-major, as sc.F is; X is dense in the stored order, as sc.F_stored is)
    assert sc.inverse_error(1.0 / sc.F) == pytest.approx(
        np.linalg.norm(np.diag(1.0 / sc.F_stored) - X) / np.linalg.norm(X), rel=1e-9)


@pytest.mark.parametrize("name", ["convex", "flat"])
def test_no_interreflection_on_convex_and_flat(tmp_path, name):
    sc = scenes.make(name, (8, 12), tmp_path / "s.zarr", density="exact", dtype="float64",
                     preview=False)
    T = dense(sc.T)
    assert sc.A.nnz == 0
    np.testing.assert_array_equal(T, np.diag(np.diag(T)))
    assert sc.spectral_radius == pytest.approx(0.0, abs=1e-12)  # rounding of d / d


def test_corner_interreflects_across_the_fold_only(tmp_path):
    sc = scenes.corner((8, 12), tmp_path / "c.zarr", density="exact", dtype="float64",
                       preview=False)
    A = dense(sc.A)
    wall = np.arange(8 * 12)[sc.pixel_order.permutation] % 12 >= 6  # right half, matrix order
    assert A[np.ix_(wall, wall)].max() == 0 and A[np.ix_(~wall, ~wall)].max() == 0
    assert A[np.ix_(wall, ~wall)].min() > 0  # every pair across the fold sees each other
    assert 0 < sc.spectral_radius < 1
    # T = (I - A)^-1 F has a bounce expansion: its shares of the light decrease and,
    # as `bigT bounces` counts them, add up to 100 %
    shares = sc.bounce_shares
    assert shares[0] > shares[1] > shares[2] > 0
    assert sum(shares) == pytest.approx(1.0, abs=1e-12)
    T1 = dense(sc.T) @ np.ones(sc.T.shape[0])  # exact scene: the bounces sum to T 1
    assert shares[1] == pytest.approx(float(np.sum(dense(sc.A) @ sc.F_stored)) / T1.sum(), rel=1e-3)


@pytest.mark.parametrize("builder", [
    lambda: geometry.wall_corner((8, 12)), lambda: geometry.wall_corner((8, 12), concave=False),
    lambda: geometry.flat_wall((6, 8)), lambda: geometry.cornell_box((8, 10)),
    lambda: geometry.hemisphere_field((12, 16)),
])
@pytest.mark.parametrize("cut", [0.0, 1e-3])
def test_searching_other_faces_only_loses_nothing(builder, cut):
    """The built-in faces are planar or convex: searching every pair, same face
    included, finds exactly the same form factors."""
    P = builder()
    assert P.same_face_exchange is False
    every = geometry.Patches(P.points, P.normals, P.areas, P.view_cos, P.distance, P.face,
                             P.reference_distance, P.spheres, same_face_exchange=True)
    A = radiosity.form_factors(P, cut, progress=False)
    B = radiosity.form_factors(every, cut, progress=False)
    assert (A != B).nnz == 0


def test_form_factor_reciprocity():
    P = geometry.cornell_box((10, 12))
    FF = radiosity.form_factors(P, 0.0, progress=False).toarray()
    lhs = P.areas[:, None] * FF
    np.testing.assert_allclose(lhs, lhs.T, rtol=1e-12, atol=1e-18)
    assert (FF.sum(axis=1) < 1).all()  # a patch cannot send out more than all its light


def test_form_factor_cut_keeps_symmetric_pattern():
    P = geometry.wall_corner((16, 20))
    full = radiosity.form_factors(P, 0.0, progress=False)
    cut = 2e-3
    FF = radiosity.form_factors(P, cut, progress=False)
    pattern = (FF != 0).astype(int)
    assert (pattern != pattern.T).nnz == 0
    # the kept entries are exactly the full ones whose pair passes the cut
    F = full.toarray()
    ref = np.where((F >= cut) | (F.T >= cut), F, 0.0)
    np.testing.assert_allclose(FF.toarray(), ref, rtol=1e-12, atol=0)
    assert 0 < FF.nnz < full.nnz


def test_hemispheres_occlude():
    P = geometry.hemisphere_field((24, 32))
    with_vis = radiosity.form_factors(P, 0.0, progress=False)
    open_P = geometry.Patches(P.points, P.normals, P.areas, P.view_cos, P.distance, P.face,
                              P.reference_distance)  # same patches, no occluders
    without = radiosity.form_factors(open_P, 0.0, progress=False)
    assert with_vis.nnz < without.nnz
    # two plane points on either side of a sphere, at its height, do not see each other
    c = P.spheres[0]
    p = np.array([[c[0] - 1.5 * c[3], c[1], c[2]], [c[0] + 1.5 * c[3], c[1], c[2]]])
    probe = geometry.Patches(np.r_[p, p], np.tile([0.0, 0.0, -1.0], (4, 1)), np.ones(4),
                             np.ones(4), np.ones(4), np.zeros(4, np.int32), 1.0, P.spheres)
    assert not radiosity._visible(probe, np.array([0]), np.array([1]))[0]


def test_ground_truth_reopens(tmp_path):
    sc = scenes.corner((16, 24), tmp_path / "c.zarr", density="sparse", preview=False)
    again = scenes.load(tmp_path / "c.zarr")
    assert again.summary == sc.summary
    np.testing.assert_array_equal(again.F, sc.F)
    assert again.A.nnz == sc.A.nnz and again.T.nnz == sc.T.nnz
    assert bigT.open(tmp_path / "c.zarr").metadata["scene"]["name"] == "corner"
    bigT.from_scipy(sp.eye(4, format="csr"), tmp_path / "plain.zarr")
    with pytest.raises(StoreError, match="ground truth"):
        scenes.load(tmp_path / "plain.zarr")


def test_threshold_truncates_and_stays_close(tmp_path):
    exact = scenes.corner((12, 16), tmp_path / "e.zarr", density="exact", dtype="float64",
                          preview=False)
    thr = 1e-4
    cut = scenes.corner((12, 16), tmp_path / "t.zarr", ff_cut=0.0, threshold=thr,
                        dtype="float64", preview=False)
    Te, Tt = dense(exact.T), dense(cut.T)
    assert Tt[Tt != 0].min() >= thr
    assert cut.T.nnz < exact.T.nnz
    # bounces are pruned at config.SCENE_PRUNE_FRACTION (0.1) of thr, so a kept entry
    # misses only such tails, and a dropped one was below thr up to those tails
    kept = Tt != 0
    assert np.abs(Tt[kept] - Te[kept]).max() < 0.2 * thr
    assert np.abs(Te[~kept]).max() < 1.2 * thr


def test_noise_floor_and_seed(tmp_path):
    kw = dict(density="exact", noise=1e-4, preview=False, dtype="float64")
    a = scenes.corner((8, 12), tmp_path / "a.zarr", seed=3, **kw)
    b = scenes.corner((8, 12), tmp_path / "b.zarr", seed=3, **kw)
    c = scenes.corner((8, 12), tmp_path / "c.zarr", seed=4, **kw)
    Ta, Tb, Tc = dense(a.T), dense(b.T), dense(c.T)
    np.testing.assert_array_equal(Ta, Tb)
    assert not np.array_equal(Ta, Tc)
    assert Ta[Ta != 0].min() >= 3e-4  # default floor: 3 x noise
    assert not a.exact


def test_blur_spreads_the_direct_bounce(tmp_path):
    """On a flat wall (no interreflection) with defocus sigma, the camera image of
    projector pixel (r, c) is f at each lit pixel times a normalised Gaussian centred
    on (r, c): built here in image coordinates, independently of the pixel order."""
    H, W, sigma = 10, 12, 1.0
    sc = scenes.flat((H, W), tmp_path / "b.zarr", density="exact", blur=sigma,
                     dtype="float64", preview=False)
    po = sc.pixel_order
    T = dense(sc.T)
    f_img = po.to_images(sc.F_stored)
    np.testing.assert_array_equal(f_img.ravel(), sc.F)  # the public F is the image
    rad = int(np.ceil(3 * sigma))
    yy, xx = np.mgrid[0:H, 0:W]
    for r, c in [(0, 0), (4, 5), (9, 11), (5, 0)]:
        g = np.exp(-((yy - r) ** 2 + (xx - c) ** 2) / (2 * sigma ** 2))
        g[(np.abs(yy - r) > rad) | (np.abs(xx - c) > rad)] = 0
        expected = f_img * g / g.sum()
        j = po.inverse_permutation[r * W + c]  # matrix index of projector pixel (r, c)
        np.testing.assert_allclose(po.to_images(T[:, j]), expected, rtol=1e-12, atol=1e-15)


def test_bad_scene_input(tmp_path):
    with pytest.raises(InvalidMatrixError, match="albedo"):
        scenes.corner((4, 6), tmp_path / "x.zarr", albedo=1.0)
    with pytest.raises(ShapeMismatchError, match="texture"):
        scenes.corner((4, 6), tmp_path / "x.zarr", albedo=np.ones((3, 3)))
    with pytest.raises(BigTError, match="density"):
        scenes.corner((4, 6), tmp_path / "x.zarr", density="medium")
    with pytest.raises(InvalidMatrixError, match="albedo"):
        scenes.corner((4, 6), tmp_path / "x.zarr", albedo=0.0)
    with pytest.raises(BigTError, match="noise"):
        scenes.corner((4, 6), tmp_path / "x.zarr", noise=-1)
    assert not (tmp_path / "x.zarr").exists()
    # an existing store is kept unless overwrite=True; a non-bigT folder never replaced
    sc = scenes.corner((4, 6), tmp_path / "c.zarr", preview=False)
    with pytest.raises(StoreError, match="already exists"):
        scenes.corner((4, 6), tmp_path / "c.zarr", albedo=0.3)
    assert scenes.load(tmp_path / "c.zarr").summary == sc.summary
    other = tmp_path / "photos"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    with pytest.raises(StoreError, match="not a bigT store"):
        scenes.corner((4, 6), other, overwrite=True)
    assert (other / "keep.txt").read_text() == "mine"
    # no partial scene left behind by the failures
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".partial")]


def test_albedo_texture(tmp_path):
    tex = np.full((8, 12), 0.5)
    tex[:, :3] = 0.1
    sc = scenes.corner((8, 12), tmp_path / "t.zarr", albedo=tex, density="exact",
                       preview=False)
    F_img = sc.F.reshape(8, 12)
    assert F_img[:, :3].max() < F_img[:, 3:6].min()
    assert sc.summary["albedo"] == "texture"


def test_preview_scan_lines_differ():
    """The preview's three scan lines are rows whose profiles differ: a scene symmetric
    top to bottom would otherwise draw one on top of another."""
    from bigT.scenes.preview import distinct_rows

    H, W = 12, 16
    y = np.abs(np.arange(H) - (H - 1) / 2)[:, None]  # symmetric top to bottom
    image = 1.0 / (1.0 + y) + np.linspace(0, 0.1, W)[None, :]
    rows = distinct_rows(image, 3)
    assert len(rows) == 3 and rows == sorted(rows)
    profiles = image[rows]
    assert min(np.linalg.norm(a - b) for i, a in enumerate(profiles)
               for b in profiles[i + 1:]) > 0
    assert distinct_rows(np.ones((5, 4)), 3) == [2]  # identical rows: one line says it all


@pytest.mark.parametrize("name", ["convex", "flat"])
def test_scenes_without_interreflection_build_beyond_the_dense_path(tmp_path, name):
    """A = 0 and more pixels than the dense eigenvalue path: the radii are 0."""
    sc = scenes.make(name, (24, 32), tmp_path / "s.zarr", preview=False)
    assert sc.spectral_radius == 0 and sc.summary["spectral_radius_A"] == 0
