"""Crash-point loops for ``invert``, ``convert --overwrite`` and ``export`` (issue #17,
item 2), shared by ``tests/reliability/test_crash_points.py`` and
``benchmarks/bench_reliability.py``.

Each command runs in a forked child killed (``os._exit``, no cleanup) just before its
k-th file-system mutation (:mod:`crash_harness`), for each chosen k; then:

* ``invert`` is rerun and must finish with an inverse bit-identical to an
  uninterrupted run's;
* ``convert --overwrite`` and ``export`` over an existing output must leave, right
  after the crash, the old output or the new one, whole (never missing, never
  truncated), and the rerun the new one;
* nothing hidden may be left behind after the rerun (temporary files and folders of
  dead writers are cleaned by the next writer).
"""

from __future__ import annotations

import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "algorithms"))

from crash_harness import CRASH_STATUS, first_of_each_kind, run_forked  # noqa: E402
from inverse_helpers import random_dominant, store  # noqa: E402

from bigT.cli import main  # noqa: E402
from bigT.storage import open as open_store  # noqa: E402
from bigT.storage.locks import READER_LEASE, WRITER_LOCK  # noqa: E402

#: Files a finished store keeps on purpose (the locks are flock'ed, never stale).
EXPECTED_HIDDEN = {WRITER_LOCK, READER_LEASE}


@dataclass(frozen=True)
class CrashResult:
    """A crash loop's outcome.

    Attributes
    ----------
    command : the subcommand
    mutations : file-system mutations of one uninterrupted run
    kinds : distinct kinds among them (:func:`crash_harness.kind_of`)
    points : crash points tried
    problems : (point, kind, what went wrong) of each point not resumed or rolled back
    """

    command: str
    mutations: int
    kinds: int
    points: int
    problems: tuple

    @property
    def recovered(self) -> int:
        return self.points - len(self.problems)


def hidden_leftovers(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob(".*")
                  if p.name not in EXPECTED_HIDDEN)


def dense(path) -> np.ndarray:
    return open_store(path).to_scipy().toarray()


def choose(kinds: list[str], sample: int, every_point: bool, op: str = "") -> list[int]:
    """Every point, or every ``sample``-th first point of a kind (of the mutations
    ``op`` only, when given)."""
    if every_point:
        return [k for k in range(1, len(kinds) + 1) if kinds[k - 1].startswith(op)]
    return [k for k in first_of_each_kind(kinds) if kinds[k - 1].startswith(op)][::sample]


def check_invert(tmp: Path, sample: int = 1, every_point: bool = False, T=None,
                 terms: int = 2, op: str = "") -> CrashResult:
    """Crash a ``terms``-term invert of a 64 x 64 T (4 x 4 tiles; default a random
    diagonally dominant one) at its mutations (``op``'s only, when given) and resume
    it."""
    tmp.mkdir(parents=True, exist_ok=True)
    store(tmp, random_dominant(64, seed=1) if T is None else T, "T.zarr", tile_size=16)
    argv = lambda out: ["invert", str(tmp / "T.zarr"), "-o", str(out), "--terms", str(terms),
                        "-q"]
    assert main(argv(tmp / "warm.zarr")) == 0  # children start with everything imported
    status, kinds = run_forked(argv(tmp / "reference.zarr"))
    assert status == 0
    reference = dense(tmp / "reference.zarr")
    points, problems = choose(kinds, sample, every_point, op), []
    for k in points:
        out = tmp / f"crash{k}"
        out.mkdir()
        X = out / "X.zarr"
        crashed, _ = run_forked(argv(X), crash_at=k)
        resumed, _ = run_forked(argv(X))
        if crashed != CRASH_STATUS or resumed != 0:
            problems.append((k, kinds[k - 1], f"exit {crashed} then {resumed}"))
        elif not np.array_equal(dense(X), reference):
            problems.append((k, kinds[k - 1], "resumed inverse differs"))
        elif hidden_leftovers(out):
            problems.append((k, kinds[k - 1], f"left {hidden_leftovers(out)}"))
        shutil.rmtree(out)
    return CrashResult("invert", len(kinds), len(set(kinds)), len(points), tuple(problems))


