"""``bigT invert``: the stratified inverse of a stored T (bigT.stratified_inverse)."""

from __future__ import annotations

import json
import os
import sys

from ..atomic import atomic_output, refuse_overwriting_inputs
from ..errors import BigTError
from ._argtypes import integer, number
from ._options import add_memory_limit, add_progress, add_scheduler, add_threads

# The library's layers are imported inside each command's functions, where the
# command runs: building the parser imports every command module, and a command
# should pay only for the layers it uses (stores: zarr ~0.3 s; compensation ~0.5 s).

TERMS_HELP = (
    "series terms n: the store holds T_n^-1 = F^-1 sum_{{k=0..n}} (I - T F^-1)^k (paper eq. "
    "13), so --terms 0 is F^-1 alone and each term costs one sparse product (power form). "
    "The paper also counts bounces from 1 (§5.1 calls T_4^-1 the five-bounce inverse); "
    "this option uses eq. 13's n. newton-schulz rounds n up to 2^j - 1. With no series "
    "option, as many as an invisible error needs (below); with --prune, --prune-feed, "
    "--prune-operator, --tol or --force, a fixed setting (default {terms})")

DEFAULT_HELP = (
    "With none of --terms, --prune, --prune-feed, --prune-operator, --tol, --force and "
    "--target-error, a grey T gets the quickest inverse whose error is invisible on an "
    "8-bit projector: --target-error {target:g}, measured to keep the projector image "
    "within {levels:g} of an 8-bit level of the exact inverse's on the scenes of "
    "benchmarks/bench_defaults.py (a store made with other settings is resumed with "
    "its own). Give --terms or --prune for a fixed setting (a colour T runs the fixed "
    "default)")

#: The options that make a fixed-setting run; with none of them (and no
#: --target-error), a grey T runs the default target error.
SERIES_OPTIONS = ("terms", "prune", "prune_feed", "prune_operator", "tol", "force")


def register(subparsers) -> None:
    from .. import config  # light: constants only

    p = subparsers.add_parser(
        "invert", help="stratified inverse of a stored T, out of core, term by term",
        description="Compute the stratified inverse T_n^-1 = F^-1 sum_{k=0..n} "
                    "(I - T F^-1)^k (paper eq. 13) of a bigT store, term by term, into a "
                    "versioned store. An interrupted run is resumed by running the same "
                    "command again; the store always holds the last complete term. "
                    + DEFAULT_HELP.format(target=config.DEFAULT_TARGET_ERROR,
                                          levels=config.INVISIBLE_LEVELS))
    # added when invert runs or prints its help: no other command's parser needs them
    p.defer(_add_options)
    p.set_defaults(func=invert_cmd)


