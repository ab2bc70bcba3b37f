"""The power form with a separate threshold for the factor it feeds on (``prune_feed``)
against its recurrence evaluated densely, and the per-term multiply-add counts against
a count made from the dense factors."""

from pathlib import Path

import numpy as np
import pytest

import bigT
from bigT.errors import BigTError, StoreError
from bigT.algorithms import TermRecord

from inverse_helpers import dense, dense_stratified, random_dominant


def _pruned(A, t):
    return np.where(np.abs(A) >= t, A, 0.0)


def dense_carried_power(T, n, prune, feed, operator=0.0):
    """Q_k = prune(M_o P_{k-1}, prune), X_k = X_{k-1} + F^-1 Q_k, P_k = prune(Q_k, feed),
    with P_0 = I, Q_1 = prune(M, prune) and M_o = prune(M, operator): the carried power
    form, densely.

    Returns (X, [M-row nnz x P row lengths per term]): the multiply-adds of the
    product M P_{k-1} are sum over M's entries (i, j) of nnz(P_{k-1}[j, :]).
    """
    f = np.diag(T)
    M = np.eye(len(T)) - T / f[None, :]
    np.fill_diagonal(M, 0.0)
    X = np.diag(1 / f)
    P = np.eye(len(T))
    M_o = _pruned(M, operator)
    madds = [0]
    for k in range(1, n + 1):
        if k == 1:
            Q, work = _pruned(M, prune), 0
        else:
            Q = _pruned(M_o @ P, prune)
            work = int(((M_o != 0) * np.count_nonzero(P, axis=1)[None, :]).sum())
        X = X + Q / f[:, None]
        P = _pruned(Q, feed)
        madds.append(work)
    return X, madds


@pytest.mark.parametrize("prune,feed", [(1e-4, 1e-4), (1e-5, 1e-3), (0.0, 3e-3)])
def test_carried_power_matches_dense_recurrence(tmp_path, make_store, prune, feed):
    A = random_dominant(80, seed=21, density=0.3, margin=0.8)
    T = make_store(A, tile_size=16)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=4, prune=prune,
                                  prune_feed=feed, progress=False)
    want, madds = dense_carried_power(A, 4, prune, feed)
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), want, rtol=1e-10, atol=1e-13)
    # a P_k pruned to nothing ends the series: the terms after it add nothing
    held = len(rep.history)
    assert [h.multiply_adds for h in rep.history] == madds[:held]
    assert not any(madds[held:])
    assert rep.prune_feed == (None if feed == prune else feed)


@pytest.mark.parametrize("prune,feed,operator", [(1e-5, 1e-5, 1e-3), (1e-6, 1e-3, 3e-3),
                                                 (0.0, 0.0, 2e-2)])
def test_operator_pruned_power_matches_dense_recurrence(tmp_path, make_store, prune, feed,
                                                        operator):
    A = random_dominant(80, seed=23, density=0.3, margin=0.8)
    T = make_store(A, tile_size=16)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=4, prune=prune,
                                  prune_feed=feed, prune_operator=operator,
                                  progress=False)
    want, madds = dense_carried_power(A, 4, prune, feed, operator)
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), want, rtol=1e-10, atol=1e-13)
    assert [h.multiply_adds for h in rep.history] == madds[:len(rep.history)]
    assert rep.prune_operator == operator
    assert f"M pruned at {operator:g} in the products" in rep.table()
    # term 1 is M down to prune: the operator threshold leaves it alone
    want_1, _ = dense_carried_power(A, 1, prune, feed)
    bigT.stratified_inverse(T, tmp_path / "X1.zarr", terms=1, prune=prune,
                            prune_feed=feed, prune_operator=operator, progress=False)
    np.testing.assert_allclose(dense(tmp_path / "X1.zarr"), want_1, rtol=1e-10, atol=1e-13)


def test_pruning_the_operator_costs_a_bounce_down(tmp_path, make_store):
    """What the left factor drops, D_o P_{k-1}, is one bounce below D_o: against the
    exact inverse, the error grows far less than pruning X at the same threshold
    would cost, while the multiply-adds fall. M's entries span five decades, as a
    transport's do, and the threshold is their median."""
    rng = np.random.default_rng(8)
    n = 120
    C = (rng.random((n, n)) < 0.5) * 10 ** rng.uniform(-6, -1, (n, n))
    np.fill_diagonal(C, 0.0)
    d = C.sum(axis=0) / 0.4  # M = -C / d: column sums 0.4
    A = C + np.diag(d)
    t = float(np.median((C / d[None, :])[C > 0]))
    T = make_store(A, tile_size=32)
    exact = np.linalg.inv(A)
    err = {}
    work = {}
    for name, kw in {"plain": {}, "operator": {"prune_operator": t},
                     "x pruned": {"prune": t}}.items():
        out = tmp_path / f"{name}.zarr"
        rep = bigT.stratified_inverse(T, out, terms=4, progress=False,
                                      **{"prune": 0.0, **kw})
        err[name] = np.linalg.norm(dense(out) - exact) / np.linalg.norm(exact)
        work[name] = sum(h.multiply_adds for h in rep.history)
    assert work["operator"] < 0.8 * work["plain"]
    assert err["operator"] - err["plain"] < 0.5 * (err["x pruned"] - err["plain"])


