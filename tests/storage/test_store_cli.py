"""``bigT convert / export / info`` through bigT.cli.main, checked against scipy."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import scipy.sparse as sp

from bigT.cli import main

TS = 16


@pytest.fixture
def A():
    n = 50
    M = sp.random(n, n, density=0.08, format="csr", random_state=4, dtype=np.float64)
    M = M + sp.diags(np.r_[np.zeros(3), np.linspace(0.5, 2.0, n - 3)])
    return sp.csr_array(M)


def _read(path):
    if str(path).endswith(".npz"):
        return sp.load_npz(path)
    return sp.csr_array(scipy.io.mmread(path))


def _roundtrip(tmp_path, src, A, extra=()):
    out = tmp_path / "s.zarr"
    assert main(["convert", str(src), "-o", str(out), "--tile-size", str(TS),
                 "--dtype", "float64", *extra]) == 0
    for ext in ("npz", "mtx"):
        dst = tmp_path / f"back.{ext}"
        assert main(["export", str(out), "-o", str(dst)]) == 0
        B = _read(dst)
        assert B.shape == A.shape
        np.testing.assert_allclose(B.toarray(), A.toarray(), rtol=1e-15, atol=0)
    return out


def test_convert_npz(tmp_path, A):
    sp.save_npz(tmp_path / "a.npz", sp.csr_matrix(A))
    _roundtrip(tmp_path, tmp_path / "a.npz", A)


def test_convert_mtx(tmp_path, A):
    scipy.io.mmwrite(tmp_path / "a.mtx", sp.coo_matrix(A))
    _roundtrip(tmp_path, tmp_path / "a.mtx", A)


def test_convert_npy_dense(tmp_path, A):
    np.save(tmp_path / "a.npy", A.toarray())
    _roundtrip(tmp_path, tmp_path / "a.npy", A)


def test_convert_mat_and_var(tmp_path, A, capsys):
    scipy.io.savemat(tmp_path / "one.mat", {"T": sp.csc_matrix(A), "name": "x"})
    _roundtrip(tmp_path, tmp_path / "one.mat", A, ("--overwrite",))
    scipy.io.savemat(tmp_path / "two.mat", {"T": sp.csc_matrix(A), "D": np.eye(3)})
    capsys.readouterr()
    assert main(["convert", str(tmp_path / "two.mat"), "-o", str(tmp_path / "t.zarr")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--var" in err and "D, T" in err
    assert not (tmp_path / "t.zarr").exists()
    _roundtrip(tmp_path, tmp_path / "two.mat", A, ("--var", "T", "--overwrite"))


def test_convert_tile_major_exports_row_major(tmp_path, capsys):
    H, W = 6, 10
    M = sp.csr_array(sp.random(H * W, H * W, density=0.1, format="csr", random_state=9))
    sp.save_npz(tmp_path / "m.npz", sp.csr_matrix(M))
    _roundtrip(tmp_path, tmp_path / "m.npz", M,
               ("--image-shape", f"{H}x{W}", "--pixel-order", "tile-major", "--image-tile", "4x4"))
    capsys.readouterr()
    assert main(["info", str(tmp_path / "s.zarr"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["pixel_order"] == {"image_shape": [H, W], "pixel_order": "tile-major",
                                   "image_tile": [4, 4]}


def test_convert_refuses_existing_and_bad_input(tmp_path, A, capsys):
    sp.save_npz(tmp_path / "a.npz", sp.csr_matrix(A))
    out = str(tmp_path / "s.zarr")
    assert main(["convert", str(tmp_path / "a.npz"), "-o", out]) == 0
    capsys.readouterr()
    assert main(["convert", str(tmp_path / "a.npz"), "-o", out]) == 2
    assert "already exists" in capsys.readouterr().err
    (tmp_path / "x.csv").write_text("1,2")
    assert main(["convert", str(tmp_path / "x.csv"), "-o", str(tmp_path / "y.zarr")]) == 2
    assert "unknown input format" in capsys.readouterr().err
    B = A.toarray()
    B[1, 1] = np.nan
    np.save(tmp_path / "nan.npy", B)
    assert main(["convert", str(tmp_path / "nan.npy"), "-o", str(tmp_path / "n.zarr")]) == 2
    assert "NaN" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "a.npz"), "-o", str(tmp_path / "i.zarr"),
                 "--image-shape", "7x7"]) == 2
    assert "image shape" in capsys.readouterr().err


def test_info_json_matches_scipy(tmp_path, A, capsys):
    sp.save_npz(tmp_path / "a.npz", sp.csr_matrix(A))
    out = tmp_path / "s.zarr"
    assert main(["convert", str(tmp_path / "a.npz"), "-o", str(out), "--tile-size", str(TS),
                 "--dtype", "float64"]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    d = A.diagonal()
    coo = A.tocoo()
    tiles = {(int(r) // TS, int(c) // TS) for r, c in zip(coo.row, coo.col)}
    assert info["shape"] == list(A.shape) and info["nnz"] == A.nnz
    assert info["tile_size"] == TS and info["n_tiles_stored"] == len(tiles)
    assert info["diagonal_min"] == d.min() and info["diagonal_max"] == d.max()
    assert info["zero_diagonal"] == int(np.count_nonzero(d == 0)) == 3
    assert info["metadata"]["source"].endswith("a.npz")
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"nnz          {A.nnz}" in text and "zero entries 3" in text and "source" in text


def _broken_store(tmp_path, A):
    sp.save_npz(tmp_path / "a.npz", sp.csr_matrix(A))
    out = tmp_path / "s.zarr"
    assert main(["convert", str(tmp_path / "a.npz"), "-o", str(out), "--tile-size", str(TS)]) == 0
    os.remove(out / "rows" / "0" / "data" / "c" / "0")   # tile row 0's values
    return out


def test_info_deleted_chunk_exits_2_one_line(tmp_path, A, capsys):
    out = _broken_store(tmp_path, A)
    capsys.readouterr()
    assert main(["info", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing chunk file rows/0/data/c/0" in err and str(out) in err
    assert main(["info", str(tmp_path / "none.zarr")]) == 2
    assert "no such store" in capsys.readouterr().err


def test_console_script_deleted_chunk(tmp_path, A):
    out = _broken_store(tmp_path, A)
    script = Path(sys.executable).with_name("bigT")
    if not script.exists():
        pytest.skip("bigT console script not installed next to this interpreter")
    proc = subprocess.run([str(script), "info", str(out)], capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bigT info: error:") and "missing chunk" in lines[0]
