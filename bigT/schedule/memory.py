"""How a ``memory_limit`` is shared out among the parts of a series run.

What a run holds, and why each part is budgeted the way it is:

* the **baseline**: the interpreter, numpy/scipy/numba/dask/zarr and their compiled
  code, T's index arrays. It is measured (the resident set when the plan is made),
  not guessed: it is ~190 MB on Linux with every library imported.
* per task in flight (``workers`` of them), a **fixed** part that no plan can shrink:
  making one tile row of M from T's (``M_ROW_BYTES_PER_ENTRY`` per entry of T's
  largest tile row) and the product kernel's workspace (dense accumulators, (GROUP +
  1) float64 per column, and markers: ``bigT.kernels.workspace_bytes``), kept between
  tasks rather than made per tile row.
* the **tile cache**: tile rows of M, reused by every term and every mat-vec.
* the **shared right factor**: P_{k-1} (or S, R) held whole and shared by the tasks
  when it fits, read once per pass.
* per task, a **work** share: when the right factor does not fit whole, each task
  reads it in batches of tile rows and keeps unpruned partial sums of a chunk of its
  output rows (:func:`bigT.schedule.blocks.row_product_batched`); the chunks are sized
  to this share.

The plan refuses (``MemoryLimitError``) a limit that cannot hold the baseline and the
fixed parts with a minimum working share, and says how much would do.
"""

from __future__ import annotations

import functools
import os
import sys
from dataclasses import dataclass

from .. import config
import warnings

from ..errors import MemoryLimitError, MemoryLimitWarning
from ._backend import workspace_bytes

#: Bytes per entry of T's tile row while it becomes M's: the decoded tiles and the
#: assembled row (8 + 8), the scaled copy (8), the row and mask arrays of the diagonal
#: surgery (6), the compacted result (8), allocator slack (measured: 32 let a 768 MiB
#: run peak at 775 MiB).
M_ROW_BYTES_PER_ENTRY = 48

#: Bytes per entry of an unpruned partial sum: the running sum, the new part and their
#: scipy sum alive at once (float32 value + int32 index each), plus the kernel's
#: output buffer.
PARTIAL_BYTES_PER_ENTRY = 32


def human_bytes(n: float) -> str:
    """``n`` bytes in KiB, MiB or GiB, whichever reads best."""
    for unit, size in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if abs(n) >= size:
            return f"{n / size:.0f} {unit}" if unit != "GiB" else f"{n / size:.2f} {unit}"
    return f"{int(n)} B"


