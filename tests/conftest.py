"""The suite's tests were written for the engine's out-of-core path (its tasks, task
hooks, files and crash points): they run it, here and in the CLI processes they start.
The in-memory path has its own tests (tests/algorithms/test_in_memory.py), which ask
for it explicitly."""

import os

os.environ.setdefault("BIGT_IN_MEMORY", "0")
