"""Colour acquisition: pattern sets of three primaries, RGB captures, a colour T.

The scene is an independent colour T: three grey corner transports (one albedo each)
mixed by a camera matrix C and a projector matrix P with cross-talk,
A[3p+i, 3q+j] = sum_k C[i,k] T_k[p,q] P[k,j]; what a build recovers is compared with it
entry by entry, as the grey tests compare with the grey scene."""

import json

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT import scenes
from bigT.acquisition import (Captures, build_transport, load_correspondence, make_manifest,
                              pattern_image, read_manifest, simulate_captures, write_patterns)
from bigT.acquisition.mixing import Mixing
from bigT.acquisition.validate import check_white
from bigT.cli import main
from bigT.errors import AcquisitionError, ShapeMismatchError
from bigT.images import read_raw_image, write_image
from bigT.storage import PixelOrder
from bigT.storage import open as open_store

GRID = (6, 8)
PROJECTOR, S = (12, 16), 2
CAMERA = (20, 26)
ALBEDOS = (0.7, 0.5, 0.3)
#: camera channel i's response to light primary k, and light primary k from projector
#: primary j: cross-talk of 5-15 %
C = np.array([[0.90, 0.12, 0.03], [0.08, 0.85, 0.10], [0.02, 0.10, 0.80]])
P = np.array([[0.95, 0.10, 0.02], [0.06, 0.90, 0.08], [0.01, 0.12, 0.92]])


def mixed(transports, camera=C, projector=P) -> sp.csr_array:
    """A[3p+i, 3q+j] = sum_k camera[i,k] T_k[p,q] projector[k,j] (row-major pixels)."""
    return sp.csr_array(sum(sp.kron(T, np.outer(camera[:, k], projector[k, :]))
                            for k, T in enumerate(transports)))


@pytest.fixture(scope="module")
def colour_T(tmp_path_factory):
    root = tmp_path_factory.mktemp("colour")
    greys = [scenes.make("corner", GRID, root / f"grey{k}.zarr", albedo=a, density="exact",
                         preview=False, progress=False).T.to_scipy()
             for k, a in enumerate(ALBEDOS)]
    return bigT.from_scipy(mixed(greys), root / "T.zarr", image_shape=GRID, channels=3,
                           tile_size=24, pixel_order="tile-major", image_tile=(2, 4))


@pytest.fixture(scope="module")
def pattern_sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("colour-patterns")
    sets = {}
    for method, graycode in (("brute-force", True), ("brute-force", False), ("stripes", True)):
        folder = root / f"{method}-{graycode}"
        write_patterns(folder, make_manifest(method, PROJECTOR, S, graycode=graycode,
                                             channels=3), progress=False)
        sets[method, graycode] = folder
    return sets


def _simulate(T, patterns, out, **kw):
    kw.setdefault("black", 0.02)
    kw.setdefault("fmt", "npy")
    return simulate_captures(T.path, patterns, out, camera=CAMERA, progress=False, **kw)


def _expected(T, model) -> np.ndarray:
    """exposure x mean camera gain of each row's group x T, unseen rows and columns
    empty (dense, row-major order: the scene's image tile is not the build's)."""
    scale = model.expected_scale(PixelOrder(GRID, channels=3))
    E = scale[:, None] * T.to_scipy().toarray()
    E[:, scale == 0] = 0
    return E


def _built(path) -> np.ndarray:
    """The acquired T, dense, row-major (as ``_expected``)."""
    return open_store(path).to_scipy().toarray()


# --- the pattern set -----------------------------------------------------------------

