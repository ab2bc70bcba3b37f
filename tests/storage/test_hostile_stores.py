"""Stores crafted as an adversary would (issue #33, points 1-3): every read is bounded
by what the store declares and that by sense, no symbolic link below a store's root is
followed, every malformed metadata value ends in one line naming the file.

Checksums are recomputed wherever the point is that they pass.
"""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import google_crc32c
import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numcodecs.zstd import compress

import bigT
from bigT.cli import main
from bigT.errors import BigTError, CorruptStoreError, StoreError
from bigT.storage import _format as fmt

TS = 4


def _matrix():
    A = sp.random(10, 10, density=0.4, random_state=np.random.default_rng(3), format="csr")
    return sp.csr_array(A + sp.eye(10))


@pytest.fixture
def store(tmp_path):
    path = tmp_path / "s.zarr"
    bigT.storage.from_scipy(_matrix(), path, tile_size=TS)
    return path


def _write_chunk(chunk_file: Path, frame: bytes) -> None:
    """A chunk file holding ``frame`` with its crc32c recomputed: the checksum passes."""
    crc = np.uint32(google_crc32c.value(frame)).astype("<u4").tobytes()
    chunk_file.write_bytes(frame + crc)


def _edit_json(path: Path, edit) -> None:
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def _edit_attrs(store: Path, **changes) -> None:
    _edit_json(store / "zarr.json", lambda m: m["attributes"]["bigT"].update(changes))


def _one_line_error(store: Path, capsys, *commands) -> None:
    """``bigT info/verify/export`` each exit 2 with one line naming a file of ``store``."""
    for command in commands or ("info", "verify", "export"):
        args = [command, str(store)] + (["-o", str(store.parent / "out.npz")]
                                        if command == "export" else [])
        capsys.readouterr()
        assert main(args) == 2, command
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert str(store) in err and "Traceback" not in err


def _every_reader(store: Path) -> None:
    """Run every reader, each of which must raise a BigTError (pytest.raises below)."""
    A = bigT.open(store)
    A.info()
    A.verify()
    for i in range(A.grid[0]):
        A.get_tile_row(i)
    A.to_scipy()


# --- 1. bounded by what the store declares ------------------------------------------

_BOUNDED_READ = textwrap.dedent("""
    import resource, sys
    limit = 600 << 20  # address space: far below what the hostile header claims
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    import bigT
    from bigT.errors import BigTError
    try:
        A = bigT.open(sys.argv[1], allow_incomplete=True)
        A.info(); A.verify()
        [A.get_tile_row(i) for i in range(A.grid[0])]
    except BigTError as exc:
        print("BigTError:", exc)
        sys.exit(0)
    print("read")
    sys.exit(1)
""")


def _read_under_memory_limit(store: Path) -> str:
    """The one-line error of reading ``store`` in a process limited to 600 MiB of
    address space (a MemoryError or a kill fails the test)."""
    proc = subprocess.run([sys.executable, "-c", _BOUNDED_READ, str(store)],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "NUMBA_DISABLE_JIT": "0"})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout.strip()


def test_zstd_bomb_in_a_tile_fails_within_its_declared_size(store, capsys):
    """A tile row's data chunk replaced by a frame of 2 GiB of zeros (a few KB on disk,
    valid checksum): refused from the frame header, memory stays far below."""
    chunk = store / "rows/0/data/c/0"
    _write_chunk(chunk, compress(bytes(256 << 20), 19) * 8)  # 8 frames of 256 MiB
    assert chunk.stat().st_size < 1 << 20
    # a frame file longer than any frame of the chunk's size is refused unread
    assert "rows/0/data/c/0 is larger than" in _read_under_memory_limit(store)
    _one_line_error(store, capsys)
    # a small one (1 MiB of zeros, 30 bytes) is refused from its header, undecoded
    _write_chunk(chunk, compress(bytes(1 << 20), 1))
    with pytest.raises(CorruptStoreError, match="c/0 decompresses to 1048576 bytes"):
        bigT.open(store).get_tile_row(0)
    _one_line_error(store, capsys)