def test_feeding_on_less_does_less_work_for_the_same_x_threshold(tmp_path, make_store):
    A = random_dominant(96, seed=5, density=0.3, margin=0.8)
    T = make_store(A, tile_size=32)
    plain = bigT.stratified_inverse(T, tmp_path / "a.zarr", terms=3, prune=1e-5,
                                    progress=False)
    carried = bigT.stratified_inverse(T, tmp_path / "b.zarr", terms=3, prune=1e-5,
                                      prune_feed=1e-3, progress=False)
    work = [sum(h.multiply_adds for h in r.history) for r in (plain, carried)]
    assert 0 < work[1] < work[0]


def test_feed_threshold_checked(tmp_path, make_store):
    T = make_store(random_dominant(32, seed=1), tile_size=16)
    with pytest.raises(BigTError, match="prune_feed must be >= prune"):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", prune=1e-3, prune_feed=1e-4,
                                progress=False)
    with pytest.raises(BigTError, match="horner method has none"):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", method="horner", prune_feed=1e-3,
                                progress=False)
    with pytest.raises(BigTError, match="prune_operator must be >= prune"):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", prune=1e-3, prune_operator=1e-4,
                                progress=False)
    with pytest.raises(BigTError, match="products M P_{k-1}; the newton-schulz method"):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", method="newton-schulz",
                                prune_operator=1e-3, progress=False)


def test_another_feed_threshold_is_not_resumed(tmp_path, make_store):
    T = make_store(random_dominant(32, seed=2), tile_size=16)
    plain, fed = tmp_path / "plain.zarr", tmp_path / "fed.zarr"
    bigT.stratified_inverse(T, plain, terms=1, prune=1e-5, progress=False)
    with pytest.raises(StoreError, match="different prune_feed"):
        bigT.stratified_inverse(T, plain, terms=2, prune=1e-5, prune_feed=1e-3,
                                progress=False)
    # a feed equal to prune is the plain power form: it resumes the plain store
    rep = bigT.stratified_inverse(T, plain, terms=2, prune=1e-5, prune_feed=1e-5,
                                  progress=False)
    assert rep.terms == 2 and rep.prune_feed is None
    bigT.stratified_inverse(T, fed, terms=1, prune=1e-5, prune_feed=1e-3, progress=False)
    with pytest.raises(StoreError, match="different prune_feed .*prune_feed=0.001"):
        bigT.stratified_inverse(T, fed, terms=2, prune=1e-5, progress=False)
    with pytest.raises(StoreError, match="different prune_operator"):
        bigT.stratified_inverse(T, fed, terms=2, prune=1e-5, prune_feed=1e-3,
                                prune_operator=1e-3, progress=False)


def test_counts_of_each_term_and_the_table(tmp_path, make_store):
    A = random_dominant(64, seed=3, density=0.4)
    T = make_store(A, tile_size=16)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0.0,
                                  progress=False)
    _, madds = dense_carried_power(A, 3, 0.0, 0.0)
    assert [h.multiply_adds for h in rep.history] == madds
    assert all(h.kernel_seconds > 0 for h in rep.history[2:])
    assert all(0 < h.residual_seconds < h.seconds for h in rep.history)
    lines = rep.table().splitlines()
    assert "mult-adds" in lines[0] and "kernel/core" in lines[0]
    assert f"{madds[2]:.3g}" in lines[4]  # term 2's row


def test_a_record_from_before_the_counts_reads_zero():
    old = {"term": 2, "seconds": 1.5, "nnz_P": 10, "nnz_X": 20, "tiles_computed": 1,
           "tiles_skipped": 0, "rows_skipped": 0, "residual": 1e-3, "residual_abs": 0.1}
    rec = TermRecord.from_dict(old)
    assert (rec.multiply_adds, rec.kernel_seconds, rec.residual_seconds) == (0, 0.0, 0.0)
    assert TermRecord.from_dict(rec.to_dict()) == rec
    with pytest.raises(TypeError):
        TermRecord.from_dict({**old, "multiply_adds": 1.5})