def test_a_colour_set_lists_each_transport_pattern_once_per_primary(tmp_path):
    m = make_manifest("brute-force", PROJECTOR, S, graycode=True, channels=3)
    grey = make_manifest("brute-force", PROJECTOR, S, graycode=True)
    n = GRID[0] * GRID[1]
    assert len(m.patterns) == len(grey.patterns) + 2 * n
    sp_ = m.of_kind("superpixel")
    assert [(p.index, p.primary) for p in sp_[:4]] == [(0, "R"), (0, "G"), (0, "B"), (1, "R")]
    assert sp_[4].file == "sp_01_G.png"
    assert all(p.primary is None for p in m.patterns if p.kind != "superpixel")
    stripes = make_manifest("stripes", PROJECTOR, S, channels=3)
    assert len(stripes.patterns) == 2 + 3 * (GRID[0] + GRID[1])

    write_patterns(tmp_path, m, progress=False)
    d = json.loads((tmp_path / "manifest.json").read_text())
    assert d["channels"] == 3 and d["patterns"][2]["primary"] == "R"
    assert read_manifest(tmp_path) == m
    assert "channels" not in grey.to_dict()  # a grey manifest is as it always was

    lit = pattern_image(m, sp_[4])  # super-pixel 1 in green: pixels (0:2, 2:4)
    want = np.zeros(PROJECTOR + (3,))
    want[0:2, 2:4, 1] = 1
    assert np.array_equal(lit, want)
    assert np.array_equal(read_raw_image(tmp_path / sp_[4].file), (want * 255).astype(np.uint8))
    white, gray = pattern_image(m, m.single("white")), pattern_image(m, m.of_kind("graycode")[0])
    assert (white == 1).all() and (gray[..., 0] == gray[..., 1]).all()


def test_a_manifest_edited_to_another_primary_or_channel_count_is_refused(tmp_path):
    write_patterns(tmp_path, make_manifest("stripes", (4, 4), 2, channels=3), progress=False)
    path = tmp_path / "manifest.json"
    d = json.loads(path.read_text())
    for edit in ({"channels": 2}, {"channels": 1}):
        path.write_text(json.dumps({**d, **edit}))
        with pytest.raises(AcquisitionError, match="not a valid bigT pattern manifest"):
            read_manifest(tmp_path)
    d["patterns"][2]["primary"] = "G"
    path.write_text(json.dumps(d))
    with pytest.raises(AcquisitionError, match="not a valid bigT pattern manifest"):
        read_manifest(tmp_path)


# --- round trips ---------------------------------------------------------------------

def test_colour_brute_force_recovers_the_colour_T(colour_T, pattern_sets, tmp_path):
    """16-bit RGB PNG captures without noise: the same tolerance as the grey round trip
    (test_build), every 3x3 block with its cross-talk."""
    model = _simulate(colour_T, pattern_sets["brute-force", True], tmp_path / "cap",
                      fmt="png16")
    assert read_raw_image(tmp_path / "cap" / "sp_05_B.png").shape == CAMERA + (3,)
    report = build_transport(pattern_sets["brute-force", True], tmp_path / "cap",
                             tmp_path / "T.zarr", progress=False)
    built = open_store(tmp_path / "T.zarr")
    assert built.channels == 3 and built.tile_size % 3 == 0
    assert built.pixel_order.image_shape == GRID and report.n == 3 * GRID[0] * GRID[1]
    assert np.array_equal(load_correspondence(tmp_path / "T.zarr"), model.superpixel_of())
    E, T = _expected(colour_T, model), _built(tmp_path / "T.zarr")
    assert (np.abs(T - E) <= report.settings.floor + 2.0 / 65535).all()
    assert np.linalg.norm(T - E) / np.linalg.norm(E) < 2e-4
    off_diagonal = E[0::3, 1::3]  # camera R from projector G: the cross-talk is measured
    assert off_diagonal.max() > 0.05 * E[0::3, 0::3].max()
    assert check_white(tmp_path / "T.zarr").relative_error < 5e-3


def test_colour_maximum_response_correspondence_is_exact_without_noise(colour_T, pattern_sets,
                                                                        tmp_path):
    patterns = pattern_sets["brute-force", False]
    model = _simulate(colour_T, patterns, tmp_path / "cap")
    report = build_transport(patterns, tmp_path / "cap", tmp_path / "T.zarr", progress=False)
    assert report.settings.correspondence == "maximum response"
    assert np.array_equal(load_correspondence(tmp_path / "T.zarr"), model.superpixel_of())
    E, T = _expected(colour_T, model), _built(tmp_path / "T.zarr")
    assert np.linalg.norm(T - E) / np.linalg.norm(E) < 1e-5  # float32 captures


def test_colour_stripes_overestimate_primary_by_primary(colour_T, pattern_sets, tmp_path):
    model = _simulate(colour_T, pattern_sets["stripes", True], tmp_path / "cap")
    build_transport(pattern_sets["stripes", True], tmp_path / "cap", tmp_path / "T.zarr",
                    progress=False)
    E, T = _expected(colour_T, model), _built(tmp_path / "T.zarr")
    blocks = np.kron(np.eye(GRID[0] * GRID[1]), np.ones((3, 3))) > 0  # the 3x3 direct blocks
    assert np.abs(T[blocks] - E[blocks]).max() <= 0.02 * E.max()
    assert (T >= E - 1e-6).all()
    assert T.sum() > 1.1 * E.sum()