def test_zstd_frame_without_a_size_is_decoded_into_the_chunk_only(store):
    """A frame whose header declares no content size (a streaming writer's) and holds
    far more than the chunk: decoding stops at the chunk's size."""
    frame = compress(bytes(1 << 12), 1)
    descriptor = frame[4]
    fcs = (1 if descriptor & 0x20 else 0, 2, 4, 8)[descriptor >> 6]
    header = 5 + (0 if descriptor & 0x20 else 1) + (0, 1, 2, 4)[descriptor & 3] + fcs
    # no size, no single segment: a window descriptor of 2^27 bytes instead
    _write_chunk(store / "rows/0/data/c/0", frame[:4] + bytes([descriptor & 0x04, 17 << 3])
                 + frame[header:])
    with pytest.raises(CorruptStoreError, match="Destination buffer is too small"):
        bigT.open(store).get_tile_row(0)


def test_index_array_declaring_huge_length_refused_before_allocation(store, capsys):
    _edit_json(store / "tile_indices/zarr.json", lambda m: m.update(shape=[700_000_000]))
    assert "declares 700000000 entries" in _read_under_memory_limit(store)
    _one_line_error(store, capsys)


def test_chunk_longer_than_its_array_refused(store):
    _edit_json(store / "rows/0/data/zarr.json", lambda m: m["chunk_grid"]["configuration"]
               .update(chunk_shape=[1 << 30]))
    with pytest.raises(CorruptStoreError, match="chunk length"):
        bigT.open(store).get_tile_row(0)


def test_incomplete_store_of_a_trillion_pixels_costs_what_it_holds(store, capsys):
    """An incomplete store declaring 10^12 rows, or 2^32 rows of tile size 1: refused
    as beyond sense at once. At tile size 2^12 (2^20 tile rows, within sense) the row
    scan reads the three rows on disk, not 2^20 markers."""
    _edit_attrs(store, shape=[10**12, 10**12], complete=False, nnz=None)
    assert "out of range" in _read_under_memory_limit(store)
    _edit_attrs(store, shape=[2**32, 2**32], tile_size=1)
    assert "more than bigT reads" in _read_under_memory_limit(store)
    _one_line_error(store, capsys, "info")
    _edit_attrs(store, tile_size=1 << 12)
    import time
    start = time.perf_counter()
    A = bigT.open(store, allow_incomplete=True)
    assert len(A.missing_tile_rows) == (1 << 20) - 3
    assert time.perf_counter() - start < 5  # ~0.1 s; one marker read a row would be minutes
    with pytest.raises(CorruptStoreError, match="declares 5 entries"):  # tile row 0's indptr
        A.get_tile_row(0)


def test_incomplete_scan_counts_from_the_listing(store):
    for i in (1, 2):
        os.rename(store / f"rows/{i}", store / f"rows/.{i}.gone")
    _edit_attrs(store, complete=False, nnz=None)
    A = bigT.open(store, allow_incomplete=True)
    assert A.missing_tile_rows == [1, 2]
    assert A.get_tile_row(1).nnz == 0 and A.get_tile_row(0).nnz > 0


def test_metadata_file_that_never_ends_is_refused(store, capsys):
    """A zarr.json past 8 MiB (a FIFO nobody writes would block: a regular file with
    no end in sight stands for it) is refused after reading 8 MiB + 1."""
    with open(store / "zarr.json", "ab") as f:
        f.write(b" " * (fmt.METADATA_MAX_BYTES + 1))
    with pytest.raises(StoreError, match="larger than"):
        bigT.open(store)
    _one_line_error(store, capsys, "info")


def test_metadata_fifo_is_refused_without_waiting(store, capsys):
    """A FIFO in a zarr.json's place: no writer will ever come; refused at once."""
    (store / "rows/0/indptr/zarr.json").unlink()
    os.mkfifo(store / "rows/0/indptr/zarr.json")
    with pytest.raises(CorruptStoreError, match="not a regular file"):
        bigT.open(store).get_tile_row(0)
    _one_line_error(store, capsys)


