"""A ``bigT`` command run in a child process that dies (``os._exit``, as under SIGKILL)
just before its k-th write to object storage: every ``obstore.put``, ``delete`` and
``copy`` (each object put, marker, redirect, lock, deletion). A subprocess, not a
fork: obstore's runtime threads do not survive a fork.

Usage: python crash_child.py K KINDS.json bigT-argv...   (K = 0: never dies)
"""

from __future__ import annotations

import json
import os
import re
import sys

CRASH_STATUS = 137


def kind_of(op: str, key) -> str:
    """The op and the key's last three parts, numbers and hex replaced; the term
    directory (t0001) kept."""
    key = key[0] if isinstance(key, (list, tuple)) and key else key
    parts = str(key).split("/")
    term = next((p for p in parts if re.fullmatch(r"t\d{4}", p)), "")
    return f"{op} {term}:" + re.sub(r"\d+|[0-9a-f]{8,}", "#", "/".join(parts[-3:]))


def main() -> int:
    crash_at, kinds_file, argv = int(sys.argv[1]) or None, sys.argv[2], sys.argv[3:]
    import obstore

    from bigT import config

    config.BACKGROUND_REMOVAL = False  # one thread writes: point k is the same each run
    kinds: list[str] = []

    def counted(op, func):
        def wrapper(store, key, *args, **kwargs):
            kinds.append(kind_of(op, key))
            if len(kinds) == crash_at:
                os._exit(CRASH_STATUS)
            return func(store, key, *args, **kwargs)
        return wrapper

    for op in ("put", "delete", "copy"):
        setattr(obstore, op, counted(op, getattr(obstore, op)))
    from bigT.cli import main as bigt_main

    status = bigt_main(argv)
    with open(kinds_file, "w") as f:
        json.dump(kinds, f)
    return status


if __name__ == "__main__":
    sys.exit(main())
