"""Errors carry the option they concern: Python names the argument, the CLI the flag."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.cli import main
from bigT.errors import UNSET, BigTError, Option, StoreError


def test_option_spelt_as_argument_and_as_flag():
    e = StoreError("already exists; pass {option} to replace it", "T.zarr",
                   option=("overwrite", True))
    assert str(e) == "T.zarr: already exists; pass overwrite=True to replace it"
    assert e.render() == "T.zarr: already exists; pass --overwrite to replace it"
    assert e.option == Option("overwrite", True) and e.path == "T.zarr"
    e = BigTError("pass {option}", option=("first_bounce", "identity"))
    assert str(e) == "pass first_bounce='identity'"
    assert e.render() == "pass --first-bounce identity"
    e = BigTError("{option} 64 MiB is too small", option="memory_limit")
    assert e.option.value is UNSET and str(e) == "memory_limit 64 MiB is too small"
    # the command's own flag for the argument (a renamed option) wins
    assert e.render(lambda name: "--resident-limit") == "--resident-limit 64 MiB is too small"
    # an argument the command line has no flag for: what its user does instead
    e = BigTError("to resume: {option}", option=Option("resume", cli="rerun the same command"))
    assert (str(e), e.render()) == ("to resume: resume=True",
                                    "to resume: rerun the same command")


def test_errors_survive_pickling_with_their_option():
    """dask sends errors between processes."""
    e = pickle.loads(pickle.dumps(StoreError("pass {option}", "p", option=("force", True))))
    assert type(e) is StoreError and e.option == Option("force", True)
    assert str(e) == "p: pass force=True" and e.render() == "p: pass --force"


def test_a_library_error_names_the_argument_and_the_cli_the_flag(tmp_path, capsys):
    A = sp.identity(6, format="csr")
    bigT.from_scipy(A, tmp_path / "T.zarr")
    with pytest.raises(StoreError) as caught:
        bigT.from_scipy(A, tmp_path / "T.zarr")
    assert "pass overwrite=True to replace it" in str(caught.value)
    assert "--" not in str(caught.value)
    np.save(tmp_path / "a.npy", A.toarray())
    assert main(["convert", str(tmp_path / "a.npy"), "-o", str(tmp_path / "T.zarr")]) == 2
    err = capsys.readouterr().err
    assert "pass --overwrite to replace it" in err and "overwrite=True" not in err


def test_no_library_message_embeds_a_flag():
    """The check of the issue: no ``"... --flag"`` string in a library raise or warning
    (descriptions and docstrings of command-line options aside)."""
    import pathlib
    import re

    root = pathlib.Path(bigT.__file__).parent
    found = []
    for path in root.rglob("*.py"):
        if "cli" in path.parts or path.name == "testing.py":
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if (re.search(r'"[^"]*--[a-z]', line) and "cli=" not in line  # Option's CLI words
                    and not line.strip().startswith(('"""', "#", "``"))):
                found.append(f"{path.relative_to(root)}:{n}: {line.strip()}")
    allowed = ("acquisition/build.py",)  # describe(): '--black NAME' in a report line
    assert [f for f in found if not f.startswith(allowed)] == []
