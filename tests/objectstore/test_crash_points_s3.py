"""Crash points in object storage: ``bigT invert`` with T and X in a bucket (moto on
127.0.0.1) killed just before each kind of object write (a row's objects, its marker,
the redirect, the record, the lock, the deletion of a dropped term), then rerun: the
inverse is bit-identical to an uninterrupted run's, and nothing is left but the
current term (no lock object, no row without its marker, no dropped term)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.storage import as_location, from_scipy

sys.path.insert(0, str(Path(__file__).parents[1] / "algorithms"))
from inverse_helpers import random_dominant  # noqa: E402

CHILD = Path(__file__).with_name("crash_child.py")
#: Every SAMPLE-th kind of crash point by default; all kinds with -m slow.
SAMPLE = 22


def _run(k: int, argv: list[str], tmp: Path) -> tuple[int, list[str]]:
    kinds = tmp / f"kinds-{k}.json"
    proc = subprocess.run([sys.executable, str(CHILD), str(k), str(kinds), *argv],
                          capture_output=True, text=True, env=dict(os.environ), timeout=300)
    return proc.returncode, (json.loads(kinds.read_text()) if kinds.exists() else [])


def _first_of_each_kind(kinds: list[str]) -> list[int]:
    seen, points = set(), []
    for k, kind in enumerate(kinds, start=1):
        if kind not in seen:
            seen.add(kind)
            points.append(k)
    return points


def _leftovers(url: str) -> list[str]:
    """Keys of the inverse at ``url`` outside its root record and its current term's
    directory (X and the term's product P): a lock, a dropped term, litter."""
    root = as_location(url)
    term = bigT.open(url).path.parent.relative_to(root).as_posix()
    keys = [k[len(root.key) + 1:] for k, _ in root.walk_objects()]
    lock = root / ".bigT-writer.lock"
    released = lock.is_file() and json.loads(lock.read_bytes())["released"] is True
    return [k for k in keys if k != "zarr.json" and not k.startswith(term + "/")
            and not (k == lock.name and released)]


@pytest.mark.parametrize("sample", [SAMPLE, pytest.param(1, marks=pytest.mark.slow)])
def test_invert_in_a_bucket_resumes_bit_identically_after_a_crash(s3, s3_url, tmp_path, sample):
    T_url = f"{s3_url}/T.zarr"
    from_scipy(sp.csr_array(random_dominant(64, seed=1)), T_url, tile_size=16, dtype="float64")
    argv = lambda out: ["invert", T_url, "-o", out, "--terms", "2", "--prune", "1e-5", "-q"]
    status, kinds = _run(0, argv(f"{s3_url}/reference.zarr"), tmp_path)
    assert status == 0 and len(kinds) > 50
    reference = bigT.open(f"{s3_url}/reference.zarr").to_scipy().toarray()
    points = _first_of_each_kind(kinds)[::sample]
    problems = []
    for k in points:
        out = f"{s3_url}/crash{k}/X.zarr"
        crashed, _ = _run(k, argv(out), tmp_path)
        resumed, _ = _run(0, argv(out), tmp_path)
        if crashed != 137 or resumed != 0:
            problems.append((k, kinds[k - 1], f"exit {crashed} then {resumed}"))
        elif not np.array_equal(bigT.open(out).to_scipy().toarray(), reference):
            problems.append((k, kinds[k - 1], "resumed inverse differs"))
        elif _leftovers(out):
            problems.append((k, kinds[k - 1], f"left {_leftovers(out)[:3]}"))
    assert len(points) >= 3
    assert not problems, f"{len(problems)} of {len(points)} crash points: {problems[:5]}"
