"""The series methods of the stratified inverse, each one object: its next-term rule,
the passes of a term (which task runs, which term stores it reads and writes) and its
exhaustion test. The block tasks (one row block of one pass) live here too, beside the
method that uses them; the engine (:mod:`.engine`) knows none of their details.

All work in the dimensionless variables of paper eq. 13: P_k = M^k, S_n = sum_{k<=n}
M^k, and X = F^-1 S is stored. Adding a method is one class here and one entry in
:data:`METHODS`; the CLI takes its choices from that.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

from ..schedule import blocks
from ..kernels import prune, spmm_dense
from ..schedule.worker import TaskContext
from .defaults import METHOD_HELP


@dataclass(frozen=True)
class Pass:
    """One pass of a term.

    Attributes
    ----------
    op : str
    task : callable ``task(ctx) -> BlockStats``
    inputs : tuple of (alias, store name, term)
        The task reads input ``alias`` from store ``name`` of term ``term``
        (e.g. ``("S", "X", 3)``: S read from t0003/X).
    outputs : tuple of str, the stores of the new term it writes
    right : str or None, the alias multiplied from the right
    scaled : tuple of str, aliases read as F B (S = F X)
    probed : bool, the task reports (X_k - X_{k-1}) Z for the engine's residual probes
        Z (shared as ``"Z"``, shape (n, p); only to such passes: on a cluster every
        shared array is sent to every worker)
    """

    op: str
    task: Callable
    inputs: tuple[tuple[str, str, int], ...] = ()
    outputs: tuple[str, ...] = ("X",)
    right: str | None = None
    scaled: tuple[str, ...] = ()
    probed: bool = False


# --- block tasks ---------------------------------------------------------------------

def _x_rows(ctx: TaskContext, S: sp.csr_array) -> sp.csr_array:
    """X = F^-1 S on the block's rows (a colour F^-1 mixes each pixel's 3 rows),
    explicit zeros dropped."""
    X = ctx.inverse.scale_rows(sp.csr_array(S), ctx.start, ctx.dtype)
    X.eliminate_zeros()
    return X


def _read_rows(ctx: TaskContext, alias: str) -> sp.csr_array:
    """The block's rows of input ``alias`` (not cached: read once per term)."""
    return ctx.operand(alias).rows(ctx.start, ctx.stop, cached=False)


def diag_task(ctx: TaskContext):
    """X_0 = F^-1 (term 0): a diagonal, or per-pixel 3x3 blocks for colour."""
    X = ctx.inverse.rows(ctx.start, ctx.stop, ctx.dtype)
    ctx.write("X", X)
    return ctx.stats(nnz_P=X.nnz, nnz_X=X.nnz)


def power_task(ctx: TaskContext):
    """Q_k = (M P_{k-1}) pruned, X_k = X_{k-1} + F^-1 Q_k on the block's rows, and
    P_k = Q_k, or Q_k pruned again at the spec's ``feed_threshold``. Term 1 needs no
    product: Q_1 = M P_0 = M, pruned. Rows whose every factor met a converged (empty)
    row of P_{k-1} carry X over.

    Why two thresholds: an entry dropped from Q_k only stays in X, so its error
    reaches the residual through M times it (the next terms miss M D_k, M^2 D_k, ...),
    not as D_k itself: P_k, which sets the next product's cost, may be pruned harder
    for the same error (docs/DESIGN.md, "Carrying"). Likewise the entries of M
    below the spec's ``operator_threshold`` are left out of the product M P_{k-1}
    (k >= 2): what they would add is one bounce further down, D P_{k-1}, not D."""
    M = ctx.M.rows(ctx.start, ctx.stop)
    computed = skipped = 0
    spec = ctx.spec
    if "P" in dict(spec.inputs):
        left = (M if spec.operator_threshold is None
                else prune(M, threshold=spec.operator_threshold))
        Q, computed, skipped = ctx.product(left, "P", spec.threshold)
    else:
        Q = prune(M, threshold=spec.threshold)
    feed = spec.threshold if spec.feed_threshold is None else spec.feed_threshold
    P = prune(Q, threshold=feed) if feed > spec.threshold and Q.nnz else Q
    X, kept, kept_nnz = _x_updated(ctx, Q)
    ctx.write("P", P)
    ctx.write("X", X, keep_from="X", kept_columns=kept, kept_nnz=kept_nnz)
    carried = "P" in dict(ctx.spec.inputs) and computed == 0
    return ctx.stats(nnz_P=P.nnz, nnz_X=X.nnz + int(kept_nnz.sum()), computed=computed,
                     skipped=skipped, row_skipped=carried, y=_probed(ctx, Q))


