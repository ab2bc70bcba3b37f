"""Which path a series run takes: in memory (:mod:`.resident`: T, M and the terms held
by the process, the same kernels, each term still written into the inverse store) or
out of core (:mod:`.passes`: row-block tasks reading and writing the term stores), and
the memory budget that decides it (docs/DESIGN.md, "Memory").
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass

from .. import config
from ..errors import BigTError
from ..schedule.memory import M_ROW_BYTES_PER_ENTRY, MemoryPlan, available_memory, human_bytes
from ..schedule.runner import ThreadRunner

#: The path names the record and the report use.
IN_MEMORY, OUT_OF_CORE = "in-memory", "out-of-core"

#: The environment variable that sets ``in_memory`` where a call leaves it None: "0"
#: (out of core), "1" (in memory) or unset/"auto" (the budget decides). The test
#: suite sets "0" for the tests written for the out-of-core path's tasks and files
#: (tests/conftest.py); it reaches the CLI's processes too.
ENVIRONMENT = "BIGT_IN_MEMORY"

#: Without a ``memory_limit``, the in-memory path may take this share of the memory
#: the system has available (MemAvailable) when the run starts...
AVAILABLE_SHARE = 0.5
#: ...and at most this much. What the path saves is fixed costs (dask graphs, store
#: reads, per-pass set-up, and the writes of the terms it goes past: :mod:`.engine`),
#: which matter where M is small. Measured on the dense 384x512 corner (making M
#: ~2.7 GiB, predicted; 4 terms at 3e-6/1e-4/1e-5, load average ~8): 38 s in memory
#: against 60 s out of core, peak 2.3 against 1.0 GB (before terms were left unwritten
#: in memory, no faster: 15.5-16.8 s against 15.2-16.3 s). Full HD took 5.7 GB in
#: memory against 2.9 GB out of core: a T of more than ~64 M entries (3 GiB / 48 bytes)
#: stays out of core. A ``memory_limit`` given overrides the cap.
DEFAULT_MAX_BYTES = 3 << 30

#: Without a ``memory_limit`` and where the available memory cannot be read.
FALLBACK_BUDGET_BYTES = 2 << 30


@dataclass(frozen=True)
class PathChoice:
    """Which path a run takes, and why (the report's ``engine_path_reason``).

    Attributes
    ----------
    in_memory : bool
    reason : str
    budget : int
        Bytes the in-memory path may hold (0 out of core).
    """

    in_memory: bool
    reason: str
    budget: int = 0

    @property
    def name(self) -> str:
        return IN_MEMORY if self.in_memory else OUT_OF_CORE


def memory_budget(plan: MemoryPlan) -> int:
    """Bytes the in-memory path may hold: what ``memory_limit`` leaves over the
    baseline measured and the headroom; without one, a share of the available memory,
    at most :data:`DEFAULT_MAX_BYTES`."""
    if plan.limit is not None:
        return max(0, plan.limit - plan.baseline - config.MEMORY_HEADROOM_BYTES)
    available = available_memory()
    if not available:
        return FALLBACK_BUDGET_BYTES
    return min(int(AVAILABLE_SHARE * available), DEFAULT_MAX_BYTES)


def m_build_bytes(T, channels: int) -> int:
    """Bytes of making M from the whole of T at once (the same count per entry as the
    memory plan's for one tile row of M; a colour F spreads each entry of T over its
    pixel's 3 columns)."""
    return M_ROW_BYTES_PER_ENTRY * int(T.nnz) * channels


def choose_path(in_memory, runner, T, channels: int, plan: MemoryPlan) -> PathChoice:
    """The path of a run: in memory when asked (``True``), or when ``in_memory`` is None
    and the run's tasks would run in this process and M fits the budget; out of core
    when asked (``False``) or on a cluster.

    Raises
    ------
    BigTError
        ``in_memory=True`` with a cluster scheduler (its workers hold the matrices).
    """
    if in_memory is not None and not isinstance(in_memory, bool):
        raise BigTError(f"{{option}} must be None, True or False, got {in_memory!r}",
                        option="in_memory")
    if in_memory is None:
        in_memory = _from_environment()
    local = isinstance(runner, ThreadRunner)
    if in_memory is False:
        return PathChoice(False, "out of core, as asked (in_memory=False, or "
                                 f"{ENVIRONMENT}=0)")
    if not local:
        if in_memory:
            raise BigTError("{option} runs the series in this process; a cluster scheduler "
                            "runs it on its workers, out of core: choose one",
                            option=("in_memory", True))
        return PathChoice(False, "out of core: the tasks run on a cluster")
    budget = memory_budget(plan)
    need = m_build_bytes(T, channels)
    if in_memory:
        # asked: no estimate sends it out of core, before or between the terms
        return PathChoice(True, "in memory, as asked (in_memory=True)", sys.maxsize)
    if need > budget:
        return PathChoice(False, f"out of core: making M takes ~{human_bytes(need)}, over "
                                 f"the {human_bytes(budget)} the process may hold")
    return PathChoice(True, f"in memory: M takes ~{human_bytes(need)} of the "
                            f"{human_bytes(budget)} the process may hold", budget)


def _from_environment() -> bool | None:
    """``in_memory`` as :data:`ENVIRONMENT` sets it (None: automatic)."""
    value = os.environ.get(ENVIRONMENT, "auto").strip().lower()
    choices = {"0": False, "1": True, "auto": None, "": None}
    if value not in choices:
        raise BigTError(f"the environment variable {ENVIRONMENT} must be 0, 1 or auto, "
                        f"got {value!r}")
    return choices[value]
