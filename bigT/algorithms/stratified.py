"""The stratified inverse, out of core, term by term, resumable (paper §4.2, eq. 13).

``stratified_inverse(T, out, terms=n)`` writes T_n^-1 = F^-1 sum_{k=0..n} M^k, with
M = I - T F^-1, into the inverse store ``out``: ``terms=0`` is F^-1 alone and each term
adds one power of M (in the power form, one sparse product; the first, M P_0 = M, is
free). The paper counts bounces two ways: eq. 13's index n, used here, and §5.1's
"n-bounce inverse", which calls T_0^-1 the one-bounce stratified inverse.

Where the rest lives:

* the series methods (``"power"``, ``"horner"``, ``"newton-schulz"``) and their block
  tasks: :mod:`.methods`; the thresholds ``prune``, ``prune_feed``, ``prune_operator``
  and the one place they become :class:`~bigT.schedule.spec.PassSpec`'s:
  :mod:`.settings`. The pruning error bound, power against Horner under pruning, and
  why P_k and M may be pruned harder ("Carrying"): docs/DESIGN.md;
* the run (rho(M) checked before term 0, the terms computed and published one by one,
  a growing residual refused, the resume): :mod:`.engine`, a driver whose docstring
  names the module of each of its steps; the residual estimate:
  :mod:`.residual`; what a store's inverse depends on: :mod:`.fingerprint`; the
  record kept in the store: :mod:`.records`; the report: :mod:`.report`.

Paper §5.1 note: the printed eqs. 35-41 are not consistent with the printed T of eq. 34
(eq. 37's diagonal is not the inverse of eq. 36's; eq. 38 is not symmetric where T is).
The tests compare with values computed independently (dense numpy) from eq. 34.
"""

from __future__ import annotations

import os
import time

from .. import config
from ..atomic import refuse_overwriting_inputs
from ..errors import NotSquareError
from ..schedule.runner import open_runner, worker_path
from ..sizes import parse_size
from ..storage import InverseStore, as_store
from . import defaults
from .engine import InverseEngine
from .global_mixing import global_mixing_inverse, with_colour_path
from .methods import METHODS as SERIES_METHODS
from .mixing import checked_colour_path, choose_colour_path
from .report import InverseReport
from .settings import SeriesSettings, checked_method, checked_thresholds

#: The series methods' names, the default first.
METHODS = tuple(SERIES_METHODS)


