"""Store format 2 (docs/FORMAT.md): a tile row is one group of three 1-D arrays
(``indptr``, ``indices`` with global columns, ``data``), each one chunk file.

Checked against scipy.sparse: the files a written store holds, that a format-1 store
(a group per tile, local columns; built here by zarr-python alone, as bigT up to
2789f82 wrote it) still reads as its matrix while writers refuse to add to it, and
that other zarr v3 readers (zarr-python, tensorstore) read a row's arrays as the
matrix's rows.
"""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import zarr
from zarr.codecs import BytesCodec, Crc32cCodec, ZstdCodec
from zarr.storage import LocalStore

from bigT import config
from bigT.cli import main
from bigT.errors import CorruptStoreError, StoreError
from bigT.storage import (
    BlockCSRWriter,
    KeptTiles,
    StoreAttrs,
    create_store,
    finalize_store,
    from_scipy,
    read_store_attrs,
    write_tile_row,
)
from bigT.storage import open as open_store

N, TS = 50, 16  # a 4 x 4 tile grid, the last tile row and column ragged (2)
EMPTY_ROW = 2   # a tile row without entries


def _matrix() -> sp.csr_array:
    """50 x 50, canonical CSR (sorted, no duplicates), tile row 2 empty, a full diagonal
    elsewhere."""
    rng = np.random.default_rng(5)
    A = sp.random_array((N, N), density=0.2, rng=rng, format="lil")
    A.setdiag(1.0 + rng.random(N))
    A[EMPTY_ROW * TS:(EMPTY_ROW + 1) * TS] = 0
    A = sp.csr_array(A)
    A.eliminate_zeros()
    A.sort_indices()
    return A


def _row(A: sp.csr_array, i: int) -> sp.csr_array:
    """Tile row ``i`` of ``A``, canonical CSR, global columns."""
    out = sp.csr_array(A[i * TS:min((i + 1) * TS, A.shape[0])])
    out.sort_indices()
    return out


def _files(folder: Path) -> list[str]:
    """Every file below ``folder``, as sorted POSIX paths relative to it."""
    return sorted(Path(os.path.relpath(os.path.join(d, f), folder)).as_posix()
                  for d, _, files in os.walk(folder) for f in files)


# --- (1) the files of a tile row --------------------------------------------------------