def _x_updated(ctx: TaskContext, Q: sp.csr_array):
    """X_k = X_{k-1} + F^-1 Q_k on the block's tile row, as (the rows of the tiles Q_k
    touches, updated; the other stored tile columns of X_{k-1}, (m,) int64; their
    entries, (m,) int64). Only the touched tiles are read and rewritten: the others
    are carried over unchanged, which saves most of X's rewrite in the late terms,
    where Q_k is small. A store that keeps its tile rows whole (format 2) carries a
    row Q_k does not touch whole (its files hard-linked) and reads and rewrites the
    others whole."""
    X_prev = ctx.operand("X").store
    i = ctx.block.index
    if (X_prev.tile_size != ctx.spec.block_rows or i >= X_prev.grid[0]
            or X_prev.tile_row_range(i) != (ctx.start, ctx.stop)):  # another tiling: read all
        part, kept, kept_nnz = _read_rows(ctx, "X"), np.empty(0, np.int64), np.empty(0, np.int64)
    else:
        stored = X_prev.tile_columns(i)
        touched = np.isin(stored, np.unique(Q.indices // X_prev.tile_size))
        if X_prev.row_layout and (touched.any() or Q.nnz):
            touched[:] = True  # a row is read whole: carry all of it (linked) or none
        part = (X_prev.get_tile_row(i, columns=stored[touched]) if touched.any()
                else sp.csr_array((ctx.stop - ctx.start, X_prev.shape[1]), dtype=ctx.dtype))
        stored_nnz = X_prev.tile_nnz[X_prev.tile_indptr[i]:X_prev.tile_indptr[i + 1]]
        kept, kept_nnz = stored[~touched], stored_nnz[~touched]
    if Q.nnz and ctx.inverse.b == 1:
        part = blocks.add_scaled(part, ctx.finv[ctx.start:ctx.stop], Q)
    elif Q.nnz:
        part = sp.csr_array(part + ctx.inverse.scale_rows(Q, ctx.start, ctx.dtype))
        part.eliminate_zeros()
        part.sort_indices()
    return part, kept, kept_nnz


def _probed(ctx: TaskContext, Q: sp.csr_array):
    """The block's rows of (X_k - X_{k-1}) Z = F^-1 Q_k Z, shape (rows, p), for the
    engine's residual probes Z (shared as ``"Z"``, shape (n, p)): with them the engine
    updates X Z without reading X back. None when the pass shares no probes."""
    Z = ctx.shared.get("Z")
    if Z is None:
        return None
    out = np.zeros((ctx.stop - ctx.start, Z.shape[1]), np.float64)
    if Q.nnz:
        spmm_dense(Q, Z, out=out, n_threads=1)
        out = ctx.inverse.apply(out, ctx.start)
    return out


def horner_task(ctx: TaskContext):
    """S_n = D + (M S_{n-1}) pruned, X_n = F^-1 S_n, with S_{n-1} = F X_{n-1}."""
    M = ctx.M.rows(ctx.start, ctx.stop)
    MS, computed, skipped = ctx.product(M, "S", ctx.spec.threshold)
    X = _x_rows(ctx, ctx.identity_rows() + MS)
    ctx.write("X", X)
    return ctx.stats(nnz_P=MS.nnz, nnz_X=X.nnz, computed=computed, skipped=skipped)


def ns_residual_task(ctx: TaskContext):
    """R = (I - T X) = D - S + M S (pruned) with S = F X, on the kept pixels."""
    M = ctx.M.rows(ctx.start, ctx.stop)
    MS, computed, skipped = ctx.product(M, "S", 0.0)
    R = prune(sp.csr_array(ctx.identity_rows() - _read_rows(ctx, "S") + MS),
              threshold=ctx.spec.threshold)
    ctx.write("R", R)
    return ctx.stats(nnz_P=R.nnz, computed=computed, skipped=skipped)


def ns_update_task(ctx: TaskContext):
    """S' = S + (S R) pruned, X' = F^-1 S': with the residual pass,
    X' = X + X (I - T X) = X (2I - T X)."""
    S = _read_rows(ctx, "S")
    SR, computed, skipped = ctx.product(S, "R", ctx.spec.threshold)
    X = _x_rows(ctx, S + SR)
    ctx.write("X", X)
    return ctx.stats(nnz_X=X.nnz, computed=computed, skipped=skipped)


#: Term 0, the same for every method: X_0 = F^-1.
TERM_ZERO = Pass("diag", diag_task)


# --- the methods -----------------------------------------------------------------------

class SeriesMethod:
    """A series method: subclasses set ``name`` and ``help`` and define
    :meth:`next_term` and :meth:`passes`; :meth:`exhausted` says when every later
    term is exactly zero."""

    name = ""
    help = ""

    def next_term(self, held: int) -> int:
        return held + 1

    def passes(self, held: int, k: int) -> list[Pass]:
        raise NotImplementedError

    def exhausted(self, held: int, name: str, store) -> str | None:
        """A reason to stop when the finished store ``name`` (an output of a pass of
        the term after ``held``, or an input held) shows the series has ended."""
        return None


class Power(SeriesMethod):
    """P_0 = I, P_k = M P_{k-1} (pruned), X_k = X_{k-1} + F^-1 P_k: one product with
    the shrinking P_{k-1} per term."""

    name = "power"
    help = METHOD_HELP[name]  # .defaults: the CLI lists them without importing this module

    def passes(self, held, k):
        inputs = (("X", "X", held),) if held == 0 else (("P", "P", held), ("X", "X", held))
        return [Pass("power", power_task, inputs, ("P", "X"), right="P" if held else None,
                     probed=True)]

    def exhausted(self, held, name, store):
        if name == "P" and store.nnz == 0:
            return f"series exhausted at term {held} (P_{held} = 0)"
        return None


class Horner(SeriesMethod):
    """S_n = I + M S_{n-1}: one product with the ever-growing S per term; corrects
    earlier pruning (docs/DESIGN.md, "Power against Horner")."""

    name = "horner"
    help = METHOD_HELP[name]

    def passes(self, held, k):
        return [Pass("horner", horner_task, (("S", "X", held),), ("X",), right="S",
                     scaled=("S",))]


class NewtonSchulz(SeriesMethod):
    """X <- X (2I - T X), as R = I - T X then X <- X + X R (two products per step);
    after j steps from X_0 = F^-1, X = T_{2^j - 1}^-1."""

    name = "newton-schulz"
    help = METHOD_HELP[name]

    def next_term(self, held):
        return 2 * held + 1

    def passes(self, held, k):
        return [
            Pass("ns-residual", ns_residual_task, (("S", "X", held),), ("R",), right="S",
                 scaled=("S",)),
            Pass("ns-update", ns_update_task, (("S", "X", held), ("R", "R", k)), ("X",),
                 right="R", scaled=("S",)),
        ]

    def exhausted(self, held, name, store):
        if name == "R" and store.nnz == 0:
            return f"series exhausted at term {held} (I - T X pruned to 0)"
        return None


METHODS: dict[str, SeriesMethod] = {m.name: m for m in (Power(), Horner(), NewtonSchulz())}
