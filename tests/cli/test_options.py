"""One meaning per option: sizes in dask's syntax, library defaults shown, renamed
options whose old spellings still work (and say what replaced them)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT import config
from bigT.algorithms import stratified_inverse
from bigT.cli import build_parser, main


def _parse(argv):
    return build_parser().parse_args(argv)


@pytest.mark.parametrize("new, old, dest, value", [
    (["compensate", "X", "d", "-o", "o", "--cache-size", "64MiB"],
     ["compensate", "X", "d", "-o", "o", "--cache-mb", "64"], "cache_bytes", 64 << 20),
    (["export", "S", "-o", "o.npz", "--max-size", "2GB"],
     ["export", "S", "-o", "o.npz", "--max-gb", "2"], "max_bytes", 2 * 10 ** 9),
    (["invert", "T", "-o", "X", "--threads", "3"],
     ["invert", "T", "-o", "X", "--workers", "3"], "workers", 3),
    (["compensate", "X", "d", "-o", "o", "--resident-limit", "1GiB"],
     ["compensate", "X", "d", "-o", "o", "--memory-limit", "1GiB"], "memory_limit", 1 << 30),
])
def test_renamed_options_keep_their_old_spelling(new, old, dest, value, capsys):
    assert getattr(_parse(new), dest) == value
    assert capsys.readouterr().err == ""
    assert getattr(_parse(old), dest) == value
    err = capsys.readouterr().err
    assert "deprecated" in err and new[-2] in err  # names the option to write instead


def test_cache_size_takes_zero_and_defaults_to_the_library():
    assert _parse(["compensate", "X", "d", "-o", "o", "--cache-size", "0"]).cache_bytes == 0
    assert _parse(["compensate", "X", "d", "-o", "o"]).cache_bytes is None


def _help(command):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices[command]
    return " ".join(sub.format_help().split())


def test_help_shows_the_library_defaults_and_sizes():
    text = _help("invert")
    sig = {k: v.default for k, v in __import__("inspect").signature(
        stratified_inverse).parameters.items()}
    assert f"(default {sig['terms']})" in text and f"default {sig['prune']:g}" in text
    assert f"default {sig['method']}" in text and f"(default {sig['workers']})" in text
    assert "--workers" not in text and "--threads N" in text
    assert "(default 1GiB; 0: re-read every pass)" in _help("compensate")
    assert "--resident-limit" in _help("compensate") and "--memory-limit" not in _help(
        "compensate")
    assert "(default 4GiB)" in _help("export") and "4.29" not in _help("export")
    assert "(default 2GiB)" in _help("scene") and "(default no limit)" in text
    assert config.TO_SCIPY_MAX_BYTES == 4 << 30


def test_the_methods_invert_offers_are_the_engine_s_in_its_order():
    """The help lists the methods from bigT.algorithms.defaults (light); the engine
    runs those of bigT.algorithms.methods: the same names, order and lines."""
    from bigT.algorithms import defaults
    from bigT.algorithms.methods import METHODS

    method = next(a for a in build_parser()._actions if a.dest == "command").choices[
        "invert"]._option_string_actions["--method"]
    assert method.choices == tuple(METHODS) == tuple(defaults.METHOD_HELP)
    assert [m.help for m in METHODS.values()] == list(defaults.METHOD_HELP.values())
    assert all(f"{m.name}: {m.help}" in method.help for m in METHODS.values())


def test_no_progress_is_one_option_everywhere():
    for argv in (["invert", "T", "-o", "X"], ["scene", "corner", "-o", "T"], ["verify", "S"],
                 ["relight", "T", "i", "-o", "o"], ["acquire", "simulate", "s", "p", "-o", "o",
                                                     "--camera", "4x4"]):
        assert _parse(argv).progress is True
        assert _parse(argv + ["--no-progress"]).progress is False


def test_invert_json_prints_one_object_on_stdout(tmp_path, capsys):
    n = 16
    A = sp.random(n, n, density=0.2, random_state=1, format="csr") * 0.1 + sp.identity(n)
    bigT.from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=8)
    assert main(["invert", str(tmp_path / "T.zarr"), "-o", str(tmp_path / "X.zarr"),
                 "--terms", "1", "--no-progress", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)  # the whole of stdout: no table
    assert report["terms"] == 1 and report["method"] == "power"
    # the older form writes a file beside the table
    assert main(["invert", str(tmp_path / "T.zarr"), "-o", str(tmp_path / "Y.zarr"),
                 "--terms", "1", "--no-progress", "--json", str(tmp_path / "r.json")]) == 0
    assert "tile products" in capsys.readouterr().out
    assert isinstance(json.loads((tmp_path / "r.json").read_text()), dict)


def test_bounces_says_what_it_counts(tmp_path, capsys):
    from bigT.images import write_image

    n = 12
    rng = np.random.default_rng(0)
    A = sp.random(n, n, density=0.3, random_state=rng).toarray() * 0.05
    np.fill_diagonal(A, 0)
    T = np.linalg.inv(np.eye(n) - A)
    X = np.eye(n) - 3 * A  # not the inverse of T: its bounces A' = 3 A overshoot T l
    for name, M in (("T", T), ("X", X)):
        bigT.from_scipy(sp.csr_array(M), tmp_path / f"{name}.zarr", image_shape=(3, 4),
                        tile_size=8)
    write_image(tmp_path / "w.npy", np.ones((3, 4)))
    assert main(["bounces", str(tmp_path / "T.zarr"), str(tmp_path / "X.zarr"),
                 str(tmp_path / "w.npy"), "--bounces", "2", "-o", str(tmp_path / "b"),
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "4 parts" in out and "bounces 0 (direct light) to 2" in out
    assert "bounce(s)" not in out
    assert re.search(r"remainder: +-\d", out) and "remainder is negative" in out
    assert "not the exact inverse" in out