def _add_options(p) -> None:
    """``invert``'s arguments, their defaults and method names the library's own (one
    source of truth: the engine's signature takes them from the light
    :mod:`bigT.algorithms.defaults` and :mod:`bigT.config`, read here without importing
    the engine, its numpy, scipy and stores)."""
    from .. import config
    from ..algorithms import defaults

    p.add_argument("T", metavar="T.zarr")
    p.add_argument("-o", "--output", required=True, metavar="X.zarr",
                   help="the inverse store (created, or resumed when it holds the same "
                        "T and parameters)")
    # an option not given is not passed: the library's default applies (shown here, the
    # values its signature takes), and --target-error can tell what was given explicitly
    p.add_argument("--terms", type=integer(0), default=None,
                   help=TERMS_HELP.format(terms=defaults.TERMS))
    p.add_argument("--prune", type=number(0), default=None,
                   help="drop entries below this (absolute, on the dimensionless terms "
                        f"M^k) inside each product (default {config.DEFAULT_PRUNE:g} in a "
                        "fixed-setting run; with --target-error, the first prune tried, "
                        f"P_k fed on at {config.TARGET_FEED_RATIO:g}x it and M pruned at "
                        f"{config.TARGET_OPERATOR_RATIO:g}x it in the products)")
    p.add_argument("--prune-feed", dest="prune_feed", type=number(0), default=None,
                   help="power form: prune P_k, the factor of the next product, at this "
                        "(>= --prune) while X keeps each term's entries down to --prune: "
                        "less work for about the same error (default: --prune)")
    p.add_argument("--prune-operator", dest="prune_operator", type=number(0), default=None,
                   help="power form: leave M's entries below this (>= --prune) out of the "
                        "products of the terms after the first, M P_{k-1}; the first term "
                        "still adds M down to --prune. What they would add is one bounce "
                        "further down: less work for about the same error (default: none "
                        "left out)")
    p.add_argument("--tol", type=number(0), default=None,
                   help="stop once the estimated ||I - T X||_F / sqrt(n) is below this")
    p.add_argument("--method", choices=tuple(defaults.METHOD_HELP), default=None,
                   help="; ".join(f"{name}: {text}"
                                  for name, text in defaults.METHOD_HELP.items())
                   + f" (default {defaults.METHOD}; with --target-error, fixes the method instead of "
                     "choosing it)")
    p.add_argument("--target-error", type=number(0, 1, lo_open=True, hi_open=True),
                   default=None, metavar="E",
                   help="choose the method, prune and number of terms that bring the "
                        "relative error of compensated probe images below E (e.g. "
                        "0.0039 = 1/255 for an 8-bit display) at the least cost, and "
                        "stop there; exit 1 when it stops short (best effort). Refuses "
                        "--terms, --tol, --prune-feed, --prune-operator and --force. "
                        f"Default {config.DEFAULT_TARGET_ERROR:g} when no fixed setting is "
                        "asked for (see above)")
    p.add_argument("--colour-path", dest="colour_path", choices=("auto", "general", "global"),
                   default="auto",
                   help="a colour T: 'global' inverts three grey transports between two "
                        "3x3 un-mixings when the rig's colour mixing is one camera and one "
                        "projector matrix for every pixel (recorded with T, or estimated "
                        "from its diagonal blocks; verified over all of T, refused when it "
                        "does not hold); 'general' the 3x3 block-diagonal engine; 'auto' "
                        "global when the mixing holds, else general (default). A grey T "
                        "ignores it")
    p.add_argument("--first-bounce", default=defaults.FIRST_BOUNCE,
                   metavar="diag|diag-skip-ill|identity|FILE.npy",
                   help="F: diag(T), identity (the naive choice), or a .npy vector "
                        "(e.g. recovered from an earlier inverse, F_ii = 1 / X_ii); default "
                        "%(default)s. Colour: diag is T's 3x3 diagonal blocks (each pixel's "
                        "colour mixing, inverted per pixel; a .npy holds (H*W, 3, 3) "
                        "blocks); diag-skip-ill leaves out the pixels whose block is "
                        "ill-conditioned instead of refusing them")
    add_scheduler(p, "tasks", "; T and the output must be at the same paths on every "
                  "worker")
    add_threads(p, defaults.WORKERS)
    add_memory_limit(
        p, default=None,
        bounds="bound the resident memory of the process running the tasks, e.g. 2GiB "
        "(with local:N, of the N workers together; a cluster's workers also keep their own "
        "limits): what a process already holds is measured and the rest shared out (tile "
        "cache, a shared right factor, per-task batches); a limit too small is refused "
        "with the sizes")
    p.add_argument("--json", nargs="?", const="-", default=None, metavar="FILE",
                   help="print the report as one JSON object on stdout instead of the "
                        "table (as every command's --json does); --json FILE, the older "
                        "form, writes it to FILE beside the table")
    p.add_argument("--force", action="store_true",
                   help="run even when the estimated spectral radius of M is >= 1")
    p.add_argument("--overwrite", action="store_true",
                   help="delete the inverse the output holds (whatever its parameters) and "
                        "start anew; never deletes anything that is not a bigT inverse")
    add_progress(p)