@pytest.mark.parametrize("attrs", [
    {"nnz": 10**9},                     # more entries than the matrix has
    {"shape": [2**40, 2**40]},          # beyond sense
    {"tile_size": 0},
    {"image_shape": [3, 3]},            # 9 pixels for a 10 x 10 matrix
])
def test_declared_sizes_checked_against_shape(store, attrs, capsys):
    _edit_attrs(store, **attrs)
    with pytest.raises(CorruptStoreError, match="zarr.json|s.zarr"):
        bigT.open(store)
    _one_line_error(store, capsys, "info")


def test_tile_nnz_larger_than_its_tile_refused(store):
    A = bigT.open(store)
    k = 0
    nnz = np.asarray(A.tile_nnz).copy()
    nnz[k] = TS * TS + 1
    fmt.write_array_files(store, "tile_nnz", nnz, fmt.FILL_INT)
    _edit_attrs(store, nnz=int(nnz.sum()))
    with pytest.raises(CorruptStoreError, match="larger than their tile"):
        bigT.open(store)


# --- 2. a store is a closed world -------------------------------------------------------

def _outside_copy(store: Path, rel: str) -> Path:
    """A copy of ``store/rel`` outside the store, and ``store/rel`` a link to it."""
    import shutil

    target = store.parent / ("outside_" + rel.replace("/", "_"))
    shutil.copytree(store / rel, target) if (store / rel).is_dir() else shutil.copy(store / rel, target)
    shutil.rmtree(store / rel) if (store / rel).is_dir() else (store / rel).unlink()
    os.symlink(target, store / rel)
    return target


@pytest.mark.parametrize("rel", ["rows", "rows/1", "rows/0", "rows/0/data",
                                 "rows/0/indices/c/0", "tile_indptr", "tile_nnz/c/0"])
def test_link_inside_a_store_is_refused(store, rel, capsys):
    _outside_copy(store, rel)
    with pytest.raises(CorruptStoreError, match=f"{rel} is a symbolic link"):
        _every_reader(store)
    _one_line_error(store, capsys)


def test_link_in_an_unread_place_is_damage_verify_reports(store, capsys):
    os.symlink("/etc", store / "rows/0/extra")
    bigT.open(store).get_tile_row(0)  # not a tile: readers never look at it
    with pytest.raises(CorruptStoreError, match="rows/0/extra is a symbolic link"):
        bigT.open(store).verify()
    _one_line_error(store, capsys, "verify")


def test_root_may_itself_be_a_link(store, tmp_path):
    os.symlink(store, tmp_path / "alias.zarr")
    assert bigT.open(tmp_path / "alias.zarr").verify()["nnz"] == _matrix().nnz


def _versioned(tmp_path: Path) -> Path:
    """A root redirecting to ``terms/1`` (a copy of a plain store)."""
    root = tmp_path / "v.zarr"
    bigT.storage.from_scipy(_matrix(), root / "terms/1", tile_size=TS)
    (root / "zarr.json").write_text(json.dumps(fmt.group_json(
        {"bigT": {"format": fmt.FORMAT_NAME, "version": 1, "redirect": "terms/1"}})))
    (root / "terms/zarr.json").write_text(json.dumps(fmt.group_json({})))
    return root


def test_term_behind_the_redirect_through_a_link_is_refused(tmp_path, capsys):
    root = _versioned(tmp_path)
    assert bigT.open(root).verify()["nnz"] == _matrix().nnz
    _outside_copy(root, "terms")
    with pytest.raises(CorruptStoreError, match="terms is a symbolic link"):
        bigT.open(root)
    _one_line_error(root, capsys)