def test_the_floor_and_noise_are_per_camera_channel(colour_T, pattern_sets, tmp_path):
    noise = (0.001, 0.002, 0.004)
    patterns = pattern_sets["brute-force", True]
    model = _simulate(colour_T, patterns, tmp_path / "cap", noise=noise, seed=4)
    report = build_transport(patterns, tmp_path / "cap", tmp_path / "T.zarr", progress=False)
    assert report.settings.channel_noise == pytest.approx(noise, rel=0.15)
    labels = load_correspondence(tmp_path / "T.zarr")  # row-major grid indices
    counts = np.repeat(np.bincount(labels[labels >= 0], minlength=GRID[0] * GRID[1]), 3)
    sigma = np.tile(report.settings.channel_noise, GRID[0] * GRID[1])
    floors = 3 * sigma * np.sqrt(2.0 / counts)
    T = _built(tmp_path / "T.zarr")
    rows, cols = np.nonzero(T)
    assert (T[rows, cols] >= floors[rows] * (1 - 1e-3)).all()
    assert set(rows % 3) == {0, 1, 2}
    E = _expected(colour_T, model)
    bound = floors[:, None] * 1.001 + 6 * sigma[:, None] * np.sqrt(2.0 / counts)[:, None]
    assert (np.abs(T - E) <= bound).all()
    assert np.linalg.norm(T - E) / np.linalg.norm(E) < 0.05


# --- refusals ------------------------------------------------------------------------

def test_grey_captures_of_a_colour_set_are_refused_naming_the_file(colour_T, pattern_sets,
                                                                   tmp_path):
    patterns = pattern_sets["brute-force", True]
    _simulate(colour_T, patterns, tmp_path / "cap")
    odd = tmp_path / "cap" / "sp_07_G.npy"
    np.save(odd, np.load(odd)[:, :, 1])
    with pytest.raises(AcquisitionError, match="grey capture of a colour pattern set") as err:
        build_transport(patterns, tmp_path / "cap", tmp_path / "T.zarr", progress=False)
    assert str(err.value.path) == str(odd)


def test_simulate_refuses_a_colour_T_with_grey_patterns_and_the_reverse(colour_T, pattern_sets,
                                                                        tmp_path):
    grey = tmp_path / "grey"
    write_patterns(grey, make_manifest("brute-force", PROJECTOR, S), progress=False)
    with pytest.raises(AcquisitionError, match="colour transport .* grey patterns"):
        _simulate(colour_T, grey, tmp_path / "a")
    grey_T = bigT.from_scipy(sp.identity(GRID[0] * GRID[1], format="csr"), tmp_path / "g.zarr",
                             image_shape=GRID)
    with pytest.raises(AcquisitionError, match="grey transport and colour patterns"):
        _simulate(grey_T, pattern_sets["brute-force", True], tmp_path / "b")


def test_a_mixing_is_recorded_for_colour_and_refused_for_grey(colour_T, pattern_sets,
                                                              tmp_path):
    patterns = pattern_sets["brute-force", True]
    _simulate(colour_T, patterns, tmp_path / "cap")
    m = tmp_path / "mixing.json"
    m.write_text(json.dumps({"camera": C.tolist(), "projector": P.tolist()}))
    report = build_transport(patterns, tmp_path / "cap", tmp_path / "T.zarr", mixing=m,
                             progress=False)
    assert isinstance(report.mixing, Mixing)
    meta = open_store(tmp_path / "T.zarr").metadata["mixing"]
    assert np.array_equal(meta["camera"], C) and np.array_equal(meta["projector"], P)
    assert "global colour mixing recorded" in report.describe()
    for bad, says in (({"camera": C.tolist()}, 'no "projector"'),
                      ({"camera": [[1, 0], [0, 1]], "projector": P.tolist()}, "not a 3x3"),
                      ({"camera": np.ones((3, 3)).tolist(), "projector": P.tolist()},
                       "singular")):
        m.write_text(json.dumps(bad))
        with pytest.raises(AcquisitionError, match=says):
            build_transport(patterns, tmp_path / "cap", tmp_path / "T2.zarr", mixing=m,
                            progress=False)
    grey = tmp_path / "grey"
    write_patterns(grey, make_manifest("brute-force", PROJECTOR, S), progress=False)
    with pytest.raises(AcquisitionError, match="for a colour pattern set"):
        build_transport(grey, tmp_path / "cap", tmp_path / "T3.zarr", mixing=m, progress=False)