@pytest.mark.parametrize("chunk", [None, 8], ids=["one chunk", "chunks of 8"])
def test_a_tile_row_is_a_group_of_three_arrays(tmp_path, monkeypatch, chunk):
    """Per tile row: the group's zarr.json (the marker) and three arrays, each a
    zarr.json and one chunk file (ceil(length / CHUNK_ELEMENTS) when that is small;
    none for an empty array). Nothing per tile."""
    if chunk:
        monkeypatch.setattr(config, "CHUNK_ELEMENTS", chunk)
    A = _matrix()
    S = from_scipy(A, tmp_path / "s.zarr", tile_size=TS)
    assert S.row_layout and S.attrs.version == 2 and S.grid == (4, 4)
    rows = S.path / "rows"
    assert sorted(os.listdir(rows)) == ["0", "1", "2", "3", "zarr.json"]
    for i in range(S.grid[0]):
        want = _row(A, i)
        lengths = {"indptr": want.shape[0] + 1, "indices": want.nnz, "data": want.nnz}
        expected = ["zarr.json"]
        for name, length in lengths.items():
            per_file = chunk or length
            expected += [f"{name}/zarr.json"] + [f"{name}/c/{c}" for c in range(
                -(-length // per_file) if length else 0)]
        assert _files(rows / str(i)) == sorted(expected), i
        if not chunk:
            n_files = 7 if i != EMPTY_ROW else 5  # an empty row: no indices/data chunk
            assert len(_files(rows / str(i))) == n_files
        meta = {name: json.loads((rows / str(i) / name / "zarr.json").read_text())
                for name in lengths}
        assert {name: (m["shape"], m["data_type"]) for name, m in meta.items()} == {
            "indptr": ([lengths["indptr"]], "int64"), "indices": ([want.nnz], "int32"),
            "data": ([want.nnz], "float64")}  # from_scipy keeps float64
        marker = json.loads((rows / str(i) / "zarr.json").read_text())["attributes"]["bigT_row"]
        counts = np.bincount(want.indices // TS, minlength=S.grid[1])
        assert marker == {"complete": True, "tile_columns": np.flatnonzero(counts).tolist(),
                          "tile_nnz": counts[counts > 0].tolist()}
    np.testing.assert_array_equal(S.to_scipy().toarray(), A.toarray())


def test_tile_rows_not_written_read_as_empty(tmp_path):
    """An interrupted store opened with allow_incomplete: rows without a directory read
    as empty in every reader, as in format 1 (they have no files to read)."""
    A = _matrix()
    attrs = StoreAttrs((N, N), TS, "float64")
    path = tmp_path / "part.zarr"
    create_store(path, attrs)
    for i in (0, 3):
        write_tile_row(path, attrs, i, _row(A, i))
    S = open_store(path, allow_incomplete=True)
    assert S.missing_tile_rows == [1, 2]
    want = A.toarray()
    want[TS:3 * TS] = 0
    for i in range(4):
        np.testing.assert_array_equal(S.get_tile_row(i).toarray(), want[i * TS:(i + 1) * TS])
    assert list(S.iter_tiles(1)) == []
    np.testing.assert_array_equal(S.get_tile(1, 1).toarray(), np.zeros((TS, TS)))
    np.testing.assert_array_equal(S.to_scipy().toarray(), want)
    x = np.random.default_rng(0).random(N)
    np.testing.assert_allclose(S @ x, want @ x, rtol=1e-12)
    np.testing.assert_array_equal(S.diagonal(), np.diag(want))
    S.check_chunks_exist()
    assert S.verify()["nnz"] == np.count_nonzero(want)


# --- (2) a format-1 store -------------------------------------------------------------

def _zarr_array(store: LocalStore, name: str, values: np.ndarray, fill_value) -> None:
    """A 1-D array as format 1 wrote it: codecs bytes (little endian), zstd, crc32c;
    chunks of min(length, 2^20), every chunk written."""
    n = int(values.shape[0])
    arr = zarr.create_array(store, name=name, shape=(n,), dtype=values.dtype,
                            chunks=(max(1, min(n, 1 << 20)),), fill_value=fill_value,
                            serializer=BytesCodec(endian="little"),
                            compressors=[ZstdCodec(level=1), Crc32cCodec()], filters=None,
                            config={"write_empty_chunks": True})
    if n:
        arr[...] = values


def _format1_store(path: Path, A: sp.csr_array, ts: int, dtype="float64") -> Path:
    """A finalized bigT store of format 1 holding ``A``, written with zarr-python alone:
    a group ``rows/{i}/{j}`` per non-empty tile with local column indices, a marker per
    tile row, the tile index, root attributes of version 1 (docs/FORMAT.md of 2789f82)."""
    store = LocalStore(path)
    n_rows, n_cols = A.shape
    grid = (-(-n_rows // ts), -(-n_cols // ts))
    zarr.create_group(store, zarr_format=3, attributes={"bigT": {
        "format": "bigT-block-csr", "version": 1, "inner_format": "csr",
        "shape": [n_rows, n_cols], "tile_size": ts, "dtype": dtype, "nnz": int(A.nnz),
        "complete": True, "metadata": {}}})
    zarr.create_group(store, path="rows", zarr_format=3)
    tile_indptr, tile_indices, tile_nnz = [0], [], []
    for i in range(grid[0]):
        block = sp.csr_array(A[i * ts:(i + 1) * ts])
        tiles = {j: sp.csr_array(block[:, j * ts:(j + 1) * ts]) for j in range(grid[1])}
        tiles = {j: t for j, t in tiles.items() if t.nnz}
        columns, counts = list(tiles), [int(t.nnz) for t in tiles.values()]
        zarr.create_group(store, path=f"rows/{i}", zarr_format=3, attributes={
            "bigT_row": {"complete": True, "tile_columns": columns, "tile_nnz": counts}})
        for j, tile in tiles.items():
            tile.sort_indices()
            zarr.create_group(store, path=f"rows/{i}/{j}", zarr_format=3)
            _zarr_array(store, f"rows/{i}/{j}/indptr", tile.indptr.astype(np.int64), -1)
            _zarr_array(store, f"rows/{i}/{j}/indices", tile.indices.astype(np.int32), -1)
            _zarr_array(store, f"rows/{i}/{j}/data", tile.data.astype(dtype), float("nan"))
        tile_indptr.append(tile_indptr[-1] + len(columns))
        tile_indices += columns
        tile_nnz += counts
    for name, values in (("tile_indptr", tile_indptr), ("tile_indices", tile_indices),
                         ("tile_nnz", tile_nnz)):
        _zarr_array(store, name, np.asarray(values, np.int64), -1)
    return path


@pytest.fixture
def format1(tmp_path):
    A = _matrix()
    return _format1_store(tmp_path / "v1.zarr", A, TS), A


def test_the_format1_builder_writes_the_old_layout(format1):
    """The fixture is what it claims: per-tile groups, no per-row arrays."""
    path, A = format1
    assert (path / "rows" / "0" / "0" / "indices" / "c" / "0").is_file()
    assert not (path / "rows" / "0" / "indices").exists()
    assert read_store_attrs(path).version == 1
    assert _files(path / "rows" / str(EMPTY_ROW)) == ["zarr.json"]


def test_a_format1_store_reads_as_its_matrix(format1):
    path, A = format1
    S = open_store(path)
    assert not S.row_layout and S.attrs.version == 1 and S.nnz == A.nnz
    dense = A.toarray()
    np.testing.assert_array_equal(S.to_scipy().toarray(), dense)
    for i in range(S.grid[0]):
        np.testing.assert_array_equal(S.get_tile_row(i).toarray(), dense[i * TS:(i + 1) * TS])
        part = S.get_tile_row(i, columns=[0, 3]).toarray()
        masked = dense[i * TS:(i + 1) * TS].copy()
        masked[:, TS:3 * TS] = 0
        np.testing.assert_array_equal(part, masked)
        for j in range(S.grid[1]):
            np.testing.assert_array_equal(
                S.get_tile(i, j).toarray(), dense[i * TS:(i + 1) * TS, j * TS:(j + 1) * TS])
    X = np.random.default_rng(1).random((N, 3))
    np.testing.assert_allclose(S.matmul(X), dense @ X, rtol=1e-12)
    np.testing.assert_allclose(S @ X[:, 0], dense @ X[:, 0], rtol=1e-12)
    np.testing.assert_array_equal(S.diagonal(), np.diag(dense))
    assert S.verify() == {"tiles": S.n_tiles_stored, "nnz": A.nnz}
    assert S.info()["version"] == 1


def test_writers_refuse_to_add_to_a_format1_store(format1, capsys):
    """Resuming, or writing a tile row into, a format-1 store: one line naming the
    upgrade; the store is left as it was."""
    path, A = format1
    before = {f: (path / f).read_bytes() for f in _files(path)}
    with pytest.raises(StoreError, match=r"format 1.*convert") as ei:
        BlockCSRWriter(path, (N, N), tile_size=TS, dtype="float64", resume=True)
    assert "\n" not in str(ei.value) and str(path) in str(ei.value)
    for attrs in (read_store_attrs(path), StoreAttrs((N, N), TS, "float64", version=1)):
        with pytest.raises(StoreError, match=r"format 1.*convert") as ei:
            write_tile_row(path, attrs, 0, _row(A, 0))
        assert "\n" not in str(ei.value)
    assert {f: (path / f).read_bytes() for f in _files(path)} == before


def test_write_tile_row_checks_the_version_on_disk(format1):
    """A writer process that builds its StoreAttrs itself (this bigT's version) and
    writes a missing row into an interrupted format-1 store is refused too: the layout
    on disk decides (a format-2 row there would read as damage)."""
    path, A = format1
    shutil.rmtree(path / "rows" / "1")
    meta = json.loads((path / "zarr.json").read_text())
    meta["attributes"]["bigT"].update(complete=False, nnz=None)
    (path / "zarr.json").write_text(json.dumps(meta))
    before = _files(path)
    with pytest.raises(StoreError, match=r"format 1.*convert"):
        write_tile_row(path, StoreAttrs((N, N), TS, "float64"), 1, _row(A, 1))
    assert _files(path) == before
    assert open_store(path, allow_incomplete=True).missing_tile_rows == [1]


def test_tiles_kept_from_a_format1_store_are_rewritten(format1, tmp_path):
    """KeptTiles from a format-1 store into a new one: its tiles are read and written
    in format 2 (a link would put format-1 files into a format-2 row)."""
    old_path, A = format1
    old = open_store(old_path)
    attrs = StoreAttrs((N, N), TS, "float64")
    new_path = tmp_path / "new.zarr"
    create_store(new_path, attrs)
    for i in range(attrs.grid[0]):
        lo, hi = old.tile_indptr[i], old.tile_indptr[i + 1]
        rows = _row(A, i).shape[0]
        write_tile_row(new_path, attrs, i, sp.csr_array((rows, N)), keep=KeptTiles(
            old_path, tuple(old.tile_indices[lo:hi].tolist()), tuple(old.tile_nnz[lo:hi].tolist())))
    assert (new_path / "rows" / "0" / "indices" / "c" / "0").is_file()
    new = finalize_store(new_path)
    assert new.row_layout
    np.testing.assert_array_equal(new.to_scipy().toarray(), A.toarray())
    assert new.verify()["nnz"] == A.nnz


def test_bigT_verify_and_info_read_a_format1_store(format1, capsys):
    path, A = format1
    assert main(["verify", str(path), "--no-progress"]) == 0
    assert main(["info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out.split("\n", 1)[1])["nnz"] == A.nnz


def test_convert_upgrades_a_format1_store(format1, tmp_path, capsys):
    """``bigT convert OLD.zarr -o NEW.zarr`` (``upgrade_store``) rewrites a format-1
    store in format 2: same matrix, tiles, attributes and metadata; the old store is
    left as it was; an output over the input is refused."""
    from bigT.storage.upgrade import upgrade_store

    path, A = format1
    before = {f: (path / f).read_bytes() for f in _files(path)}
    new = tmp_path / "v2.zarr"
    assert main(["convert", str(path), "-o", str(new), "-q"]) == 0
    S = open_store(new)
    assert S.row_layout and S.attrs.version == 2 and S.nnz == A.nnz
    old = open_store(path)
    np.testing.assert_array_equal(S.tile_indices, old.tile_indices)
    np.testing.assert_array_equal(S.tile_nnz, old.tile_nnz)
    assert (S.tile_size, S.dtype, S.metadata) == (old.tile_size, old.dtype, old.metadata)
    np.testing.assert_array_equal(S.to_scipy().toarray(), A.toarray())
    assert S.verify()["nnz"] == A.nnz
    assert {f: (path / f).read_bytes() for f in _files(path)} == before
    # the library call, and a second run refused without overwrite
    again = upgrade_store(path, tmp_path / "lib.zarr")
    np.testing.assert_array_equal(again.to_scipy().toarray(), A.toarray())
    assert main(["convert", str(path), "-o", str(new)]) == 2
    assert main(["convert", str(path), "-o", str(path)]) == 2
    assert {f: (path / f).read_bytes() for f in _files(path)} == before


# --- (3) other zarr v3 readers -----------------------------------------------------------

def _interop_store(tmp_path, monkeypatch, chunk):
    if chunk:
        monkeypatch.setattr(config, "CHUNK_ELEMENTS", chunk)
    A = _matrix()
    S = from_scipy(A, tmp_path / "s.zarr", tile_size=TS, dtype="float64")
    return S, A


def _assert_row_arrays(read, S, A) -> None:
    """``read(i, name)`` of every tile row's three arrays equals the scipy row's CSR."""
    for i in range(S.grid[0]):
        want = _row(A, i)
        indptr, indices, data = (read(i, name) for name in ("indptr", "indices", "data"))
        assert (indptr.dtype, indices.dtype, data.dtype) == (np.int64, np.int32, np.float64)
        np.testing.assert_array_equal(indptr, want.indptr)
        np.testing.assert_array_equal(indices, want.indices)  # global columns
        np.testing.assert_array_equal(data, want.data)
        back = sp.csr_array((data, indices, indptr), shape=want.shape)
        np.testing.assert_array_equal(back.toarray(), want.toarray())


@pytest.mark.parametrize("chunk", [None, 8], ids=["one chunk", "chunks of 8"])
def test_zarr_python_reads_a_tile_row(tmp_path, monkeypatch, chunk):
    S, A = _interop_store(tmp_path, monkeypatch, chunk)
    group = zarr.open_group(LocalStore(S.path, read_only=True), mode="r")
    assert group.attrs["bigT"]["version"] == 2

    def read(i, name):
        return group[f"rows/{i}/{name}"][...]

    _assert_row_arrays(read, S, A)
    assert group[f"rows/{EMPTY_ROW}"].attrs["bigT_row"]["tile_columns"] == []


@pytest.mark.parametrize("chunk", [None, 8], ids=["one chunk", "chunks of 8"])
def test_tensorstore_reads_a_tile_row(tmp_path, monkeypatch, chunk):
    ts = pytest.importorskip("tensorstore")
    S, A = _interop_store(tmp_path, monkeypatch, chunk)

    def read(i, name):
        spec = {"driver": "zarr3",
                "kvstore": {"driver": "file", "path": str(S.path / "rows" / str(i) / name)}}
        return ts.open(spec, read=True).result().read().result()

    _assert_row_arrays(read, S, A)


# --- found by review -----------------------------------------------------------------

def test_some_tile_columns_of_a_row_whose_last_rows_are_empty(tmp_path):
    """get_tile_row(i, columns) keeps the entries of those tile columns, whatever rows
    are empty (the last ones included), as scipy's column mask does."""
    A = sp.lil_array((8, 8))
    A[0, 0], A[0, 5], A[1, 6] = 1.0, 2.0, 3.0  # rows 2, 3 of tile row 0 empty
    A[5, 1], A[6, 6] = 4.0, 5.0
    A = sp.csr_array(A)
    S = from_scipy(A, tmp_path / "s.zarr", tile_size=4, dtype="float64")
    for i in range(2):
        for cols in ([0], [1], [0, 1], []):
            want = A[i * 4:(i + 1) * 4].toarray()
            mask = np.zeros(8, bool)
            for j in cols:
                mask[j * 4:(j + 1) * 4] = True
            want[:, ~mask] = 0
            got = S.get_tile_row(i, columns=cols)
            np.testing.assert_array_equal(got.toarray(), want)
            assert np.all(np.diff(got.indptr) >= 0) and got.indptr[-1] == got.nnz


def test_a_linked_row_is_fsynced_before_its_marker(tmp_path, monkeypatch):
    """A row carried by links (or copies) reaches the disk before the marker that
    announces it, as a written row does: the arrays' files are fsynced, then the marker
    is linked."""
    from bigT.storage import writer

    A = _matrix()
    old = from_scipy(A, tmp_path / "old.zarr", tile_size=TS, dtype="float64")
    attrs = StoreAttrs((N, N), TS, "float64")
    create_store(tmp_path / "new.zarr", attrs)
    order = []
    real_fsync_tree, real_link_file = writer.fsync_tree, writer._link_file
    monkeypatch.setattr(writer, "durable", lambda: True)
    monkeypatch.setattr(writer, "fsync_tree", lambda p, **kw: (order.append("fsync"),
                                                             real_fsync_tree(p, **kw)))
    def link(src, dst):
        marker = Path(dst).name == "zarr.json" and Path(dst).parent.name.endswith(".partial")
        order.append("marker" if marker else "file")
        real_link_file(src, dst)

    monkeypatch.setattr(writer, "_link_file", link)
    lo, hi = old.tile_indptr[0], old.tile_indptr[1]
    assert write_tile_row(tmp_path / "new.zarr", attrs, 0, sp.csr_array((TS, N)),
                          keep=KeptTiles(old.path, tuple(old.tile_indices[lo:hi].tolist()),
                                         tuple(old.tile_nnz[lo:hi].tolist())))
    assert order.count("file") == 6 and order.index("fsync") > order.index("file")
    assert order.index("fsync") < order.index("marker") == len(order) - 1
    np.testing.assert_array_equal(open_store(tmp_path / "new.zarr", allow_incomplete=True)
                                  .get_tile_row(0).toarray(), _row(A, 0).toarray())


def test_row_arrays_of_another_type_are_refused(tmp_path):
    """A row whose data array holds integers (or whose indices hold floats) is damage:
    one line naming the row, not a matrix of another dtype or a numpy error."""
    A = _matrix()
    S = from_scipy(A, tmp_path / "s.zarr", tile_size=TS, dtype="float64")
    row = _row(A, 0)
    store = LocalStore(tmp_path / "s.zarr")
    for name, values in (("data", row.data.astype(np.int64)),
                         ("indices", row.indices.astype(np.float64))):
        shutil.rmtree(tmp_path / "s.zarr" / "rows" / "0" / name)
        arr = zarr.create_array(store, name=f"rows/0/{name}", shape=values.shape,
                                dtype=values.dtype, chunks=values.shape,
                                fill_value=-1)
        arr[...] = values
        with pytest.raises(CorruptStoreError, match="tile row 0: arrays of types") as err:
            open_store(S.path).get_tile_row(0)
        assert "\n" not in str(err.value)
        from_scipy(A, tmp_path / "s.zarr", tile_size=TS, dtype="float64", overwrite=True)


# --- (3) the diagonal's read and the smallest entry ------------------------------------

@pytest.mark.parametrize("negative", [False, True])
def test_the_diagonal_scan_sees_every_entry_of_a_format2_store(tmp_path, negative):
    """Format 2 reads every tile row holding a diagonal tile whole: the scan reports the
    smallest entry (capped at 0), and hands each row read to ``keep``; a tile row with
    entries but no diagonal tile leaves the smallest unknown."""
    A = _matrix().tolil()
    if negative:
        A[3, 40] = -0.25
    A = sp.csr_array(A)
    S = from_scipy(A, tmp_path / "A.zarr", tile_size=TS)
    kept = {}
    scan = S.diagonal_scan("matrix", keep=lambda i, row: kept.setdefault(i, row))
    np.testing.assert_array_equal(scan.diagonal, A.diagonal())
    assert scan.smallest == (-0.25 if negative else 0.0)
    assert sorted(kept) == [i for i in range(S.grid[0]) if i != EMPTY_ROW]
    for i, row in kept.items():
        assert (row != S.get_tile_row(i)).nnz == 0
    B = A.tolil()
    B[0:TS, 0:TS] = 0  # tile row 0 keeps entries, but no diagonal tile
    B = sp.csr_array(B)
    B.eliminate_zeros()
    assert from_scipy(B, tmp_path / "B.zarr", tile_size=TS).diagonal_scan().smallest is None


def test_a_format1_store_reads_its_diagonal_tiles_only(format1):
    """Format 1 reads only the diagonal tiles: the smallest entry is not known."""
    path, A = format1
    scan = open_store(path).diagonal_scan("matrix")
    np.testing.assert_array_equal(scan.diagonal, A.diagonal())
    assert scan.smallest is None
