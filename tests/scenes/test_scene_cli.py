"""``bigT scene`` and ``bigT demo`` through bigT.cli.main."""

import json

import numpy as np
import pytest

import bigT
from bigT.cli import main


def test_scene_cli_writes_store_ground_truth_and_preview(tmp_path, capsys):
    out = tmp_path / "corner.zarr"
    assert main(["scene", "corner", "--size", "8x12", "-o", str(out), "--density", "exact",
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "spectral radius of M" in text and "bounce shares" in text
    assert (tmp_path / "corner-preview.png").stat().st_size > 1000
    sc = bigT.scenes.load(out)
    assert sc.T.shape == (96, 96) and sc.summary["name"] == "corner"
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["shape"] == [96, 96] and info["nnz"] == sc.T.nnz
    # the text form lists the scene's summary one entry per line
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "metadata     scene:" in text
    rho = next(line for line in text.splitlines() if line.strip().startswith("spectral_radius "))
    assert float(rho.split()[1]) == pytest.approx(sc.spectral_radius, rel=1e-3)


def test_scene_cli_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "d4.zarr"
    assert main(["scene", "dihedral4", "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(["scene", "dihedral4", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and str(out) in err and len(err.strip().splitlines()) == 1
    assert main(["scene", "dihedral4", "-o", str(out), "--overwrite"]) == 0


def test_scene_cli_bad_albedo_is_one_line_error(tmp_path, capsys):
    assert main(["scene", "corner", "--size", "4x6", "--albedo", "1.2", "-o",
                 str(tmp_path / "c.zarr")]) == 2
    err = capsys.readouterr().err
    assert "albedo" in err and len(err.strip().splitlines()) == 1


def test_scene_cli_bad_density_is_one_line_error(tmp_path, capsys):
    assert main(["scene", "corner", "--size", "4x6", "--density", "medium", "-o",
                 str(tmp_path / "c.zarr")]) == 2
    err = capsys.readouterr().err
    assert "density" in err and len(err.strip().splitlines()) == 1


def test_demo_refuses_a_folder_it_did_not_write(tmp_path, capsys):
    (tmp_path / "inputs").mkdir()
    (tmp_path / "inputs" / "mine.png").write_bytes(b"not the demo's")
    assert main(["demo", "--dir", str(tmp_path), "--size", "8x12", "--no-progress"]) == 2
    assert "not an earlier demo's folder" in capsys.readouterr().err
    assert (tmp_path / "inputs" / "mine.png").read_bytes() == b"not the demo's"


def test_demo_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--dir", str(out), "--size", "24x32", "--no-progress"]) == 0
    text = capsys.readouterr().out
    report = (out / "report.md").read_text()
    for needle in ("held term 4", "relative error", "fluctuation", "bounce"):
        assert needle in report
    for png in ("compensated/test_pattern_compare.png", "compensated/constant_scanline.png",
                "bounces/bounces.png", "T-preview.png"):
        assert (out / png).exists(), png
    # the demo's numbers are the real ones: compensation beats no compensation
    line = next(l for l in text.splitlines() if "relative error ||T l_in" in l)
    comp, uncomp = (float(v) for v in
                    [line.split(":")[1].split()[0], line.split(",")[1].split()[0]])
    assert comp < 0.1 * uncomp
    err = next(l for l in text.splitlines() if "exact inverse F^-1 (I - A):" in l)
    assert float(err.split(":")[1].split()[0]) < 1e-3
    np.testing.assert_equal(bigT.open(out / "X.zarr").metadata["inverse"]["term"], 4)
    # a rerun into the same folder replaces the earlier demo, even one that was
    # interrupted before its report
    (out / "report.md").unlink()
    assert main(["demo", "--dir", str(out), "--size", "24x32", "--no-progress"]) == 0
    assert (out / "report.md").exists()
