"""``bigT invert``: the stratified inverse of a stored T (bigT.stratified_inverse)."""

from __future__ import annotations

import json
import os

from .. import config
from ._argtypes import integer, memory_size, number, scheduler_address

TERMS_HELP = (
    "series terms n: the store holds T_n^-1 = F^-1 sum_{k=0..n} (I - T F^-1)^k (paper eq. "
    "13), so --terms 0 is F^-1 alone and each term costs one sparse product (power form). "
    "The paper also counts bounces from 1 (§5.1 calls T_4^-1 the five-bounce inverse); "
    "this option uses eq. 13's n. newton-schulz rounds n up to 2^j - 1 (default 4)")


def register(subparsers) -> None:
    from ..algorithms.methods import METHODS

    p = subparsers.add_parser(
        "invert", help="stratified inverse of a stored T, out of core, term by term",
        description="Compute the stratified inverse T_n^-1 = F^-1 sum_{k=0..n} "
                    "(I - T F^-1)^k (paper eq. 13) of a bigT store, term by term, into a "
                    "versioned store. An interrupted run is resumed by running the same "
                    "command again; the store always holds the last complete term.")
    p.add_argument("T", metavar="T.zarr")
    p.add_argument("-o", "--output", required=True, metavar="X.zarr",
                   help="the inverse store (created, or resumed when it holds the same "
                        "T and parameters)")
    p.add_argument("--terms", type=integer(0), default=4, help=TERMS_HELP)
    p.add_argument("--prune", type=number(0), default=config.DEFAULT_PRUNE,
                   help="drop entries below this (absolute, on the dimensionless terms "
                        "M^k) inside each product (default %(default)g)")
    p.add_argument("--prune-feed", dest="prune_feed", type=number(0), default=None,
                   help="power form: prune P_k, the factor of the next product, at this "
                        "(>= --prune) while X keeps each term's entries down to --prune: "
                        "less work for about the same error (default: --prune)")
    p.add_argument("--tol", type=number(0), default=None,
                   help="stop once the estimated ||I - T X||_F / sqrt(n) is below this")
    p.add_argument("--method", choices=tuple(METHODS), default="power",
                   help="; ".join(f"{m.name}: {m.help}" for m in METHODS.values()))
    p.add_argument("--first-bounce", default="diag", metavar="diag|identity|FILE.npy",
                   help="F: diag(T) (default), identity (the naive choice), or a .npy vector "
                        "(e.g. recovered from an earlier inverse, F_ii = 1 / X_ii)")
    p.add_argument("--scheduler", type=scheduler_address, default=None,
                   metavar="ADDRESS|local:N",
                   help="run the tasks on a dask cluster: a scheduler address "
                        "(tcp://HOST:PORT; T and the output must be at the same paths on "
                        "every worker), or local:N to start N worker processes for this "
                        "run (default: local threads)")
    p.add_argument("--workers", type=integer(1), default=2,
                   help="threads of the local scheduler (default %(default)s)")
    p.add_argument("--memory-limit", type=memory_size, default=None, metavar="SIZE",
                   help="bound the resident memory of the process running the tasks, e.g. "
                        "2GiB (with local:N, of the N workers together; a cluster's workers "
                        "also keep their own limits): what a process already holds is "
                        "measured and the rest shared out (tile cache, a shared right "
                        "factor, per-task batches); a limit too small is refused with the "
                        "sizes")
    p.add_argument("--json", default=None, metavar="FILE",
                   help="also write the report as JSON")
    p.add_argument("--force", action="store_true",
                   help="run even when the estimated spectral radius of M is >= 1")
    p.add_argument("--overwrite", action="store_true",
                   help="delete the inverse the output holds (whatever its parameters) and "
                        "start anew; never deletes anything that is not a bigT inverse")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=invert_cmd)


def invert_cmd(args) -> int:
    from ..algorithms import stratified_inverse

    from ..errors import BigTError

    fb = args.first_bounce
    if fb not in ("diag", "identity") and not os.path.exists(fb):
        raise BigTError("--first-bounce is neither diag, identity nor an existing .npy file",
                        fb)
    if args.json and os.path.isdir(args.json):  # refused now, not after the whole run
        raise BigTError("is a folder; the --json report is a file: choose a file name",
                        args.json)
    report = stratified_inverse(
        args.T, args.output, terms=args.terms, prune=args.prune, tol=args.tol,
        prune_feed=args.prune_feed,
        first_bounce=fb, method=args.method, scheduler=args.scheduler,
        memory_limit=args.memory_limit, progress=not args.no_progress, force=args.force,
        workers=args.workers, overwrite=args.overwrite)
    print(report.table())
    print(f"{report.products} tile products in {report.seconds:.1f} s -> {report.path}")
    if args.json:
        from ..atomic import atomic_output

        with atomic_output(args.json, "the JSON report") as tmp:
            tmp.write_text(json.dumps(report.to_dict(), indent=1, default=str))
    return 0
