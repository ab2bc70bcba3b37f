"""A full disk (ENOSPC) or a read-only one (EROFS) at any write of every command that
writes (issue #17, item 3; the check is :func:`disk_faults.check_command`)."""

from __future__ import annotations

import errno
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from disk_faults import COMMANDS, build_inputs, check_command  # noqa: E402

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")

#: Every SAMPLE-th kind of mutation is made to fail by default, every kind with -m slow.
SAMPLE = 3


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return build_inputs(tmp_path_factory.mktemp("disk"))


@pytest.mark.parametrize("sample", [SAMPLE, pytest.param(1, marks=pytest.mark.slow)])
@pytest.mark.parametrize("name", COMMANDS)
@pytest.mark.parametrize("error", [errno.ENOSPC, errno.EROFS], ids=["ENOSPC", "EROFS"])
def test_a_failing_disk_gives_one_line_and_keeps_what_was_written(inputs, tmp_path, name,
                                                                   error, sample):
    if name == "invert" and sample > 1:
        sample *= 3  # 230 kinds of mutation, the others' 10-80: the default run stays short
    result = check_command(inputs, tmp_path, name, error, sample)
    assert result.points >= 2 and result.refused >= 1
    assert result.ok, f"{len(result.problems)} failures: {result.problems[:3]}"
