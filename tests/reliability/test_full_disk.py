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

#: Every SAMPLE-th kind of mutation is made to fail by default, every kind with -m slow;
#: by default the two errors take turns over those kinds (ENOSPC the first, EROFS the
#: next, ...): both go down the same write paths to the same one-line refusal, and
#: between them every SAMPLE-th kind is still tried, in half the time.
SAMPLE = 3
#: Where each error starts in its share of the sample (the default run only).
TURN = {errno.ENOSPC: 0, errno.EROFS: 1}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return build_inputs(tmp_path_factory.mktemp("disk"))


@pytest.mark.parametrize("sample", [SAMPLE, pytest.param(1, marks=pytest.mark.slow)])
@pytest.mark.parametrize("name", COMMANDS)
@pytest.mark.parametrize("error", [errno.ENOSPC, errno.EROFS], ids=["ENOSPC", "EROFS"])
def test_a_failing_disk_gives_one_line_and_keeps_what_was_written(inputs, tmp_path, name,
                                                                   error, sample):
    offset = 0
    if sample > 1:
        if name == "invert":
            sample *= 3  # 230 kinds of mutation, the others' 10-80: the default run stays short
        offset = TURN[error] * sample
        sample *= len(TURN)
    result = check_command(inputs, tmp_path, name, error, sample, offset)
    assert result.points >= 2 and result.refused >= 1
    assert result.ok, f"{len(result.problems)} failures: {result.problems[:3]}"
