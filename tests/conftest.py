"""The suite's tests were written for the engine's out-of-core path (its tasks, task
hooks, files and crash points): they run it, here and in the CLI processes they start.
The in-memory path has its own tests (tests/algorithms/test_in_memory.py), which ask
for it explicitly.

Their temporary directories (``tmp_path``, ``tmp_path_factory``) are on tmpfs when the
machine has one (``/dev/shm``): the suite checks what the engine writes, not how fast a
disk syncs it, and there the fsyncs and renames of every published file cost nothing (a
series term several times quicker than on a shared disk, as the stability helpers found).
The durability tests record the fsyncs themselves (tests/reliability/test_durability.py).
``PYTEST_DEBUG_TEMPROOT`` set by hand wins."""

import os

os.environ.setdefault("BIGT_IN_MEMORY", "0")
# as the bigT command runs (bigT.cli._advise_no_huge_pages), here and in the processes
# the tests start
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


#: The suite's largest tests write a few hundred MB at once; a container's /dev/shm is
#: often 64 MB, where they would fail for want of space, not of correctness.
TMPFS_MIN_FREE_BYTES = 4 << 30


def _tmpfs() -> str | None:
    """/dev/shm when it is there, writable and has TMPFS_MIN_FREE_BYTES free, else None
    (pytest's default root)."""
    shm = "/dev/shm"
    if not (os.path.isdir(shm) and os.access(shm, os.W_OK)):
        return None
    st = os.statvfs(shm)
    return shm if st.f_bavail * st.f_frsize >= TMPFS_MIN_FREE_BYTES else None


# read by pytest when the first temporary directory is made, after this import
if _tmpfs() and "PYTEST_DEBUG_TEMPROOT" not in os.environ:
    os.environ["PYTEST_DEBUG_TEMPROOT"] = _tmpfs()