def _default_run(args) -> bool:
    """No option asks for a fixed setting (SERIES_OPTIONS, a colour path) and T is grey:
    the run is the default target error's. A colour T keeps the fixed default, whose
    automatic colour path may invert three grey transports instead (the target error
    measures the general path)."""
    if any(getattr(args, name) not in (None, False) for name in SERIES_OPTIONS) \
            or args.colour_path != "auto":
        return False
    from ..storage import open as open_store  # zarr: the run opens T anyway

    return getattr(open_store(args.T), "channels", 1) == 1


def invert_cmd(args) -> int:
    from .. import config
    from ..algorithms import stratified_inverse

    fb = args.first_bounce
    if fb not in ("diag", "diag-skip-ill", "identity") and not os.path.exists(fb):
        raise BigTError("--first-bounce is neither diag, identity nor an existing .npy file",
                        fb)
    if args.json not in (None, "-") and os.path.isdir(args.json):  # refused now, not after the run
        raise BigTError("is a folder; the --json report is a file: choose a file name",
                        args.json)

    json_file = None if args.json == "-" else args.json
    refuse_overwriting_inputs([args.output, json_file],
                              [args.T, None if fb in ("diag", "identity") else fb])
    if args.target_error is None and _default_run(args):
        args.target_error = config.DEFAULT_TARGET_ERROR
        args.target_default = True
    if args.target_error is not None:
        if args.colour_path == "global":
            raise BigTError("--colour-path global cannot be combined with --target-error, "
                            "which measures the general path's terms as they are published")
        return _invert_to_target(args, fb)
    given = {name: getattr(args, name) for name in ("terms", "prune", "method")
             if getattr(args, name) is not None}
    report = stratified_inverse(
        args.T, args.output, tol=args.tol, prune_feed=args.prune_feed,
        prune_operator=args.prune_operator, first_bounce=fb, scheduler=args.scheduler,
        memory_limit=args.memory_limit, progress=args.progress, force=args.force,
        workers=args.workers, overwrite=args.overwrite, colour_path=args.colour_path,
        **given)
    if args.json != "-":
        if getattr(report, "colour_reason", None):  # a colour T: which path, and why
            print(f"colour path: {report.colour_reason}")
        print(report.table())
        if getattr(report, "colour_path", None) == "global":
            print(f"global path: un-mixing T {report.seconds_split:.2f} s, publishing X "
                  f"factored {report.seconds_publish:.2f} s, nnz(X) {report.nnz_X:,}")
        print(f"{report.products} tile products in {report.seconds:.1f} s -> {report.path}")
    _write_json(args.json, report.to_dict())
    return 0


def _invert_to_target(args, fb) -> int:
    """``--target-error``: the choice, why, and the probes' errors per term. Exit 0
    when the target is met, 1 after a best-effort stop (the store keeps the last
    term)."""
    from ..algorithms.target import invert_to_target

    for given, name in ((args.terms, "--terms"), (args.tol, "--tol"),
                        (args.prune_feed, "--prune-feed"),
                        (args.prune_operator, "--prune-operator"),
                        (args.force or None, "--force")):
        if given is not None:
            raise BigTError(f"{name} cannot be combined with --target-error, which chooses "
                            "the number of terms and stops on the measured error itself")
    report = invert_to_target(
        args.T, args.output, args.target_error, method=args.method, prune=args.prune,
        first_bounce=fb, memory_limit=args.memory_limit, scheduler=args.scheduler,
        workers=args.workers, progress=args.progress, overwrite=args.overwrite)
    if args.json != "-":
        if getattr(args, "target_default", False):
            print(f"default: the quickest inverse whose error is invisible at 8 bits "
                  f"(--target-error {args.target_error:g}); --terms or --prune for a "
                  "fixed setting")
        print(report.summary())
        print(f"-> {args.output}")
    _write_json(args.json, report.to_dict())
    return 0 if report.met else 1


def _write_json(path, data: dict) -> None:
    """``--json``: ``data`` on stdout ("-"), or into the file ``path``."""
    if path == "-":
        json.dump(data, sys.stdout, indent=1, default=str)
        print()
    elif path:

        with atomic_output(path, "the JSON report") as tmp:
            tmp.write_text(json.dumps(data, indent=1, default=str))
