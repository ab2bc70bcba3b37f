"""The inverse store: term metadata, refusal of a different T/parameters, resume after
a crash mid-term (same result as an uninterrupted run), early stops."""

import numpy as np
import pytest

import bigT
from bigT.schedule import worker

from inverse_helpers import dense, dense_stratified, random_dominant


class Crash(RuntimeError):
    pass


def test_metadata_and_info(tmp_path, make_store):
    A = random_dominant(40, seed=1)
    T = make_store(A)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=2, prune=1e-6,
                                  progress=False)
    X = bigT.open(tmp_path / "X.zarr")
    inv = X.metadata["inverse"]
    assert inv["term"] == 2 and inv["method"] == "power" and inv["prune"] == 1e-6
    assert inv["first_bounce"] == "diag"
    assert inv["residual"] == pytest.approx(rep.residual)
    assert inv["spectral_radius"] == pytest.approx(rep.spectral_radius)
    rho = max(abs(np.linalg.eigvals(np.eye(40) - A / np.diag(A)[None, :])))
    assert rep.spectral_radius == pytest.approx(rho, rel=0.05)
    d = rep.to_dict()
    assert len(d["history"]) == 3 and "term" in rep.table()


def test_refuses_other_parameters_and_resumes_same(tmp_path, make_store):
    A = random_dominant(40, seed=2)
    T = make_store(A)
    out = tmp_path / "X.zarr"
    bigT.stratified_inverse(T, out, terms=2, prune=0, progress=False)
    with pytest.raises(bigT.StoreError, match="prune"):
        bigT.stratified_inverse(T, out, terms=3, prune=1e-3, progress=False)
    with pytest.raises(bigT.StoreError, match="method"):
        bigT.stratified_inverse(T, out, terms=3, prune=0, method="horner", progress=False)
    T2 = make_store(random_dominant(40, seed=9), name="T2.zarr")
    with pytest.raises(bigT.StoreError, match="T"):
        bigT.stratified_inverse(T2, out, terms=3, prune=0, progress=False)
    rep = bigT.stratified_inverse(T, out, terms=4, prune=0, progress=False)
    assert rep.resumed_from == 2 and rep.terms == 4
    assert [h.term for h in rep.history] == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(dense(out), dense_stratified(A, 4), atol=1e-12)
    rep = bigT.stratified_inverse(T, out, terms=3, prune=0, progress=False)
    assert rep.terms == 4 and rep.stopped.startswith("already held")
    (tmp_path / "empty").mkdir()  # an empty directory holds nobody's work: it is used
    assert bigT.stratified_inverse(T, tmp_path / "empty", terms=1, progress=False).terms == 1
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("mine")
    with pytest.raises(bigT.StoreError, match="not a bigT inverse"):
        bigT.stratified_inverse(T, tmp_path / "junk", terms=1, progress=False)
    assert (tmp_path / "junk" / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("method", ["power", "newton-schulz"])
def test_crash_mid_term_then_resume(tmp_path, make_store, monkeypatch, method):
    A = random_dominant(96, seed=4, density=0.2)
    T = make_store(A, tile_size=16)  # 6 tile rows
    ref = tmp_path / "ref.zarr"
    bigT.stratified_inverse(T, ref, terms=3, prune=1e-6, method=method, progress=False)

    out = tmp_path / "X.zarr"
    calls = {"n": 0}
    crash_op = "power" if method == "power" else "ns-update"

    def hook(op, i):
        if op == crash_op:
            calls["n"] += 1
            # term 1 of power (6 rows) passes; crash on the 4th row of term 2
            if calls["n"] == (6 + 4 if method == "power" else 6 + 4):
                raise Crash("injected")

    monkeypatch.setattr(worker, "task_hook", hook)
    with pytest.raises(Crash):
        bigT.stratified_inverse(T, out, terms=3, prune=1e-6, method=method, progress=False)
    monkeypatch.setattr(worker, "task_hook", None)
    # the previous term is still readable and says which term it is
    X_prev = bigT.open(out)
    assert X_prev.metadata["inverse"]["term"] == 1
    np.testing.assert_allclose(X_prev.to_scipy().toarray(), dense_stratified(A, 1),
                               atol=1e-5)

    done = []
    monkeypatch.setattr(worker, "task_hook", lambda op, i: done.append((op, i)))
    rep = bigT.stratified_inverse(T, out, terms=3, prune=1e-6, method=method, progress=False)
    monkeypatch.setattr(worker, "task_hook", None)
    assert rep.resumed_from == 1 and rep.terms == 3
    # rows completed before the crash were not recomputed
    assert len([d for d in done if d[0] == crash_op]) < 12
    np.testing.assert_array_equal(dense(out), dense(ref))


def test_tol_stops_early(tmp_path, make_store):
    A = random_dominant(60, seed=5, margin=0.3)
    T = make_store(A)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=20, prune=0, tol=1e-3,
                                  progress=False)
    assert rep.terms < 20 and rep.stopped.startswith("tol")
    assert rep.residual <= 1e-3
    assert all(h.residual > 1e-3 for h in rep.history[:-1])


