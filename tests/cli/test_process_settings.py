"""What the ``bigT`` command sets for its own process before a layer is imported."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[2]


def _huge_pages_advised_after_a_command(tmp_path: Path, setting: str | None) -> bool:
    """Run ``bigT info`` through :func:`bigT.cli.main` in a new interpreter whose
    environment has ``NUMPY_MADVISE_HUGEPAGE`` = ``setting`` (unset: None); whether
    numpy then advises huge pages for its large arrays."""
    from bigT.storage import from_scipy

    store = tmp_path / "T.zarr"
    if not store.exists():
        from_scipy(sp.csr_array(np.eye(4)), store, tile_size=4)
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    if setting is not None:
        env["NUMPY_MADVISE_HUGEPAGE"] = setting
    script = ("import contextlib, io, sys\n"
              "from bigT.cli import main\n"
              "with contextlib.redirect_stdout(io.StringIO()):\n"
              f"    assert main(['info', {str(store)!r}]) == 0\n"
              "assert 'numpy' in sys.modules\n"
              "try:\n"
              "    from numpy._core.multiarray import _get_madvise_hugepage\n"
              "except ImportError:  # numpy 1.x\n"
              "    from numpy.core.multiarray import _get_madvise_hugepage\n"
              "print(_get_madvise_hugepage())\n")
    proc = subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.split()[-1] == "True"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="numpy advises on Linux only")
def test_a_command_asks_numpy_for_no_huge_pages_unless_the_environment_says(tmp_path):
    """numpy advises huge pages for arrays of 4 MiB and more; where the kernel then
    compacts memory before a fault (defrag ``madvise``) the first touch of fresh
    memory cost 3-4x (bigT.cli._advise_no_huge_pages). The command turns it off for
    itself, and leaves a user's own setting alone."""
    assert not _huge_pages_advised_after_a_command(tmp_path, None)
    assert not _huge_pages_advised_after_a_command(tmp_path, "0")
    assert _huge_pages_advised_after_a_command(tmp_path, "1")


def test_a_caller_that_imported_numpy_keeps_its_environment(monkeypatch):
    """main() called from Python after numpy was imported changes nothing: the switch
    is read at numpy's import, and the caller's later child processes keep its own
    environment."""
    from bigT.cli import _advise_no_huge_pages

    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    assert "numpy" in sys.modules
    _advise_no_huge_pages()
    assert "NUMPY_MADVISE_HUGEPAGE" not in os.environ
