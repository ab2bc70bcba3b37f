"""benchmarks/report.py turns the records benchmarks write (``_results.Results``) into
RESULTS.md: their tables, figure links, the paper's claims, the machine stamp, a failed
run's log, and "not measured in this run" for what did not run."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))

import _results  # noqa: E402
import report  # noqa: E402


def _png(path: Path) -> None:
    from PIL import Image

    Image.new("RGB", (320, 200), "white").save(path)


@pytest.fixture
def out(tmp_path, monkeypatch):
    """Two fake records, a stamp and a plan in which a third benchmark failed."""
    folder = tmp_path / "results"
    monkeypatch.setenv(_results.OUT_ENV, str(folder))
    alt = _results.Results("alternatives", "What users would pick instead")
    alt.table("alternatives", "compensating at 96x128",
              ["size", "n", "method", "setup s", "frame s (batch 1)", "frame s (batch 64)",
               "peak MiB", "error"],
              [["96x128", 12288, "scipy splu", 0.7, 0.009, 0.009, 300.0, 1.2e-12],
               ["96x128", 12288, "bigT explicit inverse", 3.2, 0.15, 0.0015, 500.0, 4e-5],
               ["96x128", 12288, "numpy inv", "did not fit", None, None, None, None]])
    _png(alt.figure_path("alt.png"))
    alt.figure("alt.png", "frame time against size")
    alt.save()
    paper = _results.Results("paper", "The paper's figures")
    paper.table("fig6", "Fig. 6: time per term", ["terms", "s"], [[7, 0.25]])
    paper.claim("Fig. 6", "T_7^-1 more than 8x faster than the true inverse", "11.2x faster",
                True)
    paper.claim("Fig. 6", "no convergence with F = I", "converged", False)
    paper.save()
    stamp = _results.machine()
    stamp.save(folder)
    (folder / "scale.txt").write_text("building\nTraceback (most recent call last)\n"
                                      "MemoryError: the last line\n")
    runs = [report.Run("paper", ["python", "benchmarks/bench_paper.py"], 0, 12.0,
                       "paper.txt"),
            report.Run("alternatives", ["python", "benchmarks/bench_alternatives.py"], 0,
                       30.0, "alternatives.txt"),
            report.Run("scale", ["python", "benchmarks/bench_scale.py"], 1, 4.0,
                       "scale.txt")]
    report.Plan("quick", ["paper", "tradeoff", "alternatives", "scale"], runs).save(folder)
    return folder


def test_tables_figures_claims_and_stamp(out, tmp_path):
    md = report.write(out, tmp_path / "RESULTS.md").read_text()
    stamp = _results.Machine.load(out)
    assert md.startswith("# ")
    assert stamp.line() in md and "numpy" in md and stamp.cpu_model in md
    assert "| size | n | method | setup s |" in md
    assert "| 96x128 | 12,288 | scipy splu | 0.7 | 0.009 |" in md
    assert "4.00e-5" in md and "1.20e-12" in md  # small errors in scientific notation
    assert "![frame time against size](results/alt.png)" in md  # relative to RESULTS.md
    assert ("| Fig. 6 | T_7^-1 more than 8x faster than the true inverse | 11.2x faster | – "
            "| yes |") in md
    assert ("1 of the 2 claims of the paper checked hold on bigT's scenes (2 checks in all); "
            'the one that does not: Fig. 6 "no convergence with F = I"') in md
    # the summary quotes the numbers it decides on: splu for one frame, bigT for many
    assert "for 1 frame the quickest is scipy splu (0.7 s setup" in md
    assert "for 1,000 frames the quickest is bigT explicit inverse" in md
    assert "bigT explicit inverse overtakes scipy splu after about" in md
    # sections in the plan's order, the failed one with the end of its log
    assert md.index("(`paper`)") < md.index("(`alternatives`)") < md.index("(`scale`)")
    assert "**failed** (exit 1" in md and "MemoryError: the last line" in md


def test_missing_records_are_not_measured(out, tmp_path):
    md = report.write(out, tmp_path / "RESULTS.md").read_text()
    summary = md[md.index("## Summary"):md.index("## The paper's claims")]
    assert "Time against error (the prune threshold and method trade): not measured in this run" \
        in summary
    assert "Scaling of the 4-term inverse with n: not measured in this run" in summary
    tradeoff = md[md.index("(`tradeoff`)"):md.index("(`alternatives`)")]
    assert "Not measured in this run" in tradeoff


def test_figures_are_stamped_once(out, tmp_path):
    from PIL import Image

    report.write(out, tmp_path / "RESULTS.md")
    with Image.open(out / "alt.png") as im:
        height, text = im.height, dict(im.text)
    assert height > 200 and text[report.STAMP_KEY] == _results.Machine.load(out).line()
    report.write(out, tmp_path / "RESULTS.md")
    with Image.open(out / "alt.png") as im:
        assert im.height == height


@pytest.mark.parametrize("x, text", [(None, "–"), (True, "yes"), (12288, "12,288"), (1000, "1,000"), (7, "7"),
                                     (0.0, "0"), (3.14159, "3.14"), (0.00421, "0.00421"),
                                     (5.3e-5, "5.30e-5"), (1234.5, "1,234"),
                                     (2.3e10, "2.30e10"), (float("nan"), "–"),
                                     ("power", "power")])
def test_numbers_are_formatted(x, text):
    assert report.fmt(x) == text


# --- sentences consistent with their tables --------------------------------------------------

def _claims_rows(md: str) -> list[list[str]]:
    """The claims table of RESULTS.md as cells (figure, paper, measured, test, verdict)."""
    part = md[md.index("## The paper's claims"):md.index("## 1.")]
    rows = [line.strip("|").split(" | ") for line in part.splitlines()
            if line.startswith("| ") and not line.startswith("| figure")]
    return [[c.strip() for c in r] for r in rows]


@pytest.fixture
def paper_out(tmp_path, monkeypatch):
    """A paper record whose claims are checked several ways, one judged by a test the
    benchmark wrote as "(holds: ...)", one not judged; a stamp; no plan."""
    folder = tmp_path / "results"
    monkeypatch.setenv(_results.OUT_ENV, str(folder))
    paper = _results.Results("paper", "The paper's figures")
    speed = "the computational time for T_7^-1 is more than 8 times faster"
    paper.claim("Fig. 6(a)", speed, "engine, prune 1e-05: 2.1x", False)
    paper.claim("Fig. 6(a)", speed, "engine, prune 1e-07: 1.9x", False)
    paper.claim("Fig. 6(a)", speed, "plain scipy: 8.4x", True)
    paper.claim("Fig. 5", "the two curves are very close",
                "gap 6 % (holds: < 10 %); rho(M) 0.16 (diag T)", True)
    paper.claim("Fig. 6(a)", "convergence does not happen for F = I",
                "rho(I - T) = 0.930: the error falls (holds: rho >= 1)", False)
    paper.claim("Fig. 8", "a real camera's noise", "not simulated", None)
    paper.save()
    _results.machine().save(folder)
    return folder


def test_claims_count_and_list_agree_with_the_table(paper_out, tmp_path):
    import re

    md = report.write(paper_out, tmp_path / "RESULTS.md").read_text()
    rows = _claims_rows(md)
    assert len(rows) == 6 and all(len(r) == 5 for r in rows)
    # the table, read independently: a claim holds when every judged check of it does
    verdicts: dict[tuple[str, str], list[str]] = {}
    for figure, paper, _, _, verdict in rows:
        if verdict != "–":
            verdicts.setdefault((figure, paper), []).append(verdict)
    failing = {k for k, v in verdicts.items() if "no" in v}
    held = len(verdicts) - len(failing)
    sentence = next(line for line in md.splitlines() if "claims of the paper checked" in line)
    m = re.search(r"(\d+) of the (\d+) claims of the paper checked hold .*\((\d+) checks", sentence)
    assert (int(m[1]), int(m[2]), int(m[3])) == (held, len(verdicts), 5)
    assert f"the {len(failing)} that do not:" in sentence
    named = re.findall(r'(Fig\. [^ ]+) "([^"]+)"', sentence)
    assert set(named) == failing and len(named) == len(failing)
    assert "(2 of its 3 checks fail)" in sentence  # the speed claim: 2 checks of 3 fail


def test_claims_table_puts_the_test_in_its_own_column(paper_out, tmp_path):
    md = report.write(paper_out, tmp_path / "RESULTS.md").read_text()
    rows = {r[2]: r for r in _claims_rows(md)}
    assert rows["rho(I - T) = 0.930: the error falls"][3:] == ["rho >= 1", "no"]
    assert rows["gap 6 %; rho(M) 0.16 (diag T)"][3:] == ["< 10 %", "yes"]  # a test mid-text
    assert rows["not simulated"][3:] == ["–", "–"]
    assert "(holds:" not in md


def _tradeoff_record(folder: Path) -> None:
    """Per-term points (part A) where power's 3rd term beats every sweep run to 1e-4,
    and a sweep (part B) whose fastest run to 1e-4 is slower: the summary must give one
    answer per target, the fastest of both."""
    res = _results.Results("tradeoff", "Run time against error")
    res.table("terms:corner-96x128-sparse", "Time against error per term: corner-96x128-sparse",
              ["method", "term", "term s", "cumulative s", "wall s", "error", "residual",
               "nnz(X)"],
              [["power", 0, 0.1, 0.1, 0.2, 0.02, 0.01, 1000],
               ["power", 1, 0.2, 0.3, 0.4, 0.003, 0.002, 2000],
               ["power", 2, 0.3, 0.6, 0.7, 0.0006, 0.0004, 3000],
               ["power", 3, 0.3, 0.9, 1.0, 9e-5, 8e-5, 4000],
               ["horner", 3, 0.4, 1.2, 1.3, 8e-5, 7e-5, 4000]],
              note="n = 12288, T 25 nonzeros/row, prune 1e-05. cumulative s: ...")
    res.table("pareto", "Pareto front of time against error: corner-96x128-sparse",
              ["method", "prune", "feed", "seconds", "nnz(X)", "error", "on front"],
              [["power", 0.001, "-", 0.7, 900, 0.0033, "yes"],
               ["power", 0.0001, "-", 0.95, 2000, 0.0002, "yes"],
               ["horner", 0.0001, "-", 1.05, 2100, 2.6e-5, "yes"],
               ["power", 1e-05, 0.0001, 1.1, 4000, 9.9e-5, "no"]],
              note="corner-96x128-sparse, 4 terms each from scratch; seconds: ...")
    res.table("terms:cornell-64x80-sparse", "Time against error per term: cornell-64x80-sparse",
              ["method", "term", "term s", "cumulative s", "wall s", "error", "residual",
               "nnz(X)"],
              [["power", 0, 0.1, 0.1, 0.2, 0.05, 0.04, 1000],
               ["power", 4, 0.5, 2.4, 2.5, 0.00086, 0.0001, 9000]],
              note="n = 5120, T 80 nonzeros/row, prune 1e-05. cumulative s: ...")
    res.save()


def test_tradeoff_summary_gives_one_answer_per_target(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    _tradeoff_record(tmp_path)
    rec = report.load_records(tmp_path)["tradeoff"]
    lines = report.summary_tradeoff(rec)
    corner, cornell = lines
    # one sentence per scene, each target answered once
    assert corner.count("error ≤ 1.00e-4") == 1 and corner.count("error ≤ 0.001") == 1
    # the answer is the fastest row of either table reaching the target, read here
    # independently from the tables' cells
    rows = [(r[3], r[5]) for r in rec.table("terms:corner-96x128-sparse").rows]
    rows += [(r[3], r[5]) for r in rec.table("pareto").rows]
    for target in report.TRADEOFF_TARGETS:
        seconds = min(s for s, e in rows if e <= target)
        assert f"error ≤ {report.fmt(target)} takes {report.fmt(seconds)} s" in corner
    assert "takes 0.9 s (power, 3 terms, prune 1e-05: error 9.00e-5)" in corner
    assert "of the 9 settings measured" in corner
    # a scene that never reaches a target says so once, with its lowest error
    assert "error ≤ 0.01 takes 2.4 s" in cornell and "error ≤ 0.001 takes 2.4 s" in cornell
    assert "none of its 2 settings reaches error ≤ 1.00e-4 (lowest: 8.60e-4" in cornell
    assert cornell.count("error ≤ 1.00e-4") == 1


# --- which code a run measured ------------------------------------------------------------------

def test_code_state_is_stamped_and_a_changed_record_is_named(out, tmp_path):
    stamp = _results.Machine.load(out)
    dirty = _results.CodeState("abc1234", False, ["bigT/x.py"], 1)
    _results.Machine(**{**stamp.__dict__, "code": dirty}).save(out)
    md = report.write(out, tmp_path / "RESULTS.md").read_text()
    assert ("**Not from a committed state:** the run started at commit abc1234 with "
            "uncommitted changes to 1 file (bigT/x.py)") in md
    # the fixture's records were saved by this checkout, not at abc1234: each says so
    paper = md[md.index("(`paper`)"):md.index("(`tradeoff`)")]
    assert "**Measured with commit " in paper and "(the run started at commit abc1234" in paper


def test_a_clean_run_says_all_records_share_its_commit(out, tmp_path):
    code = _results.code_state()
    stamp = _results.Machine.load(out)
    _results.Machine(**{**stamp.__dict__, "code": code}).save(out)
    md = report.write(out, tmp_path / "RESULTS.md").read_text()
    assert f"**Code:** all 2 records were measured with {code.words()}." in md
    assert "**Measured with" not in md


def test_an_old_stamp_string_still_reads():
    old = _results.CodeState.from_dict("6fde496+dirty")
    assert old == _results.CodeState("6fde496", False)
    assert old.words() == "commit 6fde496 with uncommitted changes: not any commit's code"
    assert _results.CodeState.from_dict("6fde496").words() == "commit 6fde496, clean tree"


def test_the_committed_results_need_a_clean_tree(monkeypatch):
    import run_all

    dirty = _results.CodeState("abc1234", False, ["bigT/x.py"], 1)
    monkeypatch.setattr(run_all, "code_state", lambda root: dirty)
    committed = run_all.HERE / "RESULTS.md"
    assert "must come from a commit" in run_all.refuse_dirty(committed, allow_dirty=False)
    assert run_all.refuse_dirty(committed, allow_dirty=True) is None
    assert run_all.refuse_dirty(run_all.ROOT / "bench-out" / "RESULTS.md", False) is None
    clean = _results.CodeState("abc1234", True)
    monkeypatch.setattr(run_all, "code_state", lambda root: clean)
    assert run_all.refuse_dirty(committed, allow_dirty=False) is None