def test_flat_scene_finishes_with_zero_products(tmp_path, make_store):
    d = 0.5 + np.linspace(0, 1, 50)
    T = make_store(np.diag(d), tile_size=16)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=6, progress=False)
    assert rep.products == 0 and rep.terms == 6
    assert rep.spectral_radius == 0
    assert "exhausted" in rep.stopped
    np.testing.assert_array_equal(dense(tmp_path / "X.zarr"), np.diag(1 / d))
    assert rep.residual == pytest.approx(0, abs=1e-12)


def test_converged_block_rows_are_skipped(tmp_path, make_store):
    # two decoupled blocks: pixels 0..31 interreflect, 32..63 do not (M = 0 there), so
    # P's tile rows 2, 3 are empty from term 1 on and never scheduled as factors
    A = random_dominant(64, seed=6, density=0.4)
    A[32:, :] = 0
    A[:, 32:] = 0
    A[32:, 32:] = np.diag(1 + np.arange(32) / 32)
    T = make_store(A, tile_size=16)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0, progress=False)
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), dense_stratified(A, 3), atol=1e-12)
    for h in rep.history[2:]:
        assert h.tiles_computed == 4  # only the 2x2 tiles of the coupled block
        # M's rows 2, 3 are zero (F = diag T): no tile pair there, none to skip
        assert h.tiles_skipped == 0
        assert h.rows_skipped == 2    # rows 2, 3: no product at all


#: The keys of the root record and of its history entries as bigT wrote them before the
#: record was split into storage's generic part and the engine's details (the split:
#: e227470; 60b422a wrote this layout).
OLD_RECORD_KEYS = ("params", "term", "dir", "history", "spectral_radius", "exhausted_at",
                   "tile_size", "excluded_pixels", "residual", "spectral_uncertainty",
                   "spectral_products")
OLD_TERM_KEYS = ("term", "seconds", "nnz_P", "nnz_X", "tiles_computed", "tiles_skipped",
                 "rows_skipped", "residual", "residual_abs", "multiply_adds",
                 "kernel_seconds", "residual_seconds")


def test_a_store_in_the_older_record_layout_opens_and_resumes(tmp_path, make_store):
    """A root record holding exactly the older layout's keys (no ``spectral_method``)
    resumes: the terms held read back as they were written, are marked as an earlier
    run's in the table, and the series goes on to the same inverse as one run."""
    import json

    A = random_dominant(48, seed=17)
    T = make_store(A)
    out = tmp_path / "X.zarr"
    bigT.stratified_inverse(T, out, terms=1, prune=0.0, progress=False)
    root = out / "zarr.json"
    j = json.loads(root.read_text())
    new = j["attributes"]["bigT_inverse"]
    assert set(OLD_RECORD_KEYS) <= set(new) and set(new) - set(OLD_RECORD_KEYS) == {
        "spectral_method"}
    # a term's record now also holds its task costs (issue #32), absent from the older
    assert all(set(h) == set(OLD_TERM_KEYS) | {"tasks"} for h in new["history"])
    old = {k: new[k] for k in OLD_RECORD_KEYS}
    old["history"] = [{**{k: h[k] for k in OLD_TERM_KEYS}, "seconds": 10.0 + h["term"]}
                      for h in new["history"]]
    j["attributes"]["bigT_inverse"] = old
    root.write_text(json.dumps(j))

    rep = bigT.stratified_inverse(T, out, terms=3, prune=0.0, progress=False)
    assert rep.resumed_from == 1 and rep.terms == 3
    assert [h.seconds for h in rep.history[:2]] == [10.0, 11.0]
    assert rep.history[1].residual == old["residual"]
    np.testing.assert_allclose(dense(out), dense_stratified(A, 3), atol=1e-12)
    rows = rep.table().splitlines()
    assert rows[2].startswith("   0*") and rows[3].startswith("   1*")
    assert rows[4].startswith("   2 ") and "earlier run" in rows[6]
    assert "earlier run's terms 0-1 took 21.00 s" in rows[7]
    assert "read from the store" in rows[7] and "terms 2-3" in rows[7]