def test_deleting_a_store_never_follows_a_link_out(tmp_path):
    from bigT.storage.inverse_store import InverseStore
    from bigT.storage.locks import remove_unless_read

    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "precious").write_text("keep")
    (outside / ".lease").touch()
    inverse = tmp_path / "X.zarr"
    (inverse / "t0001").mkdir(parents=True)
    os.symlink(outside, inverse / "t0001" / "X")
    os.symlink(outside, inverse / "t0002")
    assert remove_unless_read(inverse / "t0001")
    assert remove_unless_read(inverse / "t0002")
    store = InverseStore(inverse)
    os.symlink(outside, inverse / "t0003")
    store._delete_contents()  # what --overwrite runs, the writer lock held
    assert (outside / "precious").read_text() == "keep"
    assert not (inverse / "t0003").exists()  # the link went, as itself


# --- 3. every malformed metadata value is one line --------------------------------------

@pytest.mark.parametrize("field, value", [
    ("shape", [3.5, 10]), ("shape", [10.0, 10]), ("shape", "10x10"), ("shape", [True, 10]),
    ("tile_size", 2.5), ("tile_size", "4"), ("nnz", 3.5), ("nnz", [1]),
    ("dtype", "float32\x00"), ("dtype", 32), ("complete", "yes"), ("version", 1.0),
    ("version", True), ("metadata", [1]), ("image_shape", [2.5, 4]),
    ("pixel_order", 7), ("image_tile", ["a", 1]), ("image_tile", [0, 1]),
    ("inner_format", {"csr": 1}),
])
def test_wrong_json_type_is_one_line(store, field, value, capsys):
    _edit_attrs(store, **{"image_shape": [2, 5], field: value})
    with pytest.raises(StoreError, match="s.zarr"):
        bigT.open(store)
    _one_line_error(store, capsys, "info")


@pytest.mark.parametrize("redirect", [3, None, ["terms/1"], "terms/1\x00", {"a": 1}])
def test_redirect_of_the_wrong_type_is_one_line(tmp_path, redirect, capsys):
    root = _versioned(tmp_path)
    _edit_attrs(root, redirect=redirect)
    with pytest.raises(StoreError, match="redirect|zarr.json"):
        bigT.open(root)
    _one_line_error(root, capsys, "info")


@pytest.mark.parametrize("target", ["zarr.json", "rows/0/zarr.json", "rows/0/data/zarr.json",
                                    "tile_indptr/zarr.json"])
def test_json_nested_past_the_recursion_limit_is_one_line(store, target, capsys):
    (store / target).write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(BigTError):
        _every_reader(store)
    _one_line_error(store, capsys, "verify")


def test_row_marker_of_the_wrong_types_is_one_line(store, capsys):
    _edit_attrs(store, complete=False, nnz=None)
    _edit_json(store / "rows/1/zarr.json",
               lambda m: m["attributes"]["bigT_row"].update(tile_columns=[0.5]))
    with pytest.raises(CorruptStoreError, match="rows/1/zarr.json"):
        bigT.open(store, allow_incomplete=True)


@pytest.mark.parametrize("indices", [[1, 0], [0, 0]], ids=["unsorted", "duplicate"])
def test_unsorted_or_duplicate_tile_indices_refused_by_every_reader(tmp_path, indices, capsys):
    """A tile whose row holds columns [1, 0] or [0, 0], written with valid checksums."""
    A = sp.csr_array(np.array([[1.0, 2.0], [0.0, 3.0]]))
    path = tmp_path / "s.zarr"
    bigT.storage.from_scipy(A, path, tile_size=2)
    fmt.write_array_files(path / "rows/0", "indices", np.array(indices + [1], np.int32),
                          fmt.FILL_INT)
    for read in (lambda S: S.get_tile_row(0), lambda S: S.to_scipy(), lambda S: S.get_tile(0, 0),
                 lambda S: S.matmul(np.ones(2)), lambda S: S.info(), lambda S: S.verify()):
        with pytest.raises(CorruptStoreError, match="not sorted and duplicate-free"):
            read(bigT.open(path))
    _one_line_error(path, capsys)


# --- fuzz: mutate a valid store, every read ends in a result or a bigT error -----------

_JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=False)
    | st.text(max_size=8), lambda kids: st.lists(kids, max_size=3)
    | st.dictionaries(st.text(max_size=4), kids, max_size=3), max_leaves=6)

