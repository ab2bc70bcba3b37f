"""bigT.sizes reads sizes as dask does: checked against dask.utils.parse_bytes."""

import pytest
from dask.utils import parse_bytes

from bigT.sizes import format_size, parse_size


@pytest.mark.parametrize("text", ["2GiB", "500MB", "2G", "1e9", "4 GiB", ".5GiB", "1.5e3",
                                  "10", "3kb", "7KiB", "1.25TiB", "2mi", "1PB"])
def test_parse_size_agrees_with_dask(text):
    assert parse_size(text) == parse_bytes(text)


@pytest.mark.parametrize("bad", ["-5GiB", "inf", "abc", "0", "0.2", "1e999", "", "5 XB", True])
def test_parse_size_refuses_naming_the_value(bad):
    with pytest.raises(ValueError, match="memory_limit must be a positive size.*got"):
        parse_size(bad, "memory_limit")


@pytest.mark.parametrize("n", [1, 1023, 2**20, 3 * 2**29, 2**32, 4 * 10**9, 5 * 2**40])
def test_format_size_reads_back(n):
    assert abs(parse_size(format_size(n)) - n) <= 5e-4 * n
    assert format_size(2**32) == "4GiB"
