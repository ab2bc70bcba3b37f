"""``bigT invert`` end to end: the per-term table, --json, resume, ``bigT info`` of the
result, and one-line errors (exit 2) for a limit too small, a diverging series and a
bad --first-bounce."""

import json

import numpy as np
import pytest

from bigT.cli import main

from inverse_helpers import dense, dense_stratified, random_dominant


def _lines(text):
    return [line for line in text.strip().splitlines() if line.strip()]


def test_invert_table_json_info_and_resume(tmp_path, make_store, capsys):
    A = random_dominant(48, seed=11)
    T = make_store(A, tile_size=16)
    X, J = tmp_path / "X.zarr", tmp_path / "r.json"
    args = ["invert", T.path.as_posix(), "-o", str(X), "--terms", "2", "--prune", "0",
            "--no-progress"]
    assert main(args + ["--json", str(J)]) == 0
    out = capsys.readouterr().out
    rows = [line.split() for line in _lines(out) if line.split()[0] in ("0", "1", "2")]
    assert [r[0] for r in rows] == ["0", "1", "2"]
    assert "held term 2 (power, prune 0, first bounce diag)" in out
    report = json.loads(J.read_text())
    assert report["terms"] == 2 and len(report["history"]) == 3
    assert [int(r[4]) for r in rows] == [h["nnz_X"] for h in report["history"]]  # after "resid s"
    np.testing.assert_allclose(dense(X), dense_stratified(A, 2), atol=1e-10)

    assert main(["info", str(X)]) == 0
    info = capsys.readouterr().out
    for key, value in (("term", "2"), ("prune", "0"), ("first_bounce", "diag")):
        assert any(line.split()[:2] == [key, value] for line in _lines(info)), key
    assert any(line.split()[0] == "residual" for line in _lines(info))

    assert main(args) == 0  # the same command again: nothing left to do
    assert "stopped: already held term 2" in capsys.readouterr().out


def test_invert_with_feed_and_operator_thresholds(tmp_path, make_store, capsys):
    """--prune-feed and --prune-operator reach the engine: the table says so, and
    X is the carried power form with M pruned in the later products, evaluated
    densely; a threshold below --prune is refused in one line."""
    from test_carry_and_counts import dense_carried_power

    A = random_dominant(48, seed=13, density=0.4)
    T = make_store(A, tile_size=16)
    X = tmp_path / "X.zarr"
    assert main(["invert", T.path.as_posix(), "-o", str(X), "--terms", "3", "--prune",
                 "1e-5", "--prune-feed", "1e-3", "--prune-operator", "2e-3",
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "P_k pruned at 0.001, M pruned at 0.002 in the products" in out
    want, _ = dense_carried_power(A, 3, 1e-5, 1e-3, 2e-3)
    np.testing.assert_allclose(dense(X), want, rtol=1e-10, atol=1e-13)
    assert main(["invert", T.path.as_posix(), "-o", str(tmp_path / "Y.zarr"), "--prune",
                 "1e-3", "--prune-operator", "1e-4", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "--prune-operator must be >= prune" in err and len(_lines(err)) == 1


def test_invert_errors_are_one_line(tmp_path, make_store, capsys):
    A = random_dominant(32, seed=12)
    T = make_store(A, tile_size=16)
    cases = [
        (["--memory-limit", "64MiB"], "--memory-limit 64 MiB is too small", "Y1.zarr"),
        (["--first-bounce", str(tmp_path / "nope.npy")], "neither diag, identity", "Y2.zarr"),
    ]
    for extra, message, name in cases:
        assert main(["invert", T.path.as_posix(), "-o", str(tmp_path / name),
                     "--no-progress"] + extra) == 2
        err = capsys.readouterr().err
        assert message in err and len(_lines(err)) == 1, err
        assert not (tmp_path / name).exists()


def test_invert_diverging_series_stops_with_the_number(tmp_path, make_store, capsys):
    n = 24
    rng = np.random.default_rng(3)
    # one bright mode (T 1 = 3 1): M = I - T has the eigenvalue about 1 - 3 = -2
    A = np.diag(rng.uniform(0.05, 0.1, n)) + rng.uniform(2.5, 3.5, (n, n)) / n
    T = make_store(A, tile_size=8)
    assert main(["invert", T.path.as_posix(), "-o", str(tmp_path / "X.zarr"),
                 "--first-bounce", "identity", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "diverges" in err and "--force" in err and len(_lines(err)) == 1
    assert "force=True" not in err and "first_bounce=" not in err  # the CLI's words
    assert not (tmp_path / "X.zarr").exists()  # a refused run leaves nothing behind
    rho = float(err.split("M = I - T F^-1 is ")[1].split()[0])
    M = np.eye(n) - A
    assert rho >= 1 and rho == pytest.approx(max(abs(np.linalg.eigvals(M))), abs=5e-5)  # 4 digits


def test_overwrite_starts_anew_and_never_deletes_foreign_data(tmp_path, make_store, capsys):
    A = random_dominant(32, seed=13)
    T = make_store(A, tile_size=16)
    X = tmp_path / "X.zarr"
    base = ["invert", T.path.as_posix(), "-o", str(X), "--terms", "2", "--no-progress"]
    assert main(base + ["--prune", "0"]) == 0
    capsys.readouterr()
    assert main(base + ["--prune", "1e-3"]) == 2  # other parameters: refused, kept
    err = capsys.readouterr().err
    assert "different prune" in err and "--overwrite" in err and "overwrite=True" not in err
    np.testing.assert_allclose(dense(X), dense_stratified(A, 2), atol=1e-10)
    assert main(base + ["--prune", "1e-3", "--overwrite"]) == 0
    assert "held term 2 (power, prune 0.001" in capsys.readouterr().out
    foreign = tmp_path / "notes"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    assert main(["invert", T.path.as_posix(), "-o", str(foreign), "--overwrite",
                 "--no-progress"]) == 2
    assert "not a bigT inverse store" in capsys.readouterr().err
    assert (foreign / "keep.txt").read_text() == "mine"


def test_version_and_a_closed_pipe(tmp_path, make_store, capsys):
    import subprocess
    import sys
    from pathlib import Path

    import pytest

    import bigT

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"bigT {bigT.__version__}"
    T = make_store(random_dominant(16, seed=14), tile_size=16)
    exe = Path(sys.executable).with_name("bigT")
    proc = subprocess.Popen([str(exe), "info", T.path.as_posix()], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()  # `bigT info T.zarr | head -0`: the reader is gone before a line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141 and "Traceback" not in err and err == ""


def test_a_small_inverse_never_imports_numba(tmp_path, make_store):
    """Below config.KERNEL_NUMPY_MAX_WORK every kernel call takes its numpy twin, so a
    first run on a fresh install compiles nothing (#12: it took 25 s cold)."""
    import subprocess
    import sys

    T = make_store(random_dominant(16, seed=3), tile_size=8)
    code = ("import sys; from bigT.cli import main; "
            f"rc = main(['invert', {T.path.as_posix()!r}, '-o', {str(tmp_path / 'X.zarr')!r}, "
            "'--no-progress']); "
            "print('numba' in sys.modules, rc)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out[-2:] == ["False", "0"]
