"""docs/FORMAT.md lists the keys that bigT writes, and no other: each key table is
compared, both ways, with what freshly written stores hold.

The doc's rule (stated where its first key table is): a key table is a Markdown table
whose header's first cell names its record in a code span, ``key of `bigT_inverse` ``;
the first cell of each row holds the key (several, comma-separated, are allowed). A
record is a path through the JSON attributes of a ``zarr.json``: the attribute
(``bigT``, ``bigT_row``, ``bigT_inverse``, ``bigT_scene``), then the keys of nested
objects (``bigT_inverse.params.T``), ``[]`` for the objects in a list
(``bigT_inverse.history[]``).

The stores written here: a plain store (:func:`bigT.storage.from_scipy`, with every
optional attribute), a scene (:func:`bigT.scenes.corner`), a colour scene
(:func:`bigT.scenes.cornell`, its global mixing in T's metadata) and the first's inverse
(:func:`bigT.algorithms.stratified_inverse`, power form with the feed and operator
thresholds, so that the fingerprint holds them), and a colour T with a recorded global
mixing and its inverse by the global-mixing path.
Every record found in them must have a table (or be one of :data:`FREE` or
:data:`SAME_AS`), and every table must be a record found.

``BIGT_DOCS=/some/dir`` checks ``/some/dir/FORMAT.md`` instead of docs/.
"""

from __future__ import annotations

import json
import os
import re
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[2]
DOC = Path(os.environ.get("BIGT_DOCS", ROOT / "docs")) / "FORMAT.md"

#: Free JSON: its keys are the writer's choice (the sub-records named below are checked).
FREE = {"bigT.metadata"}
#: Records that repeat another (the doc says so in words): checked against its table.
SAME_AS = {"bigT.metadata.scene": "bigT_scene",
           "bigT.metadata.inverse.record": "bigT_inverse.history[]",
           "bigT.metadata.inverse.record.tasks[]": "bigT_inverse.history[].tasks[]",
           "bigT.metadata.inverse.mixing": "bigT_inverse.mixing",
           "bigT_inverse.params.mixing": "bigT.metadata.mixing"}

_SPAN = re.compile(r"`([^`]+)`")
_HEADER = re.compile(r"^\|\s*key of `(?P<record>[^`]+)`\s*\|")


# --- the doc's side -------------------------------------------------------------------

def doc_tables(path: Path = DOC) -> dict[str, dict[str, int]]:
    """{record: {key: doc line}} from the key tables of the doc."""
    tables: dict[str, dict[str, int]] = {}
    record = None
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        header = _HEADER.match(line)
        if header:
            record = header["record"]
            assert record not in tables, f"{path.name}:{number}: a second table for {record}"
            tables[record] = {}
            continue
        if record is None:
            continue
        if not line.startswith("|"):
            record = None  # the table ended
            continue
        first = line.strip().strip("|").split("|")[0]
        if set(first.strip()) <= set("-: "):
            continue  # the separator row
        keys = _SPAN.findall(first)
        assert keys, f"{path.name}:{number}: a row of the {record} table names no `key`"
        for key in keys:
            tables[record][key] = number
    return tables


# --- the code's side ------------------------------------------------------------------

def collect(record: str, obj: dict, found: dict[str, set]) -> None:
    """Add the keys of ``obj`` to ``found[record]``, and those of its nested objects."""
    found[record] |= set(obj)
    for key, value in obj.items():
        if isinstance(value, dict):
            collect(f"{record}.{key}", value, found)
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for item in value:
                collect(f"{record}.{key}[]", item, found)