def resident_bytes() -> int:
    """The resident set size of this process now, in bytes (peak so far where the
    current value is not available)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return _ru_maxrss_bytes()


def _ru_maxrss_bytes() -> int:
    """The peak resident set from getrusage, in bytes (kilobytes on Linux, bytes on
    macOS); 0 on Windows, where the plan then assumes nothing held."""
    try:
        import resource  # POSIX only: Windows has no getrusage
    except ImportError:
        return 0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


def peak_resident_bytes() -> int:
    """Peak resident set of this process in bytes: VmHWM of /proc/self/status (the
    high-water mark of this process's own memory). Not ru_maxrss where /proc exists:
    after fork + exec Linux carries the parent's high-water mark into the child's
    ru_maxrss, so a child started by a parent that built a big scene would report the
    parent's peak."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return _ru_maxrss_bytes()


def return_freed_memory() -> None:
    """Hand the heap's freed pages back to the system (glibc's ``malloc_trim``; nothing
    elsewhere).

    Why: glibc serves allocations under its mmap threshold (which grows to 32 MiB as
    large arrays are freed) from the heap, and freed heap pages stay in the process's
    resident set; scipy.sparse's temporaries of a tile row are such allocations. A long
    build's next phase then starts on top of the last one's peak: measured on the 4K
    corner, 3.3 GB resident after T was written, then 5.9 GB with the statistics' 2 GiB
    of cached tiles (dask's workers call ``malloc_trim`` for the same reason)."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


#: Without a limit, the most freed memory a process keeps for its next tasks: this
#: share of the memory available when the plan is made. Why keep any: the pages a trim
#: hands back are faulted in again by the next task (zeroed by the kernel, and on a
#: virtual machine whose host takes free memory back, backed again by the host). The
#: full-HD dense corner's 4-term inverse out of core, no limit, on this project's
#: machine: 89.4 s (53.2 s of it in the kernel) trimming after each of its ~5000 tasks,
#: 69.3 s (25.6 s) not, its peak 2.19 GB against 2.34 GB (issue #30). Under a limit
#: the plan sets the threshold (:func:`plan_memory`), so the heap's retained pages
#: never push a task past it (the 4K corner's 5.7 GiB under 4 GiB, trimming never).
UNLIMITED_RETAIN_SHARE = 0.25


def _unlimited_trim_above(baseline: int) -> int:
    available = available_memory()
    return baseline + int(UNLIMITED_RETAIN_SHARE * (available or 0))


def return_freed_memory_above(threshold: int) -> bool:
    """:func:`return_freed_memory` when this process's resident set exceeds
    ``threshold`` bytes (:attr:`MemoryPlan.trim_above`); returns whether it did."""
    if resident_bytes() <= threshold:
        return False
    return_freed_memory()
    return True


@functools.cache
def _glibc():
    """glibc, loaded once, or None."""
    import ctypes  # only where memory is handed back: a long build's phases

    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        return libc if hasattr(libc, "malloc_trim") else None
    except OSError:  # musl, or no libc.so.6
        return None


def stored_bytes(nnz: int, n_rows: int, itemsize: int) -> int:
    """Bytes of a CSR matrix in memory: values, int32 column indices, row pointers."""
    index = 4 if nnz < 2**31 else 8
    return int(nnz) * (int(itemsize) + index) + (int(n_rows) + 1) * index


@dataclass(frozen=True)
class MemoryPlan:
    """Byte budgets of one run (see the module docstring).

    Attributes
    ----------
    limit : int or None
        The limit asked for; None is the unlimited default plan.
    baseline : int
        Resident bytes measured when the plan was made.
    fixed_per_task : int
    cache_bytes : int
    whole_bytes : int
    work_bytes_per_task : int
    threads : int
        Tasks in flight at once in the process.
    trim_above : int
        Resident bytes above which a task hands the heap's freed pages back.
    """

    limit: int | None
    baseline: int
    fixed_per_task: int
    cache_bytes: int
    whole_bytes: int
    work_bytes_per_task: int
    threads: int = 1
    #: :func:`return_freed_memory_above`'s threshold, set by :func:`plan_memory`; a plan
    #: made by hand trims after every task (0)
    trim_above: int = 0

    def describe(self) -> str:
        mib = 1 << 20
        if self.limit is None:
            return "no memory limit"
        return (f"memory limit {self.limit / mib:.0f} MiB, {self.threads} threads: baseline "
                f"{self.baseline / mib:.0f}, "
                f"per task fixed {self.fixed_per_task / mib:.0f} + work "
                f"{self.work_bytes_per_task / mib:.0f}, tile cache {self.cache_bytes / mib:.0f}, "
                f"shared factor {self.whole_bytes / mib:.0f} MiB")


def plan_memory(limit: int | None, workers: int, n_cols: int, max_tile_row_nnz: int,
                baseline: int | None = None) -> MemoryPlan:
    """Share ``limit`` bytes out among the parts of a run.

    Parameters
    ----------
    limit : int or None
        Bytes for the whole process; None gives a generous fixed plan.
    workers : int
        Tasks in flight at once.
    n_cols : int
        Columns of the products (n): the kernel's accumulators scale with it.
    max_tile_row_nnz : int
        Entries of T's largest tile row.
    baseline : int, optional
        Resident bytes already held; measured now when not given.

    Raises
    ------
    MemoryLimitError
        The limit cannot hold the baseline, the fixed parts and a minimum work share.
    """
    workers = max(1, int(workers))
    fixed = (M_ROW_BYTES_PER_ENTRY * int(max_tile_row_nnz)
             + workspace_bytes(int(n_cols), int(n_cols)))
    if baseline is None:
        if limit is not None:  # what earlier work freed is not this run's baseline
            return_freed_memory()
        baseline = resident_bytes()
    if limit is None:
        return MemoryPlan(None, baseline, fixed, 1 << 30, 1 << 30, 1 << 30, workers,
                          trim_above=_unlimited_trim_above(baseline))
    headroom = config.MEMORY_HEADROOM_BYTES
    rest = int(limit) - baseline - headroom - workers * fixed
    minimum = workers * config.MEMORY_MIN_WORK_BYTES
    if rest < minimum:
        need = baseline + headroom + workers * (fixed + config.MEMORY_MIN_WORK_BYTES)
        raise MemoryLimitError(
            f"{{option}} {human_bytes(limit)} is too small for this run: the process "
            f"already holds {human_bytes(baseline)} (interpreter and libraries), and each "
            f"of {workers} tasks needs {human_bytes(fixed)} that no plan can shrink (one "
            f"tile row of M, {max_tile_row_nnz} entries, and the product's accumulators "
            f"for {n_cols} columns) plus at least "
            f"{human_bytes(config.MEMORY_MIN_WORK_BYTES)} to work in; "
            f"give at least {human_bytes(need)}, fewer workers, or a store with a smaller "
            "tile size", option="memory_limit")
    # The cache of M's tile rows saves rebuilding them from T at every term and
    # mat-vec; a shared right factor saves re-reading its tile rows per output chunk.
    cache = int(config.MEMORY_CACHE_SHARE * rest)
    whole = int(config.MEMORY_WHOLE_SHARE * rest)
    work = (rest - cache - whole) // workers
    # a task ends with the heap's freed pages handed back unless a new task's fixed
    # part and work share still fit under the limit beside what the process holds
    return MemoryPlan(int(limit), baseline, fixed, cache, whole, work, workers,
                      trim_above=max(0, int(limit) - headroom - fixed - work))


#: A task holds its output tile rows whole until they are written (the previous X's
#: row, the new P's and the new X's): this many times the widest row of X.
OUTPUT_ROWS_HELD = 3


def warn_if_rows_outgrow(plan: MemoryPlan, widest_row_bytes: int, growth: float,
                         term: int, path) -> bool:
    """Warn (``MemoryLimitWarning``) when term ``term``'s output tile rows, predicted
    as the widest tile row of X so far times the last term's growth of X, may not fit
    a task's work share: a tile row is the unit the store writes, so its width (set by
    ``prune``, not by n) is the one thing the plan cannot split. Returns whether it
    warned."""
    if plan.limit is None:
        return False
    need = OUTPUT_ROWS_HELD * widest_row_bytes * max(1.0, growth)
    if need <= plan.work_bytes_per_task:
        return False
    warnings.warn(
        f"{path}: term {term}'s tile rows may hold ~{human_bytes(need)} per task "
        f"(X's widest tile row {human_bytes(widest_row_bytes)}, growing {growth:.1f}x a "
        f"term), more than the {human_bytes(plan.work_bytes_per_task)} each task has under "
        f"memory_limit {human_bytes(plan.limit)}: the limit may be exceeded. A higher "
        "prune, a higher limit or a store with a smaller tile size keeps it",
        MemoryLimitWarning, stacklevel=5)  # the caller of stratified_inverse
    return True


def available_memory() -> int | None:
    """MemAvailable of /proc/meminfo in bytes (None where it cannot be read)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None