def test_residual_from_the_probes_carried_term_to_term_equals_reading_x(
        tmp_path, make_store, monkeypatch):
    """The power form's tasks report (X_k - X_{k-1}) Z, so the engine estimates the
    residual without reading X back: the same estimate as from X read (to float32
    rounding of the stored X)."""
    from bigT.algorithms.matvecs import MatVecs
    from bigT.algorithms.probes import ProbedResidual

    A = random_dominant(96, seed=9, density=0.3, margin=0.8)
    T = make_store(A, tile_size=32, dtype="float32")
    read = []
    monkeypatch.setattr(MatVecs, "apply_X",
                        lambda self, X, V: read.append(X.path) or X.to_scipy() @ V)
    carried = bigT.stratified_inverse(T, tmp_path / "a.zarr", terms=4, prune=1e-6,
                                      prune_feed=1e-4, progress=False)
    assert read == []  # no term read X back
    monkeypatch.setattr(ProbedResidual, "updated_XZ", lambda self, XZ, stats: None)
    reread = bigT.stratified_inverse(T, tmp_path / "b.zarr", terms=4, prune=1e-6,
                                     prune_feed=1e-4, progress=False)
    assert len(read) == 4  # terms 1-4 read X; term 0's X Z = F^-1 Z is known
    got = [h.residual for h in carried.history]
    want = [h.residual for h in reread.history]
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert got[-1] < got[0]


@pytest.mark.parametrize("negative", [False, True])
def test_the_bracket_is_asked_for_only_when_m_has_no_positive_entry(
        tmp_path, make_store, monkeypatch, negative):
    """The engine tells the spectral radius M = -|M| only after reading every row of M
    (MOperand.largest_entries, exact whether M's rows are cached or not:
    tests/schedule/test_operators.py); a T with one negative entry (noise) goes to
    ARPACK."""
    from bigT.algorithms import divergence
    from bigT.spectral import spectral_radius

    A = random_dominant(300, seed=4, density=0.05)
    if negative:
        A[10, 200] = -1e-4
    T = make_store(A, tile_size=64, dtype="float32")
    told = []

    def spy(*args, **kw):
        told.append(kw["nonpositive"])
        return spectral_radius(*args, **kw)

    monkeypatch.setattr(divergence, "spectral_radius", spy)
    monkeypatch.setattr(divergence.config, "SPECTRAL_RADIUS_DENSE_MAX", 16)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=1, progress=False)
    assert told == [not negative]
    d = np.diag(A)
    exact = max(abs(np.linalg.eigvals(np.eye(300) - A / d[None, :])))
    assert abs(rep.spectral_radius - exact) <= rep.spectral_uncertainty + 1e-6


def test_power_terms_carry_untouched_tile_rows_of_x_by_link(tmp_path, make_store, monkeypatch):
    """The power form rewrites only the tile rows of X that Q_k touches and hard-links
    the rest whole: with light going only among pixel set A, the rows of set B of M
    are zero, so every Q_k (k >= 1) leaves B's tile rows untouched and each term
    carries them; A's rows are rewritten. The inverse still equals eq. 13 evaluated
    densely."""
    from bigT.storage import writer

    rng = np.random.default_rng(3)
    n, half = 64, 32
    C = np.zeros((n, n))
    C[:half, :half] = rng.uniform(0, 0.6 / half, (half, half))
    T = np.diag(rng.uniform(1.5, 2.5, n)) + C
    linked = []
    real_link_row = writer._link_row
    monkeypatch.setattr(writer, "_link_row",
                        lambda src, dst: (linked.append(src), real_link_row(src, dst)))
    out = tmp_path / "X.zarr"
    bigT.stratified_inverse(make_store(T, tile_size=16), out, terms=3, prune=0.0,
                            progress=False)
    np.testing.assert_allclose(dense(out), dense_stratified(T, 3), rtol=1e-12, atol=1e-15)
    carried = [(Path(p).parent.name, Path(p).name) for p in linked]
    # B is tile rows 2 and 3: carried into X by terms 1 and 2; A's tile rows 0, 1 never
    assert carried.count(("rows", "2")) >= 2 and carried.count(("rows", "3")) >= 2
    assert not {("rows", "0"), ("rows", "1")} & set(carried)


def test_on_term_sees_each_published_term_and_may_stop_the_run(tmp_path, make_store):
    """``on_term`` is called with the record once each computed term is published (the
    store then holds it); a reason returned stops the run there, and the same store
    resumes from it."""
    A = random_dominant(48, seed=17)
    T = make_store(A, tile_size=16)
    out = tmp_path / "X.zarr"
    seen = []

    def on_term(record):
        seen.append((record.term, bigT.open(out).metadata["inverse"]["term"]))
        return "enough" if record.term == 2 else None

    rep = bigT.stratified_inverse(T, out, terms=5, prune=0.0, on_term=on_term,
                                  progress=False)
    assert seen == [(1, 1), (2, 2)] and rep.terms == 2 and rep.stopped == "enough"
    np.testing.assert_allclose(dense(out), dense_stratified(A, 2), atol=1e-12)
    rep = bigT.stratified_inverse(T, out, terms=3, prune=0.0, progress=False)
    assert rep.terms == 3 and rep.resumed_from == 2
    np.testing.assert_allclose(dense(out), dense_stratified(A, 3), atol=1e-12)