def test_a_colour_tile_size_not_a_multiple_of_3_is_refused(colour_T, pattern_sets, tmp_path):
    patterns = pattern_sets["brute-force", True]
    _simulate(colour_T, patterns, tmp_path / "cap")
    with pytest.raises(ShapeMismatchError, match="multiple of 3"):
        build_transport(patterns, tmp_path / "cap", tmp_path / "T.zarr", tile_size=32,
                        progress=False)


def test_captures_read_rgb_in_every_format(tmp_path):
    """8- and 16-bit PNG, TIFF and npy RGB captures: the same values to their precision."""
    m = make_manifest("brute-force", (2, 2), 1, channels=3)
    rng = np.random.default_rng(1)
    images = {p.stem: rng.uniform(0.1, 0.9, (5, 7, 3)) for p in m.patterns}
    for suffix, fmt, tol in ((".png", "png8", 0.5 / 255), (".png", "png16", 0.5 / 65535),
                             (".tif", "tif", 1e-7), (".npy", "npy", 1e-7)):
        folder = tmp_path / fmt
        for stem, image in images.items():
            write_image(folder / (stem + suffix), image, bits=8 if fmt == "png8" else 16)
        cap = Captures(m, folder)
        assert cap.channels == 3 and cap.shape == (5, 7)
        p = m.of_kind("superpixel")[4]
        assert np.abs(cap.linear(p) - images[p.stem]).max() <= tol


# --- the command line ----------------------------------------------------------------

def test_the_colour_loop_on_the_command_line(colour_T, tmp_path, capsys):
    pat, cap, out = tmp_path / "patterns", tmp_path / "cap", tmp_path / "T.zarr"
    assert main(["acquire", "patterns", "--method", "brute-force", "--projector", "12x16",
                 "--superpixel", "2", "--graycode", "--channels", "3", "-o", str(pat),
                 "--no-progress"]) == 0
    assert "colour: R, G, B each" in capsys.readouterr().out
    assert main(["acquire", "simulate", str(colour_T.path), str(pat), "-o", str(cap),
                 "--camera", "20x26", "--noise", "0.001,0.002,0.003", "--format", "npy",
                 "--no-progress"]) == 0
    assert "noise R 0.001 G 0.002 B 0.003" in capsys.readouterr().out
    (tmp_path / "mixing.json").write_text(json.dumps({"camera": C.tolist(),
                                                      "projector": P.tolist()}))
    assert main(["acquire", "build", str(pat), str(cap), "-o", str(out), "--mixing",
                 str(tmp_path / "mixing.json"), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "144 x 144 (colour" in text and "noise: R " in text
    assert "global colour mixing recorded in T's metadata (mixing)" in text
    assert "validation: T 1 against the captured white image (R, G, B), relative error" in text
    assert open_store(out).channels == 3
    assert main(["acquire", "simulate", str(colour_T.path), str(pat), "-o", str(cap),
                 "--camera", "20x26", "--noise", "0.1,0.2"]) == 2
    assert "three (R,G,B)" in capsys.readouterr().err


def test_the_readme_colour_walkthrough_runs(colour_T, tmp_path, monkeypatch):
    """README "Acquisition in colour": its commands, as written, in a folder holding a
    6x8 colour T and a mixing file."""
    import re
    import shlex
    import shutil
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "README.md").read_text(encoding="utf-8")
    start = text.index("### Acquisition in colour\n")
    block = re.compile(r"```sh\n(.*?)```", re.S).search(text, start).group(1)
    lines = [line for line in block.splitlines() if line.strip()]
    assert len(lines) == 3
    shutil.copytree(colour_T.path, tmp_path / "colour-T.zarr")
    (tmp_path / "mixing.json").write_text(json.dumps({"camera": C.tolist(),
                                                      "projector": P.tolist()}))
    monkeypatch.chdir(tmp_path)
    for line in lines:
        words = shlex.split(line)
        assert words[0] == "bigT"
        assert main([*words[1:], "--no-progress"]) == 0, line
    assert open_store(tmp_path / "T-rgb.zarr").metadata["mixing"]["camera"] == C.tolist()
