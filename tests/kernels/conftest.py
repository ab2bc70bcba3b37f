import pytest

from bigT import config


@pytest.fixture(autouse=True, params=["numba", "numpy"])
def backend(request, monkeypatch):
    """Every wrapper test runs on the numba kernels and on their numpy twins
    (``bigT.kernels._small``): the limit between them decides which one runs."""
    limit = -1 if request.param == "numba" else 10**18
    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", limit)
    return request.param