_ARRAYS = [f"{base}/{name}" for base in ("rows/0", "rows/1", "rows/2") for name in fmt.TILE_ARRAYS] \
    + list(fmt.INDEX_ARRAYS)
_ROOT_KEYS = ["shape", "tile_size", "dtype", "nnz", "complete", "version", "metadata",
              "image_shape", "pixel_order", "image_tile", "inner_format", "redirect", "format"]


@st.composite
def _mutations(draw):
    kind = draw(st.sampled_from(["root", "array_meta", "chunk", "marker"]))
    if kind == "root":
        return kind, draw(st.sampled_from(_ROOT_KEYS)), draw(_JSON_VALUES)
    if kind == "array_meta":
        key = draw(st.sampled_from(["shape", "data_type", "fill_value", "chunk_grid", "codecs"]))
        return kind, (draw(st.sampled_from(_ARRAYS)), key), draw(_JSON_VALUES)
    if kind == "marker":
        key = draw(st.sampled_from(["tile_columns", "tile_nnz", "complete"]))
        return kind, (draw(st.integers(0, 2)), key), draw(_JSON_VALUES)
    values = draw(st.lists(st.integers(-2**31, 2**31 - 1), min_size=0, max_size=40))
    return kind, draw(st.sampled_from(_ARRAYS)), values


def _apply(store: Path, mutation) -> None:
    kind, where, value = mutation
    if kind == "root":
        _edit_attrs(store, **{where: value})
    elif kind == "array_meta":
        _edit_json(store / where[0] / "zarr.json", lambda m: m.update({where[1]: value}))
    elif kind == "marker":
        _edit_attrs(store, complete=False, nnz=None)
        _edit_json(store / f"rows/{where[0]}/zarr.json",
                   lambda m: m["attributes"]["bigT_row"].update({where[1]: value}))
    else:
        dtype = json.loads((store / where / "zarr.json").read_text())["data_type"]
        raw = np.asarray(value).astype(dtype).tobytes()
        _write_chunk(store / where / "c/0", compress(raw, 1))


#: what the fuzz cases ended in, for a report (``python -c`` over the test)
OUTCOMES: dict[str, int] = {}
CHANGED: list = []


def _fuzz_case(tmp_path_factory, mutation) -> None:
    import shutil

    template = tmp_path_factory.getbasetemp() / "fuzz_template.zarr"
    if not template.exists():
        bigT.storage.from_scipy(_matrix(), template, tile_size=TS)
    store = tmp_path_factory.mktemp("fuzz") / "s.zarr"
    shutil.copytree(template, store)
    _apply(store, mutation)
    expected = _matrix().toarray()
    try:
        A = bigT.open(store, allow_incomplete=True)
        A.info()
        got = A.to_scipy().toarray()
        A.verify()
    except BigTError as exc:
        assert "\n" not in str(exc)
        _count("bigT error")
        return
    for i in A.missing_tile_rows:  # a marker no longer complete: the row reads as empty
        expected[i * TS:(i + 1) * TS] = 0
    if got.shape == expected.shape and np.allclose(got, expected, rtol=1e-6, atol=0):
        _count("the matrix written" + (", rows lost marked missing" if A.missing_tile_rows else ""))
    else:  # every check passed on a matrix other than the one written (reported)
        _count("another matrix that passes every check")
        CHANGED.append(mutation)


def _count(outcome: str) -> None:
    OUTCOMES[outcome] = OUTCOMES.get(outcome, 0) + 1


_FUZZ = settings(max_examples=40, deadline=None, database=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture,
                                        HealthCheck.too_slow])


@_FUZZ
@given(mutation=_mutations())
def test_fuzz_mutated_store_reads_or_fails_in_one_line(tmp_path_factory, mutation):
    _fuzz_case(tmp_path_factory, mutation)


@pytest.mark.slow
@settings(_FUZZ, max_examples=2000)
@given(mutation=_mutations())
def test_fuzz_mutated_store_many(tmp_path_factory, mutation):
    _fuzz_case(tmp_path_factory, mutation)

