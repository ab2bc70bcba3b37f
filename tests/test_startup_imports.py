"""A command line call imports only what its command needs (issue #30).

Each check runs in a new interpreter and reads ``sys.modules`` after the call: what a
process imported is what it paid for at start-up, whatever the machine's speed. The
times are measured in benchmarks/bench_startup.py, never asserted here.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parent.parent

#: Libraries that cost 0.1-0.5 s each to import; none is needed to print a help.
HEAVY = ("dask", "distributed", "numba", "zarr", "scipy", "numcodecs", "matplotlib",
         "skimage", "imageio", "cv2", "PIL")


def _commands() -> list[str]:
    """Every command and acquire step the parser lists (``acquire simulate``)."""
    from bigT.cli import build_parser

    def subs(parser):
        return next((a.choices for a in parser._actions
                     if isinstance(a, argparse._SubParsersAction)), {})

    return [" ".join((name, *step)) for name, p in subs(build_parser()).items()
            for step in [(), *((s,) for s in subs(p))]]


#: Every command's help (invert's defaults and method names and simulate's capture
#: formats included: they are read from light modules, bigT.algorithms.defaults and
#: bigT.acquisition.formats) imports nothing beyond the standard library (numpy
#: included: ~0.1 s).
LIGHT_HELP = tuple(_commands())


def _loaded_after(code: str) -> dict:
    """Run ``code`` in a new interpreter (stdout silenced, ``SystemExit`` caught: a
    help exits), then report which modules of :data:`HEAVY` and numpy it loaded."""
    script = (
        "import contextlib, io, json, sys\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n"
        + "".join(f"        {line}\n" for line in code.splitlines()) +
        "    except SystemExit:\n"
        "        pass\n"
        f"print(json.dumps({{m: m in sys.modules for m in {HEAVY + ('numpy',)!r}}}))\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.splitlines()[-1])


def _heavy(loaded: dict) -> list[str]:
    return [name for name in HEAVY if loaded[name]]


def test_import_bigT_loads_no_heavy_library_yet_the_api_resolves():
    loaded = _loaded_after("import bigT\nimport bigT.cli\nimport bigT.errors")
    assert _heavy(loaded) == [] and not loaded["numpy"]
    loaded = _loaded_after("import bigT\n"
                           "assert callable(bigT.open) and callable(bigT.stratified_inverse)\n"
                           "from bigT import open, stratified_inverse, BlockCSR, compensate")
    # the names resolved: their layers (the stores, scipy) are imported when first used
    assert loaded["scipy"]


def test_building_the_parser_and_the_top_help_load_no_heavy_library():
    loaded = _loaded_after("from bigT.cli import build_parser, main\n"
                           "build_parser(complete=False)\n"
                           "main(['--help'])")
    assert _heavy(loaded) == [] and not loaded["numpy"]


@pytest.mark.parametrize("command", LIGHT_HELP)
def test_a_command_help_loads_no_heavy_library(command):
    loaded = _loaded_after(f"from bigT.cli import main\nmain({command.split()!r} + ['--help'])")
    assert _heavy(loaded) == [] and not loaded["numpy"], command


def test_every_command_and_step_has_its_help_checked():
    assert {"invert", "acquire simulate", "acquire build", "compensate"} <= set(LIGHT_HELP)


@pytest.mark.parametrize("argv", [
    ["invert", "T.zarr", "-o", "X.zarr", "--terms", "-1"],
    ["invert", "T.zarr", "-o", "X.zarr", "--method", "jacobi"],
    ["acquire", "simulate", "s.zarr", "p", "-o", "c", "--camera", "4x4", "--format", "gif"],
], ids=["invert --terms -1", "invert --method jacobi", "acquire simulate --format gif"])
def test_a_bad_option_is_refused_before_any_layer_is_imported(argv):
    """Parsing a command line is light up to where the command's work starts: a bad
    value is refused (exit 2) without the engine's or the simulator's imports."""
    loaded = _loaded_after(f"from bigT.cli import main\nassert main({argv!r}) == 2")
    assert _heavy(loaded) == [] and not loaded["numpy"], argv


def test_a_deferred_parser_once_used_holds_the_options_of_the_whole_one_in_order():
    from bigT.cli import build_parser

    def options(parser, command):
        sub = next(a for a in parser._actions if a.dest == "command").choices[command]
        return [a.option_strings or [a.dest] for a in sub._actions]

    lazy = build_parser(complete=False)
    args = lazy.parse_args(["invert", "T.zarr", "-o", "X.zarr", "--terms", "3", "-q",
                            "--durability", "none"])
    assert (args.terms, args.quiet, args.durability) == (3, True, "none")
    assert options(lazy, "invert") == options(build_parser(), "invert")
    assert options(lazy, "invert")[-3:] == [["-q", "--quiet"], ["--storage-options"],
                                            ["--durability"]]


def test_the_encodings_the_cli_offers_are_the_library_s():
    from bigT import colour
    from bigT.cli.compensate_cmds import ENCODING_CHOICES

    assert ENCODING_CHOICES == ("auto", *colour.ENCODINGS)


def test_small_runs_load_no_cluster_compiler_or_plots(tmp_path):
    """The paper's 4x4 is inverted, summarised and relit on numpy twins of the kernels
    (no numba), on this process's threads (no distributed: a process that has not
    loaded it is no dask worker) and draws nothing (no matplotlib); stores bigT wrote are read
    without zarr-python (their files directly)."""
    from bigT.storage import from_scipy

    T = np.array([[1.0, .2, .1, 0], [.2, 1, 0, .1], [.1, 0, 1, .2], [0, .1, .2, 1]])
    from_scipy(sp.csr_array(T), tmp_path / "T.zarr", tile_size=4, dtype="float64",
               image_shape=(2, 2))
    np.save(tmp_path / "light.npy", np.full((2, 2), 0.5))
    runs = [["invert", "T.zarr", "-o", "X.zarr", "-q"], ["info", "X.zarr"],
            ["relight", "T.zarr", "light.npy", "-o", "seen.npy", "-q"]]
    for argv in runs:
        argv = [str(tmp_path / a) if a.endswith((".zarr", ".npy")) else a for a in argv]
        loaded = _loaded_after(f"from bigT.cli import main\nassert main({argv!r}) == 0")
        assert not {"distributed", "numba", "matplotlib", "zarr"} & set(_heavy(loaded)), argv
    assert np.allclose(np.load(tmp_path / "seen.npy").ravel(), T @ np.full(4, 0.5))


def test_writing_patterns_loads_no_store_layer(tmp_path):
    """``acquire patterns`` writes PNGs and a manifest: numpy and the image codecs, not
    the stores (zarr, scipy) that building T from the captures needs."""
    argv = ["acquire", "patterns", "--method", "stripes", "--projector", "8x8",
            "-o", str(tmp_path / "patterns")]
    loaded = _loaded_after(f"from bigT.cli import main\nassert main({argv!r}) == 0")
    assert (tmp_path / "patterns" / "manifest.json").is_file()
    assert not {"zarr", "scipy", "dask", "numba"} & set(_heavy(loaded))
