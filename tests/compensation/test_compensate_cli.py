"""bigT compensate / relight / bounces through bigT.cli.main."""

from __future__ import annotations

import numpy as np
import pytest

from bigT.cli import main
from bigT.images import read_image, write_image

from comp_helpers import make_store, random_transport

H, W = 10, 12


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    d = tmp_path_factory.mktemp("stores")
    T, X, F, A = random_transport(H, W, seed=7)
    make_store(T, d / "T.zarr", image_shape=(H, W), tile_size=48, pixel_order="tile-major")
    make_store(X, d / "X.zarr", image_shape=(H, W), tile_size=48)
    return d, T, X


def test_compensate_image_with_simulate(stores, tmp_path, capsys):
    d, T, X = stores
    write_image(tmp_path / "flat.npy", np.full((H, W), 0.5))
    out = tmp_path / "proj.npy"
    rc = main(["compensate", str(d / "X.zarr"), str(tmp_path / "flat.npy"), "-o", str(out),
               "--simulate", str(d / "T.zarr"), "--no-progress", "--path", "explicit"])
    assert rc == 0
    text = capsys.readouterr().out
    l_in = read_image(out)
    np.testing.assert_allclose(l_in.ravel(), np.clip(X @ np.full(H * W, 0.5), 0, 1),
                               rtol=1e-5, atol=1e-6)
    seen = read_image(tmp_path / "proj_seen.npy")
    np.testing.assert_allclose(seen.ravel(), T @ l_in.ravel(), rtol=1e-4, atol=1e-5)
    for name in ("proj_compare.png", "proj_scanline.png"):
        assert (tmp_path / name).stat().st_size > 1000
    assert "path: explicit" in text and "relative error" in text
    assert "fluctuation" in text and "centre scan line" in text and "clipped" in text
    err = np.linalg.norm(seen - 0.5) / np.linalg.norm(np.full((H, W), 0.5))
    assert f"{err:.4f} compensated" in text


def test_compensate_folder_batches_and_auto(stores, tmp_path, capsys):
    d, T, X = stores
    rng = np.random.default_rng(0)
    frames = rng.uniform(0.2, 0.6, (5, H, W))
    for i, f in enumerate(frames):
        write_image(tmp_path / "in" / f"frame{i}.png", f, bits=16)
    rc = main(["compensate", str(d / "X.zarr"), str(tmp_path / "in"), "-o", str(tmp_path / "out"),
               "--batch", "2", "--clip", "none", "--matrix-free", str(d / "T.zarr"),
               "--terms", "2", "--path", "auto", "--no-progress"])
    assert rc == 0
    text = capsys.readouterr().out
    # auto: nnz(X) vs 2 * nnz(T); both are dense here, so X is cheaper
    assert "path: explicit" in text and "cheaper" in text
    for i in range(5):
        desired = read_image(tmp_path / "in" / f"frame{i}.png")
        got = read_image(tmp_path / "out" / f"frame{i}.png")
        ref = (X @ desired.ravel()).reshape(H, W)
        np.testing.assert_allclose(got, np.clip(ref, 0, 1), atol=1.0 / 65535 + 1e-5)


def test_compensate_matrix_free_without_X(stores, tmp_path, capsys):
    d, T, X = stores
    write_image(tmp_path / "d.npy", np.full((H, W), 0.4))
    rc = main(["compensate", "-", str(tmp_path / "d.npy"), "-o", str(tmp_path / "p.npy"),
               "--matrix-free", str(d / "T.zarr"), "--terms", "3", "--no-progress",
               "--clip", "none"])
    assert rc == 0
    assert "path: matrix-free (3 terms)" in capsys.readouterr().out
    F = np.diag(T)
    M = np.eye(H * W) - T / F[None, :]
    S, P = np.eye(H * W), np.eye(H * W)
    for _ in range(3):
        P = M @ P
        S += P
    ref = (S / F[:, None]) @ np.full(H * W, 0.4)
    np.testing.assert_allclose(read_image(tmp_path / "p.npy").ravel(), ref, rtol=1e-4, atol=1e-5)


def test_relight_and_bounces(stores, tmp_path, capsys):
    d, T, X = stores
    l = np.random.default_rng(2).uniform(0, 1, (H, W))
    write_image(tmp_path / "l.tif", l)
    assert main(["relight", str(d / "T.zarr"), str(tmp_path / "l.tif"), "-o",
                 str(tmp_path / "seen.tif"), "--no-progress"]) == 0
    Tl = (T @ read_image(tmp_path / "l.tif").ravel()).reshape(H, W)
    np.testing.assert_allclose(read_image(tmp_path / "seen.tif"), Tl, rtol=1e-4, atol=1e-5)
    assert main(["bounces", str(d / "T.zarr"), str(d / "X.zarr"), str(tmp_path / "l.tif"),
                 "--bounces", "3", "-o", str(tmp_path / "b"), "--no-progress"]) == 0
    text = capsys.readouterr().out
    parts = [read_image(tmp_path / "b" / f"bounce_{k}.tif") for k in range(4)]
    parts.append(read_image(tmp_path / "b" / "remainder.tif"))
    np.testing.assert_allclose(np.sum(parts, axis=0), Tl, rtol=1e-4, atol=1e-5)
    assert (tmp_path / "b" / "bounces.png").stat().st_size > 1000
    assert "direct" in text and "remainder" in text and "%" in text


def test_cli_errors_are_one_line_status_2(stores, tmp_path, capsys):
    d, T, X = stores
    write_image(tmp_path / "wrong.png", np.zeros((H + 1, W)))
    rc = main(["compensate", str(d / "X.zarr"), str(tmp_path / "wrong.png"), "-o",
               str(tmp_path / "o.png"), "--no-progress"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "wrong.png" in err and "(11, 12)" in err and "(10, 12)" in err
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "rgb.png", np.zeros((H, W, 3), np.uint8))
    assert main(["relight", str(d / "T.zarr"), str(tmp_path / "rgb.png"), "-o",
                 str(tmp_path / "o.png"), "--no-progress"]) == 2
    assert "3 channels" in capsys.readouterr().err
    assert main(["compensate", str(d / "X.zarr"), str(tmp_path / "wrong.png"), "-o",
                 str(tmp_path / "o.png"), "--clip", "1,0"]) == 2


def test_cli_matrix_free_without_T_is_an_error(stores, tmp_path, capsys):
    d, T, X = stores
    write_image(tmp_path / "d.npy", np.full((H, W), 0.4))
    assert main(["compensate", "-", str(tmp_path / "d.npy"), "-o", str(tmp_path / "p.npy"),
                 "--no-progress"]) == 2
    assert "needs the inverse X" in capsys.readouterr().err
    assert main(["compensate", "-", str(tmp_path / "d.npy"), "-o", str(tmp_path / "p.npy"),
                 "--path", "matrix-free", "--no-progress"]) == 2
    assert "the transport T" in capsys.readouterr().err
