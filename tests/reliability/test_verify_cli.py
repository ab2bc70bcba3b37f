"""``bigT verify STORE`` sees damage anywhere (issue #17, item 8)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "algorithms"))

from inverse_helpers import random_dominant, store  # noqa: E402

from bigT import stratified_inverse  # noqa: E402
from bigT.cli import main  # noqa: E402


@pytest.fixture
def S(tmp_path):
    """A 64 x 64 store of 4 x 4 tiles (16 stored, every tile holding entries)."""
    return store(tmp_path, random_dominant(64, density=0.9, seed=6), "S.zarr", tile_size=16)


def flip_a_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def verify(path, capsys) -> tuple[int, str, str]:
    status = main(["verify", str(path), "--no-progress"])
    out, err = capsys.readouterr()
    return status, out, err


def test_a_sound_store_passes(S, capsys):
    status, out, err = verify(S.path, capsys)
    assert status == 0 and "OK, 16 tiles" in out and err == ""


def test_an_inverse_store_is_verified_through_its_current_term(S, tmp_path, capsys):
    stratified_inverse(S, tmp_path / "X.zarr", terms=2, progress=False)
    status, out, _ = verify(tmp_path / "X.zarr", capsys)
    assert status == 0 and "term 2 of" in out


@pytest.mark.parametrize("damage", [
    "flip a byte of a tile row's data chunk",
    "flip a byte of a tile row's indices chunk",
    "delete a row marker",
    "delete a chunk file",
])
def test_damage_off_the_diagonal_is_found_where_info_sees_none(tmp_path, capsys, damage):
    # 64 x 48: tile row 3 holds no diagonal entry, and bigT info reads only the tile
    # rows that do (a tile row is read whole to cut its diagonal tile)
    S = store(tmp_path, random_dominant(64, density=0.9, seed=6)[:, :48], "S.zarr",
              tile_size=16)
    row = S.path / "rows" / "3"
    if damage.startswith("flip"):
        flip_a_byte(row / ("data" if "data" in damage else "indices") / "c" / "0")
    elif damage == "delete a row marker":
        (row / "zarr.json").unlink()
    else:
        (row / "data" / "c" / "0").unlink()
    if "flip" in damage:  # the cheap check passes: that is why verify exists
        assert main(["info", str(S.path), "-q"]) == 0
    status, out, err = verify(S.path, capsys)
    assert status == 2 and out == "" and err.count("\n") == 1
    assert str(S.path) in err and "Traceback" not in err


@pytest.mark.parametrize("name", ["X.NPZ", "X.MTX"])
def test_export_to_an_upper_case_suffix_writes_that_file_and_nothing_else(S, tmp_path, name):
    out = tmp_path / "out"
    out.mkdir()
    assert main(["export", str(S.path), "-o", str(out / name), "-q"]) == 0
    assert [p.name for p in out.iterdir()] == [name]
