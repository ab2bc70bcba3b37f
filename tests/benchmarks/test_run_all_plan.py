"""The benchmark plans of ``benchmarks/run_all.py``: every step names a script and options
it has, carries an estimate and where the estimate comes from, and the full plan's
estimates add up to what ``make bench`` promises (about an hour, issue #34). Nothing
here runs a benchmark: the estimates are the plan's arithmetic, not timings."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))

import report  # noqa: E402
import run_all  # noqa: E402

PLANS = {"full": run_all.FULL, "quick": run_all.QUICK, "own runs": run_all.OWN_RUNS}
#: ``make bench``: "within about an hour on this machine". The estimates are the last full
#: run's own times (2026-11-27: 57.7 min of benchmarks, 58 min for the command).
FULL_PLAN_MINUTES = 62
#: ``make bench-quick``: under 5 minutes.
QUICK_PLAN_MINUTES = 5


def _options(script: str) -> set[str]:
    """The ``--options`` the script's argparse declares (read from its source)."""
    text = (BENCH / script).read_text(encoding="utf-8")
    return set(re.findall(r"add_argument\(\s*\"(--[a-z0-9-]+)\"", text))


@pytest.mark.parametrize("plan", PLANS)
def test_every_step_runs_a_script_with_options_it_declares(plan):
    for step in PLANS[plan]:
        assert (BENCH / step.argv[0]).is_file(), step
        given = {a for a in step.argv[1:] if a.startswith("--")}
        assert given <= _options(step.argv[0]), (step.name, given - _options(step.argv[0]))


@pytest.mark.parametrize("plan", PLANS)
def test_every_step_carries_an_estimate_and_its_basis(plan):
    for step in PLANS[plan]:
        assert step.minutes > 0 and step.basis.strip(), step


def test_names_are_unique_across_the_full_plan_and_the_own_runs():
    names = [s.name for s in run_all.FULL + run_all.OWN_RUNS]
    assert len(names) == len(set(names))
    assert len({s.name for s in run_all.QUICK}) == len(run_all.QUICK)


def test_the_plans_fit_what_make_bench_promises():
    assert run_all.estimate(run_all.FULL) <= FULL_PLAN_MINUTES
    assert run_all.estimate(run_all.QUICK) <= QUICK_PLAN_MINUTES
    assert run_all.estimate(run_all.FULL[:2]) == pytest.approx(
        run_all.FULL[0].minutes + run_all.FULL[1].minutes)


def test_list_prints_each_step_with_its_estimate_and_the_totals(capsys):
    assert run_all.main(["--list"]) == 0
    out = capsys.readouterr().out
    for step in run_all.FULL + run_all.OWN_RUNS:
        assert re.search(rf"^{re.escape(step.name)} +~ *{step.minutes:.1f} min ", out, re.M), \
            step.name
    totals = re.findall(r"^total +~ *([0-9.]+) min", out, re.M)
    assert [float(t) for t in totals] == [round(run_all.estimate(run_all.FULL), 1),
                                         round(run_all.estimate(run_all.OWN_RUNS), 1)]


def test_only_picks_steps_of_the_plan_and_the_own_runs_in_order():
    quick = {s.name for s in run_all.QUICK}
    own = next(s.name for s in run_all.OWN_RUNS if s.name not in quick)
    first, last = run_all.FULL[0].name, run_all.FULL[-1].name
    picked = run_all.select(run_all.FULL, f"{own},{last},{first}", run_all.OWN_RUNS)
    assert [s.name for s in picked] == [first, last, own]
    assert run_all.select(run_all.FULL, None, run_all.OWN_RUNS) == run_all.FULL
    with pytest.raises(SystemExit, match="not in this plan: no-such-benchmark"):
        run_all.select(run_all.FULL, "no-such-benchmark", run_all.OWN_RUNS)
    with pytest.raises(SystemExit, match=own):  # the quick plan has no own runs
        run_all.select(run_all.QUICK, own)


def test_a_runs_estimate_is_kept_and_shown_beside_its_time(tmp_path):
    runs = [report.Run("store", ["python", "benchmarks/bench_store.py"], 0, 14.0,
                       "store.txt", 12.0)]
    report.Plan("full", ["store"], runs).save(tmp_path)
    assert report.Plan.load(tmp_path).runs == runs
    (tmp_path / "store.txt").write_text("| n | s |\n")
    text = report.render(tmp_path, tmp_path / "RESULTS.md")
    assert "ran in 14 s (estimated 12 s)" in text
    assert "14 s of benchmarks (estimated 12 s)" in text


def test_runs_json_of_an_older_plan_without_estimates_still_loads(tmp_path):
    (tmp_path / report.RUNS_FILE).write_text(
        '{"kind": "full", "order": ["store"], "runs": [{"name": "store", "command": '
        '["python", "benchmarks/bench_store.py"], "returncode": 0, "seconds": 14.0, '
        '"log": "store.txt"}]}')
    plan = report.Plan.load(tmp_path)
    assert plan.runs[0].estimated_seconds is None
    (tmp_path / "store.txt").write_text("done\n")
    text = report.render(tmp_path, tmp_path / "RESULTS.md")
    assert "ran in 14 s;" in text and "estimated" not in text


def _target_record(name: str, ratios: list[float]) -> None:
    import _results

    res = _results.Results(name, "--target-error against a sweep")
    res.table("target", "target against fixed", ["scene", "E", "ratio"],
              [["corner", 0.001 * (i + 1), r] for i, r in enumerate(ratios)])
    res.save()


def test_the_target_sentence_reads_the_full_plans_96x128_sweep_when_alone(tmp_path,
                                                                          monkeypatch):
    import _results

    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    _target_record("target-96x128", [1.2, 1.5])
    text = report.render(tmp_path, tmp_path / "RESULTS.md")
    assert "reached its target in 1.2–1.5× the time of the best fixed setting" in text
    assert "(2 cases)" in text
    _target_record("target", [1.3])  # the 48x64 sweep, run on its own, is preferred
    text = report.render(tmp_path, tmp_path / "RESULTS.md")
    assert "reached its target in 1.3× the time of the best fixed setting" in text
