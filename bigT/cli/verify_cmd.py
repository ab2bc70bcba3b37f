"""``bigT verify``: read every chunk of a store and check it."""

from __future__ import annotations

import time

from ._options import add_progress

# The library's layers are imported inside each command's functions, where the
# command runs: building the parser imports every command module, and a command
# should pay only for the layers it uses (stores: zarr ~0.3 s; compensation ~0.5 s).


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "verify", help="check every chunk, checksum and row marker of a bigT store",
        description="Read every chunk file of a bigT store (of an inverse store: its "
                    "current term) and check its checksum, every tile's CSR structure, the "
                    "row completion markers and the tile index against each other. Exit "
                    "status 0 when all is well, 2 (with the first problem found) when not. "
                    "`bigT info` only checks that the chunk files exist.")
    p.add_argument("store", metavar="STORE")
    add_progress(p)
    p.set_defaults(func=verify_cmd)


def verify_cmd(args) -> int:
    from ..storage import open as open_store

    t0 = time.perf_counter()
    S = open_store(args.store)
    checked = S.verify(progress=args.progress)
    via = f" (term {S.metadata['inverse'].get('term')} of {S.redirected_from})" \
        if S.redirected_from is not None and "inverse" in S.metadata else ""
    tiles = f"{checked['tiles']} tile" + ("s" if checked["tiles"] != 1 else "")
    print(f"{S.path}{via}: OK, {tiles}, {checked['nnz']} entries, "
          f"every checksum and row marker checked in {time.perf_counter() - t0:.1f} s")
    return 0
