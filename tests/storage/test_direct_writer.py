"""bigT writes tile arrays directly (storage._format.write_array_files); the files must
be the ones zarr-python writes, and zarr must read them back."""

import numpy as np
import pytest
import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec
from zarr.storage import LocalStore

from bigT import config
from bigT.storage import _format as fmt


def _zarr_write(store, name, values, fill_value, level):
    """The reference: the same array written by zarr-python itself."""
    n = int(values.shape[0])
    arr = zarr.create_array(
        store, name=name, shape=(n,), dtype=values.dtype,
        chunks=(max(1, min(n, config.CHUNK_ELEMENTS)),), fill_value=fill_value,
        compressors=[ZstdCodec(level=level), Crc32cCodec()], filters=None,
        config={"write_empty_chunks": True})
    if n:
        arr[...] = values


def _files(root):
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


@pytest.mark.parametrize("values, fill", [
    (np.arange(10, dtype=np.int64), fmt.FILL_INT),
    (np.array([], dtype=np.int32), fmt.FILL_INT),
    (np.linspace(-1, 1, 7, dtype=np.float32), fmt.FILL_FLOAT),
    (np.random.default_rng(0).random(2500), fmt.FILL_FLOAT),  # three chunks, ragged edge
])
@pytest.mark.parametrize("level", [1, 3])
def test_same_files_as_zarr(tmp_path, monkeypatch, values, fill, level):
    monkeypatch.setattr(config, "CHUNK_ELEMENTS", 1000)
    zroot, droot = tmp_path / "zarr", tmp_path / "direct"
    _zarr_write(LocalStore(zroot), "a/b", values, fill, level)
    fmt.write_array_files(droot, "a/b", values, fill, level)
    zfiles = _files(zroot / "a" / "b")
    assert zfiles == _files(droot / "a" / "b")
    assert (zroot / "a" / "b" / "c" / "0").exists() == bool(values.size)
    for f in zfiles:  # zarr.json included: the same bytes
        f = zroot.joinpath("a", "b", f).relative_to(zroot)
        assert (zroot / f).read_bytes() == (droot / f).read_bytes(), f
    back = zarr.open_array(LocalStore(droot), path="a/b", mode="r")[...]
    np.testing.assert_array_equal(back, values)
    assert back.dtype == values.dtype


def _write_damaged(root, name):
    """An int64 array written by bigT, one byte of its chunk flipped afterwards."""
    fmt.write_array_files(root, name, np.arange(100, dtype=np.int64), fmt.FILL_INT, 1)
    chunk = root / name / "c" / "0"
    raw = bytearray(chunk.read_bytes())
    raw[3] ^= 0xFF
    chunk.write_bytes(bytes(raw))


def test_checksum_is_checked_on_read(tmp_path):
    _write_damaged(tmp_path, "x")
    with pytest.raises(ValueError, match="checksum"):  # zarr checks what bigT wrote
        zarr.open_array(LocalStore(tmp_path), path="x", mode="r")[...]


@pytest.mark.parametrize("values, fill", [
    (np.arange(10, dtype=np.int64), fmt.FILL_INT),
    (np.array([], dtype=np.int32), fmt.FILL_INT),
    (np.random.default_rng(0).random(2500).astype(np.float32), fmt.FILL_FLOAT),
])
def test_direct_read_equals_zarr_read(tmp_path, monkeypatch, values, fill):
    monkeypatch.setattr(config, "CHUNK_ELEMENTS", 1000)
    _zarr_write(LocalStore(tmp_path), "a", values, fill, 1)
    got = fmt.read_array_files(tmp_path / "a")
    np.testing.assert_array_equal(got, values)
    assert got.dtype == values.dtype
    if values.size > 1000:
        (tmp_path / "a" / "c" / "1").unlink()  # a missing chunk reads as the fill value
        got = fmt.read_array_files(tmp_path / "a")
        ref = zarr.open_array(LocalStore(tmp_path), path="a", mode="r")[...]
        np.testing.assert_array_equal(got, ref)
        assert np.isnan(got[1000:2000]).all()


def test_direct_read_refuses_damage_and_defers_foreign_layouts(tmp_path):
    _write_damaged(tmp_path, "x")
    with pytest.raises(ValueError, match="checksum mismatch in chunk file x/c/0"):
        fmt.read_array_files(tmp_path / "x")
    zarr.create_array(LocalStore(tmp_path), name="y", data=np.arange(5), chunks=(5,),
                      compressors=None)  # no zstd, no crc32c: not bigT's layout
    assert fmt.read_array_files(tmp_path / "y") is None