def _matrix_file(tmp: Path, name: str, seed: int) -> tuple[Path, np.ndarray]:
    tmp.mkdir(parents=True, exist_ok=True)
    A = random_dominant(48, seed=seed)
    path = tmp / name
    sp.save_npz(path, sp.csr_array(A))
    return path, A


def check_convert_overwrite(tmp: Path, sample: int = 1,
                            every_point: bool = False) -> CrashResult:
    """Crash ``convert --overwrite`` over an existing store: the old store or the new
    must open right after the crash, the rerun must give the new."""
    old_file, old = _matrix_file(tmp, "old.npz", seed=2)
    new_file, new = _matrix_file(tmp, "new.npz", seed=3)
    out = tmp / "out"
    out.mkdir()
    S = out / "S.zarr"
    write_old = ["convert", str(old_file), "-o", str(S), "--tile-size", "16", "-q"]
    argv = ["convert", str(new_file), "-o", str(S), "--tile-size", "16", "--overwrite", "-q"]
    assert main(write_old) == 0
    _, kinds = run_forked(argv)
    points, problems = choose(kinds, sample, every_point), []
    for k in points:
        shutil.rmtree(S)
        assert main(write_old) == 0
        assert run_forked(argv, crash_at=k)[0] == CRASH_STATUS
        try:
            after_crash = dense(S)  # never missing: open() puts an old store back
        except Exception as exc:  # noqa: BLE001 - what a reader would meet
            problems.append((k, kinds[k - 1], f"after the crash: {exc}"))
            continue
        if not (np.allclose(after_crash, old, rtol=1e-6)
                or np.allclose(after_crash, new, rtol=1e-6)):
            problems.append((k, kinds[k - 1], "neither the old store nor the new"))
        elif run_forked(argv)[0] != 0 or not np.allclose(dense(S), new, rtol=1e-6):
            problems.append((k, kinds[k - 1], "rerun failed"))
        elif hidden_leftovers(out):
            problems.append((k, kinds[k - 1], f"left {hidden_leftovers(out)}"))
    return CrashResult("convert --overwrite", len(kinds), len(set(kinds)), len(points),
                       tuple(problems))


def check_export(tmp: Path, sample: int = 1, every_point: bool = False) -> CrashResult:
    """Crash ``export`` over an existing file: the old bytes or the complete new file."""
    _, A = _matrix_file(tmp, "A.npz", seed=4)
    S = tmp / "S.zarr"
    assert main(["convert", str(tmp / "A.npz"), "-o", str(S), "--tile-size", "16",
                 "-q"]) == 0
    out = tmp / "out"
    out.mkdir()
    target = out / "T.npz"
    old_bytes = b"the user's previous export"
    argv = ["export", str(S), "-o", str(target), "-q"]
    _, kinds = run_forked(argv)
    points, problems = choose(kinds, sample, every_point), []
    for k in points:
        target.write_bytes(old_bytes)
        assert run_forked(argv, crash_at=k)[0] == CRASH_STATUS
        if target.read_bytes() != old_bytes and not np.allclose(
                sp.load_npz(target).toarray(), A, rtol=1e-6):
            problems.append((k, kinds[k - 1], "neither the old file nor the new"))
        elif run_forked(argv)[0] != 0 or not np.allclose(sp.load_npz(target).toarray(), A,
                                                          rtol=1e-6):
            problems.append((k, kinds[k - 1], "rerun failed"))
        elif hidden_leftovers(out):
            problems.append((k, kinds[k - 1], f"left {hidden_leftovers(out)}"))
    return CrashResult("export", len(kinds), len(set(kinds)), len(points), tuple(problems))