def stratified_inverse(T, out, terms=defaults.TERMS, prune=config.DEFAULT_PRUNE, tol=None,
                       first_bounce=defaults.FIRST_BOUNCE, method=defaults.METHOD,
                       client=None, memory_limit=None, progress=True, force=False, *,
                       workers=defaults.WORKERS, seed=0,
                       scheduler=None, overwrite=False, prune_feed=None,
                       prune_operator=None, on_term=None, colour_path="auto",
                       mixing=None, in_memory=None, T_rows=None) -> InverseReport:
    """Compute the stratified inverse T_n^-1 = F^-1 sum_{k=0..n} (I - T F^-1)^k
    (paper eq. 13) out of core, term by term, into the store ``out``.

    ``terms=n`` follows eq. 13's index: ``terms=0`` is F^-1, and each term adds one
    power of M = I - T F^-1 (one sparse product in the power form). The paper's §5.1
    calls T_n^-1 the "(n+1)-bounce" stratified inverse: the same matrix, counted from 1.

    Parameters
    ----------
    T : BlockCSR or str/PathLike, shape (n, n)
        The light transport, square (after the pixel correspondence).
    out : str or PathLike
        The inverse store. Created; or, when it holds an inverse of the same T with
        the same prune, method and first bounce, resumed (a held term >= ``terms``
        returns at once). Any other existing ``out`` is refused (StoreError).
    terms : int >= 0
    prune : float >= 0
        Entries of each new (dimensionless) term below this are dropped in the product.
    prune_feed : float >= prune, optional
        Power form only: P_k, the factor of the next product, is pruned at this
        instead, while X keeps the term's entries down to ``prune`` ("Carrying" in
        docs/DESIGN.md: less work for the same error). Default: ``prune``.
    prune_operator : float >= prune, optional
        Power form only: M's entries below this are left out of the products of the
        terms k >= 2, M P_{k-1}; term 1 still adds M down to ``prune`` (docs/DESIGN.md,
        after "Carrying": what they would add is one bounce further down). Default:
        none left out.
    tol : float, optional
        Stop once the estimated relative residual ||I - T X||_F / sqrt(n) <= tol.
    first_bounce : "diag", "identity", (n,) array or path of a .npy
        F: diag(T) (Jacobi, paper §4.4), I (the naive choice, often divergent), or a
        known F, e.g. from :func:`recover_first_bounce`.
    method : "power", "horner" or "newton-schulz" (:mod:`bigT.algorithms.methods`)
    scheduler : None, "local:N", an address or a distributed.Client
        Where the tasks run (:func:`bigT.schedule.runner.open_runner`): dask's local
        threaded scheduler with ``workers`` threads by default; ``local:N`` starts N
        worker processes for the run; an address ("tcp://host:port") or a Client uses
        that cluster, whose workers must see ``T`` and ``out`` at the same paths.
    client : distributed.Client or str, optional
        The same as ``scheduler`` (kept for callers of bigT 0.1).
    memory_limit : int or str, optional
        Bytes ("2GiB") for the resident memory of the process running the tasks (with
        ``local:N``, of the N workers together; on a cluster each worker also keeps
        its own limit). Each process measures what it holds and shares out the rest
        (:func:`bigT.schedule.memory.plan_memory`); a limit too small for the fixed
        parts raises ``MemoryLimitError`` before anything is written.
    progress : bool
        Progress bars (shown only when stderr is a terminal).
    force : bool
        Go on although the estimated spectral radius of M is >= 1.
    overwrite : bool
        Delete an inverse ``out`` holds (whatever its parameters) and start anew;
        never anything that is not a bigT inverse store.
    on_term : callable, optional
        ``on_term(record)`` is called after each term this run computes is published
        (``record`` the store's :class:`~bigT.algorithms.records.SeriesRecord`; ``out`` then holds that term),
        and first for the term held when the run resumes a store short of ``terms``;
        a string returned stops the run there, as its ``stopped`` reason. One run
        with it costs less than a run per term (one set-up, one spectral radius
        read): :func:`bigT.algorithms.target.invert_to_target` measures each term so.
        A callable with an attribute ``reads_term``, a callable taking a term's index,
        says before each term whether it reads that term from ``out``; for a term it
        does not read, a run in memory calls it with the term's record unpublished
        (the store holding an earlier term), as a run without ``on_term`` goes past
        a term. An attribute ``needs_residual`` that is false says that it measures
        the terms' errors itself: without ``tol``, no term's residual is estimated
        (their records hold none) and none is refused for growing. One with a true
        ``takes_X`` is called ``on_term(record, X=...)``: in memory the term's X as
        this process holds it (csr_array, stored order; else None), to multiply
        with instead of reading ``out``.
    colour_path : {"auto", "general", "global"}
        For a colour T (channels 3; a grey T ignores it): ``"global"`` inverts three
        grey transports between two 3x3 un-mixings when the rig's colour mixing is one
        camera C and one projector P for every pixel (:mod:`bigT.algorithms.mixing`:
        the mixing given, or recorded with T, or estimated from T's diagonal blocks,
        verified over all of T; refused, saying why, when it does not hold);
        ``"general"`` runs the colour engine (3x3 block-diagonal F); ``"auto"`` takes
        the global path when the mixing holds, else the general one.
    mixing : (camera, projector) pair of 3x3 arrays, optional
        The rig's global mixing, when known (else the one recorded with T, or the
        estimate); still verified.
    in_memory : None, True or False
        Where the series runs (:mod:`bigT.algorithms.engine_path`). None: in memory
        (:mod:`bigT.algorithms.resident`: M and the terms held by this process, the
        same kernels and pruning, no dask tasks) when the tasks would run in this
        process and M fits the memory budget (what ``memory_limit`` leaves, or half
        the available memory), else out of core; a run in memory goes on out of core
        before a term predicted not to fit. True: in memory whatever the estimate
        (refused with a cluster scheduler); False: out of core. Either way every term
        published is written into ``out`` the same way, so a run on one path resumes
        on the other; in memory, a term the run goes past is published only when
        ``on_term`` is given or 5 s passed since the last one published
        (:mod:`bigT.algorithms.engine`), its record kept all the same. The report's
        ``engine_path`` and each term's record say which path ran.
    T_rows : :class:`~bigT.algorithms.run_setup.TileRows` of ``T``, optional
        T's tile rows the caller holds: F's diagonal and, in memory, M are taken from
        them instead of reading T again (:func:`bigT.algorithms.target.invert_to_target`
        reads T once for its own products and every attempt). A grey T only.

    Returns
    -------
    InverseReport
        For a colour T, a :class:`~bigT.algorithms.global_mixing.ColourInverseReport`:
        ``colour_path`` and ``colour_reason`` say which path was taken and why.

    Raises
    ------
    MemoryLimitError
        ``memory_limit`` cannot hold what the run needs at the least.
    DivergenceError
        rho(M) >= 1 (and not ``force``).
    InvalidMatrixError
        Negative or zero diagonal on lit pixels with ``first_bounce="diag"``.
    StoreError
        ``out`` exists and holds something else.
    SchedulerError
        The scheduler cannot be reached, or its workers cannot see the stores.
    """
    t_start = time.perf_counter()
    series = checked_method(method, terms, tol)
    thresholds = checked_thresholds(method, prune, prune_feed, prune_operator)
    scheduler = client if scheduler is None else scheduler
    if isinstance(T, (str, os.PathLike)):
        T = worker_path(T, "transport T")  # a URL of a scheme not served is refused here
    T = as_store(T, "T")
    if T.shape[0] != T.shape[1]:
        raise NotSquareError(f"T is {T.shape[0]} x {T.shape[1]}; the inverse needs a square "
                             "T (apply the pixel correspondence first)", T.path)
    out = worker_path(out, "inverse store")
    fb_file = (first_bounce if isinstance(first_bounce, (str, os.PathLike))
               and str(first_bounce) not in ("diag", "identity") else None)  # a .npy read
    refuse_overwriting_inputs([out], [T.path, T.redirected_from, fb_file])
    checked_colour_path(colour_path)
    choice = (choose_colour_path(T, colour_path, mixing, first_bounce=first_bounce,
                                 on_term=on_term, seed=seed) if T.channels == 3 else None)
    if choice is not None and choice.path == "global":  # three grey inverses of U
        grey = dict(terms=terms, prune=prune, tol=tol, first_bounce=first_bounce,
                    method=method, memory_limit=memory_limit, progress=progress,
                    force=force, workers=workers, seed=seed, scheduler=scheduler,
                    overwrite=overwrite, prune_feed=prune_feed,
                    prune_operator=prune_operator, in_memory=in_memory)
        return global_mixing_inverse(T, out, choice, grey, grey_inverse=stratified_inverse,
                                     t_start=t_start)
    settings = SeriesSettings(int(terms), thresholds, tol, progress, force, seed,
                              overwrite, on_term)
    memory_limit = None if memory_limit is None else parse_size(memory_limit, "memory_limit")
    runner = open_runner(scheduler, workers=workers, memory_limit=memory_limit)
    store = InverseStore(out)
    try:
        engine = InverseEngine(T, store, series, runner, settings, first_bounce, memory_limit,
                               in_memory, T_rows)
        report = engine.run(t_start)
    finally:
        _let_go(runner, T, out)
        store.close()  # the writer lock, whatever failed
    return report if choice is None else with_colour_path(report, choice)


def _let_go(runner, T, out) -> None:
    """End of a run: every process forgets the cached rows of T's M and of the
    inverse's terms (a caller's later work starts with an empty cache), then the
    runner closes what it started."""
    try:
        runner.end_pass(None, forget=(worker_path(T.path), out))
    except Exception:  # a cluster gone with the run: nothing left to free
        pass
    runner.close()
