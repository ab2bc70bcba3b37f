import pytest
from inverse_helpers import store


@pytest.fixture
def make_store(tmp_path):
    def _make(A, name="T.zarr", tile_size=16, dtype="float64"):
        return store(tmp_path, A, name, tile_size, dtype)
    return _make