def written_records(*roots: Path) -> dict[str, set]:
    """{record: keys} over every zarr.json below ``roots``."""
    found: dict[str, set] = defaultdict(set)
    for root in roots:
        for meta in sorted(root.rglob("zarr.json")):
            attributes = json.loads(meta.read_text()).get("attributes") or {}
            for name, value in attributes.items():
                if isinstance(value, dict):
                    collect(name, value, found)
                else:
                    found[name] |= set()  # an attribute that is not an object: a record too
    return dict(found)


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """The stores of the module docstring, written once: (plain, scene T, inverse,
    colour T, its global-path inverse)."""
    import bigT
    from bigT import scenes

    tmp = tmp_path_factory.mktemp("format")
    A = sp.random(144, 144, density=0.05, random_state=0, format="csr") + sp.eye(144)
    plain = tmp / "plain.zarr"  # a colour one: it writes every key a plain store can have
    bigT.from_scipy(A, plain, tile_size=48, image_shape=(6, 8), pixel_order="tile-major",
                    image_tile=(2, 4), metadata={"note": "free JSON"}, channels=3)
    scene = tmp / "T.zarr"
    scenes.corner(size=(4, 6), path=scene, preview=False)
    scenes.cornell(size=(4, 6), path=tmp / "colour" / "T.zarr", preview=False, colour=True)
    inverse = tmp / "X.zarr"
    bigT.stratified_inverse(scene, inverse, terms=2, prune_feed=1e-4, prune_operator=1e-4,
                            progress=False)
    colour, colour_inverse = tmp / "T3.zarr", tmp / "X3.zarr"  # the global-mixing path
    mixing = np.array([[0.9, 0.1, 0.0], [0.1, 0.8, 0.1], [0.0, 0.1, 0.9]])
    grey = sp.random(24, 24, density=0.1, random_state=1, format="csr") + 4 * sp.eye(24)
    bigT.from_scipy(sp.kron(grey, mixing @ mixing), colour, tile_size=24, image_shape=(4, 6),
                    channels=3, metadata={"mixing": {"camera": mixing.tolist(),
                                                     "projector": mixing.tolist()}})
    bigT.stratified_inverse(colour, colour_inverse, terms=1, progress=False, in_memory=True)
    return plain, scene, inverse, colour, colour_inverse


@pytest.fixture(scope="module")
def records(stores):
    return written_records(*stores, stores[0].parent / "colour")


# --- the checks -----------------------------------------------------------------------

def test_every_documented_key_is_written(records):
    tables = doc_tables()
    problems = []
    for record, keys in tables.items():
        written = records.get(record)
        if written is None:
            problems.append(f"{DOC.name}: table for {record}, a record none of the stores "
                            f"written holds (they hold {', '.join(sorted(records))})")
            continue
        for key, line in keys.items():
            if key not in written:
                problems.append(f"{DOC.name}:{line}: {record} key `{key}` is not written")
    assert not problems, "\n".join(problems)


def test_every_written_key_is_documented(records):
    tables = doc_tables()
    problems = []
    for record, written in sorted(records.items()):
        if record in FREE:
            continue
        name = SAME_AS.get(record, record)
        table = tables.get(name)
        if table is None and record in SAME_AS:
            continue  # reported for the record it repeats
        if table is None:
            problems.append(f"{DOC.name}: no `key of `{name}`` table; the code writes "
                            f"{', '.join(sorted(written))}")
            continue
        for key in sorted(written - set(table)):
            problems.append(f"{DOC.name}: {record} key `{key}` is written but not documented")
        if record in SAME_AS:  # a repeat holds all of its original's keys
            for key in sorted(set(table) - written):
                problems.append(f"{record} lacks `{key}` of the {SAME_AS[record]} it repeats")
    assert not problems, "\n".join(problems)


def test_the_stores_hold_every_kind_of_record(records):
    """The stores above exercise what the doc describes (else the two tests above would
    pass on a doc without tables): store and redirect roots, row markers, the inverse
    record with its fingerprint and history, the term stores' records, the scene."""
    for record in ("bigT", "bigT_row", "bigT_inverse", "bigT_inverse.params",
                   "bigT_inverse.params.T", "bigT_inverse.history[]",
                   "bigT.metadata.inverse", "bigT.metadata.inverse.record", "bigT_scene",
                   "bigT.metadata.scene"):
        assert record in records, record
    assert {"redirect", "image_tile"} <= records["bigT"]
    assert {"prune_feed", "prune_operator"} <= records["bigT_inverse.params"]
    assert records["bigT_inverse.mixing"] and "colour_path" in records["bigT_inverse"]


def test_the_paper_scene_writes_documented_keys_only(tmp_path):
    """dihedral4's summary is made apart from the built scenes': a subset of theirs."""
    from bigT import scenes

    scenes.dihedral4(path=tmp_path / "D.zarr", preview=False)
    found = written_records(tmp_path / "D.zarr")
    tables = doc_tables()
    assert "bigT_scene" in tables, f"{DOC.name}: no `key of `bigT_scene`` table"
    documented = set(tables["bigT_scene"])
    assert found["bigT_scene"] <= documented, sorted(found["bigT_scene"] - documented)
