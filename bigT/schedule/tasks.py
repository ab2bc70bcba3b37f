"""Row tasks of the series methods: each computes one output tile row of a term from
its input tiles, writes it through the term's writers and returns statistics.

All work in the dimensionless variables of paper eq. 13: P_k = M^k, S_n = sum_k<=n M^k,
with X = F^-1 S stored. The context (``graph.Context``) carries:

``M`` (:class:`~.operators.MOperand`), ``finv``/``f``/``active`` ((n,) arrays),
``threshold``, ``dtype``, ``n``, ``writers`` (name -> writer), ``done`` (name -> set
of complete tile rows), ``plan`` (:class:`~.memory.MemoryPlan`),
``kernel_threads`` and the
method's operands (below).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import blocks
from ._backend import prune, scale_rows
from .memory import PARTIAL_BYTES_PER_ENTRY

def _write(ctx, name, i, block):
    # Rows of one store are independent directories: writers need no lock.
    if i not in ctx.done[name]:
        ctx.writers[name].write_tile_row(i, block)


def _product(ctx, left, right, i, js_left, threshold):
    """Tile row i of left @ right, pruned; only tile pairs with both factors nonzero
    count (and are read): right's empty tile rows are never read.

    The memory plan decides how the right factor is read: whole, once per pass and
    shared by the tasks, when it fits ``ctx.whole_limit`` (bytes, set per pass); else
    the tile rows this product needs, in one batch when they fit a third of the task's
    work share (``ctx.plan``, :class:`~.memory.MemoryPlan`), or in several batches
    multiplied against chunks of the output rows (:func:`~.blocks.row_product_batched`).
    """
    use = [int(j) for j in js_left if right.nonempty[j]]
    a, b = ctx.M.row_range(i)
    skipped = len(js_left) - len(use)
    if not use:
        return blocks.empty((b - a, ctx.n), ctx.dtype), 0, skipped
    L = left.row(i)
    plan = ctx.plan
    if right.nbytes <= ctx.whole_limit:
        out = blocks.row_product(L, right.whole(), threshold, ctx.kernel_threads)
        return out, len(use), skipped
    batch_bytes = max(plan.work_bytes_per_task // 3, 1)
    groups, cur, cur_bytes = [], [], 0
    for j in use:
        if cur and cur_bytes + right.row_bytes(j) > batch_bytes:
            groups.append(cur)
            cur, cur_bytes = [], 0
        cur.append(j)
        cur_bytes += right.row_bytes(j)
    groups.append(cur)
    batches = [lambda js=js: right.assembled(js) for js in groups]
    partial = max((plan.work_bytes_per_task - batch_bytes) // PARTIAL_BYTES_PER_ENTRY, 1)
    out = blocks.row_product_batched(L, batches, threshold, right.work_per_row(L), partial,
                                     ctx.kernel_threads)
    return out, len(use), skipped


def power_row(ctx, i):
    """P_k[i] = (M P_{k-1})[i] pruned; X_k[i] = X_{k-1}[i] + F^-1 P_k[i].

    Term 1 needs no product: P_1 = M P_0 = M (P_0 = D), pruned.
    """
    a, b = ctx.M.row_range(i)
    if ctx.P_prev is None:
        P = prune(ctx.M.row(i), threshold=ctx.threshold)
        computed, skipped = 0, 0
    else:
        P, computed, skipped = _product(ctx, ctx.M, ctx.P_prev, i, ctx.M.tile_columns(i),
                                        ctx.threshold)
        if computed == 0:
            # every factor tile of this row met an empty (converged) row of P_{k-1}:
            # no product; X's row is carried over
            return _finish_power(ctx, i, P, ctx.X_prev.row(i), 0, skipped, True)
    Xp = ctx.X_prev.row(i)
    X = blocks.add_scaled(Xp, ctx.finv[a:b], P) if P.nnz else Xp
    return _finish_power(ctx, i, P, X, computed, skipped, False)


def _finish_power(ctx, i, P, X, computed, skipped, row_skipped):
    _write(ctx, "P", i, P)
    _write(ctx, "X", i, X)
    return {"i": i, "nnz_P": int(P.nnz), "nnz_X": int(X.nnz), "computed": computed,
            "skipped": skipped, "row_skipped": row_skipped}


def horner_row(ctx, i):
    """S_n[i] = D_i + (M S_{n-1})[i] (products pruned); X_n[i] = F^-1 S_n[i].

    S_{n-1} = F X_{n-1} is read from the previous X (``ctx.S_prev``).
    """
    a, b = ctx.M.row_range(i)
    MS, computed, skipped = _product(ctx, ctx.M, ctx.S_prev, i, ctx.M.tile_columns(i),
                                     ctx.threshold)
    S = sp.csr_array(blocks.identity_rows(a, b, ctx.n, ctx.active, ctx.dtype) + MS)
    X = scale_rows(S, np.asarray(ctx.finv[a:b], dtype=ctx.dtype))
    X.eliminate_zeros()
    _write(ctx, "X", i, X)
    return {"i": i, "nnz_P": int(MS.nnz), "nnz_X": int(X.nnz), "computed": computed,
            "skipped": skipped}


def ns_residual_row(ctx, i):
    """Newton-Schulz, first product: R[i] = (I - T X)[i] = (D - S + M S)[i], pruned,
    with S = F X (so I - T X = D - (D - M) S on the active pixels)."""
    a, b = ctx.M.row_range(i)
    MS, computed, skipped = _product(ctx, ctx.M, ctx.S, i, ctx.M.tile_columns(i), 0.0)
    R = blocks.identity_rows(a, b, ctx.n, ctx.active, ctx.dtype) - ctx.S.row(i) + MS
    R = prune(sp.csr_array(R), threshold=ctx.threshold)
    _write(ctx, "R", i, R)
    return {"i": i, "nnz_P": int(R.nnz), "nnz_X": 0, "computed": computed,
            "skipped": skipped}


def ns_update_row(ctx, i):
    """Newton-Schulz, second product: S'[i] = S[i] + (S R)[i] (pruned), X' = F^-1 S'.

    Together with :func:`ns_residual_row`: X' = X + X (I - T X) = X (2I - T X).
    """
    a, b = ctx.M.row_range(i)
    SR, computed, skipped = _product(ctx, ctx.S, ctx.R, i, ctx.S.tile_columns(i),
                                     ctx.threshold)
    S = sp.csr_array(ctx.S.row(i) + SR)
    X = scale_rows(S, np.asarray(ctx.finv[a:b], dtype=ctx.dtype))
    X.eliminate_zeros()
    _write(ctx, "X", i, X)
    return {"i": i, "nnz_P": int(SR.nnz), "nnz_X": int(X.nnz), "computed": computed,
            "skipped": skipped}


def diag_row(ctx, i):
    """X_0[i] = F^-1 rows (term 0)."""
    a, b = ctx.M.row_range(i)
    X = blocks.diag_rows(a, b, ctx.n, ctx.finv, ctx.dtype)
    _write(ctx, "X", i, X)
    return {"i": i, "nnz_P": int(X.nnz), "nnz_X": int(X.nnz), "computed": 0, "skipped": 0}
