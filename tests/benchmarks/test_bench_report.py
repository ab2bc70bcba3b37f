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


def test_a_part_run_after_a_full_one_names_each_commit_once():
    start = _results.CodeState("bbbbbbb", True)
    full = _results.CodeState("aaaaaaa", True)

    def rec(name, code):
        return report.Record(name, "", "", [], [], {}, [], [], None, None, code)

    records = {n: rec(n, full) for n in ("paper", "tradeoff", "video")}
    records.update({n: rec(n, start) for n in ("scale", "cluster-model")})
    line, _ = report.code_lines(start, records)
    assert line == ("**Code:** `scale`, `cluster-model` measured with commit bbbbbbb, clean "
                    "tree (this run); `paper`, `tradeoff`, `video` with commit aaaaaaa, clean "
                    "tree.")


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


# --- errors beside their targets ----------------------------------------------------------------

@pytest.mark.parametrize("value, target, text", [
    (4.98e-4, 5e-4, "4.98e-4"), (5.02e-4, 5e-4, "5.02e-4"), (5e-4, 5e-4, "5.00e-4"),
    (4.9996e-4, 5e-4, "4.9996e-4"), (1.0004e-4, 1e-4, "1.0004e-4"), (1.4996, 1.5, "1.4996"),
    (0.00226, 0.00392, "0.00226"), (0.0039199, 0.00392, "0.0039199")])
def test_an_error_never_prints_as_its_target(value, target, text):
    shown = _results.beside(value, target)
    assert shown == text
    # read back, it lies on the same side of the target as the value
    assert (float(shown) < target) == (value < target)
    assert (float(shown) > target) == (value > target)


def test_tradeoff_summary_prints_an_error_just_under_its_target_as_under(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    res = _results.Results("tradeoff", "Run time against error")
    res.table("terms:corner", "Time against error per term: corner",
              ["method", "term", "term s", "cumulative s", "wall s", "error", "residual",
               "nnz(X)"],
              [["power", 3, 0.3, 0.9, 1.0, 9.9996e-5, 8e-5, 4000],
               ["power", 4, 0.3, 1.2, 1.3, 1.00004e-4, 8e-5, 4000]],
              note="n = 12288, prune 1e-05. cumulative s: ...")
    res.save()
    line, = report.summary_tradeoff(report.load_records(tmp_path)["tradeoff"])
    assert "error ≤ 1.00e-4 takes 0.9 s (power, 3 terms, prune 1e-05: error 9.9996e-5)" in line


# --- colour, calibration and clusters in the summary --------------------------------------------

ALT_COLUMNS = ["size", "n", "method", "setup s", "frame s (batch 1)", "frame s (batch 64)",
               "peak MiB", "error"]


def _alternatives(folder: Path) -> None:
    """Grey and colour alternatives: bigT's X has the cheapest frames and the most setup;
    splu is the quickest to one frame."""
    res = _results.Results("alternatives", "alternatives")
    res.table("alternatives", "grey", ALT_COLUMNS,
              [["96x128", 12288, "scipy splu", 0.5, 0.01, 0.008, 300.0, 1e-12],
               ["96x128", 12288, "bigT explicit X (4 terms)", 3.0, 0.002, 0.0005, 500.0, 4e-5],
               ["96x128", 12288, "bigT matrix-free (4 terms)", 0.2, 0.02, 0.005, 200.0, 4e-5]])
    res.table("alternatives-colour", "colour", ALT_COLUMNS,
              [["48x64", 3072, "scipy splu of the 3n system", 0.3, 0.004, 0.003, 190.0, 3e-3],
               ["48x64", 3072, "3 grey splu + per-pixel un-mixing", 0.2, 0.003, 0.0035,
                185.0, 3e-3],
               ["48x64", 3072, "bigT colour X, general path (4 terms)", 1.6, 5e-4, 9e-5,
                207.0, 3e-3],
               ["48x64", 3072, "bigT colour X, global-mixing path (4 terms)", 2.2, 4e-4, 4e-5,
                191.0, 3e-3],
               ["48x64", 3072, "MKL PARDISO of the 3n system", None, None, None, None, None]])
    res.save()


def test_when_to_use_bigT_is_computed_from_the_tables(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    _alternatives(tmp_path)
    records = report.load_records(tmp_path)
    grey, colour = report.summary_when(records)
    # grey: X (3 s setup, 5e-4 s a frame) against splu (0.5 s, 8e-3) and matrix-free
    # (0.2 s, 5e-3): ahead of splu after ceil(2.5 / 7.5e-3) = 334 frames, of the
    # matrix-free path after ceil(2.8 / 4.5e-3) = 623: the later one
    assert grey.startswith("Grey, at 96x128: use bigT explicit X (4 terms) for 623 frames or "
                           "more: from there")
    assert ("quickest of the 3 methods timed, its 3 s setup included (5.00e-4 s a frame; the "
            "last it overtakes is bigT matrix-free (4 terms))") in grey
    assert "not for a single frame: bigT matrix-free (4 terms) gives it in 0.22 s against 3 s" \
        in grey
    # colour: the global path's frames are the cheapest; splu's 0.3 s setup at 3e-3 a frame:
    # ceil((2.2 - 0.3) / (3e-3 - 4e-5)) = 642; un-mixing, one by one (its batch of 64 is
    # slower a frame): ceil(2 / (3e-3 - 4e-5)) = 676; the general path: ceil(0.6 / 5e-5)
    assert colour.startswith("Colour, at 48x64: use bigT colour X, global-mixing path (4 terms) "
                             "for 12,000 frames or more")
    assert "quickest of the 4 methods timed" in colour  # PARDISO did not run
    lines = report.summary_alternatives_colour(records["alternatives"])
    assert lines[0].startswith("Colour Cornell box: At 48x64 (n = 3,072): for 1 frame the "
                               "quickest is 3 grey splu + per-pixel un-mixing")
    assert "Not run here: MKL PARDISO of the 3n system" not in lines[0]  # empty: not a reason


def test_when_to_use_bigT_says_never_when_another_has_cheaper_frames(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    res = _results.Results("alternatives", "alternatives")
    res.table("alternatives", "grey", ALT_COLUMNS,
              [["48x64", 3072, "numpy.linalg.inv (dense)", 1.0, 3e-4, 1e-4, 300.0, 1e-12],
               ["48x64", 3072, "bigT explicit X (4 terms)", 3.0, 1e-3, 2e-4, 500.0, 4e-5]])
    res.save()
    line, = report.summary_when(report.load_records(tmp_path))
    assert ("bigT explicit X (4 terms) is never the quickest for good: numpy.linalg.inv "
            "(dense)'s frames are as cheap (1.00e-4 s against 2.00e-4 s)") in line


def test_summary_without_records_says_not_measured():
    assert "not measured in this run" in report.summary_when({})[0]
    assert "not measured in this run" in report.summary_calibration(None)[0]
    assert "not measured in this run" in report.summary_colour(None)[0]
    assert "not measured in this run" in report.summary_alternatives_colour(None)[0]
    assert "not measured in this run" in report.summary_objects(None)[0]
    assert "not measured in this run" in report.summary_cluster_model(None)[0]


def test_calibration_summary_quotes_its_tables(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    res = _results.Results("calibration", "Calibration")
    res.table("seen", "seen", ["grid", "camera", "linear rig", "nonlinear, calibrated",
                               "nonlinear, uncalibrated", "calibrated / linear",
                               "goal <= 1.5x met"],
              [["24x32", "60x80", 0.0553, 0.0428, 0.7176, _results.beside(1.4996, 1.5), True]])
    res.table("hdr", "hdr", ["grid", "camera", "exposures", "response", "camera response",
                             "nnz/row", "T rel. error", "direct (diagonal)",
                             "interreflection (off-diagonal)", "off-diagonal light kept",
                             "projector response max error", "build s"],
              [["24x32", "60x80", 1, "gamma:2.2", "gamma 2.2", 2.2, 0.0097, 0.0047, 0.4794,
                0.107, 2.8e-4, 1.4],
               ["24x32", "60x80", 3, "gamma:2.2", "gamma 2.2", 20.7, 0.0068, 0.0046, 0.2848,
                0.321, 2.9e-4, 4.3],
               ["24x32", "60x80", 3, "recover", "recovered", 20.0, 0.0071, 0.0046, 0.29,
                0.3, 3e-4, 4.4]])
    res.save()
    hdr, seen = report.summary_calibration(report.load_records(tmp_path)["calibration"])
    assert ("On the 24x32 grid (camera 60x80), T's relative error against the scene's truth "
            "from the known camera response: 0.0097 (1 exposure), 0.0068 (3 exposures); its "
            "interreflection part 0.479 from one exposure, 0.285 from 3; with the response "
            "recovered from the brackets: 0.0071 (3 exposures).") == hdr
    assert "0.0428 with the calibrated responses (1.4996× the linear rig's)" in seen
    assert "0.718 without them" in seen


def test_colour_summary_compares_with_goals_and_reads_the_sweep(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    res = _results.Results("colour")
    res.table("inverse", "Cornell box 48x64", ["path", "seconds", "nnz(X)", "x grey"],
              [["grey", 1.0, 10, 1.0]])
    res.value("general_over_grey", 1.53, "")
    res.value("global_over_grey", 3.4996, "")
    res.table("tradeoff", "Time against error, colour",
              ["path", "prune", "terms", "seconds", "nnz(X)", "error", "seen dE2000 mean"],
              [["general", 1e-4, 1, 0.5, 10, 1e-3, 1.2], ["general", 1e-4, 2, 0.8, 10, 1e-3, 0.3],
               ["general", 1e-6, 3, 1.5, 10, 1e-3, 0.09],
               ["global", 1e-4, 1, 0.6, 10, 1e-3, 0.9], ["global", 1e-4, 2, 0.9, 10, 1e-3, 0.2]])
    res.save()
    lines = report.summary_colour(report.load_records(tmp_path)["colour"])
    assert ("the general path took 1.53× the grey inverse's time (goal ≤ 10) and the "
            "global-mixing path took 3.4996× the grey inverse's time (goal ≤ 3.5)") in lines[0]
    sweep = lines[-1]
    assert "the general path reaches seen ΔE ≤ 1 in 0.8 s (prune 1.00e-4, 2 terms: ΔE 0.3)" \
        in sweep
    assert "the general path reaches seen ΔE ≤ 0.1 in 1.5 s (prune 1.00e-6, 3 terms" in sweep
    assert "the global path reaches seen ΔE ≤ 1 in 0.6 s" in sweep
    assert "the global path does not reach seen ΔE ≤ 0.1 in its 2 settings" in sweep


def test_clusters_in_the_summary(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    dist = _results.Results("distributed", "schedulers")
    dist.table("schedulers", "4-term inverse", ["scheduler", "total s", "terms s", "tasks",
                                                "ms/task", "peak RSS per process",
                                                "max |X - X_threads|"],
               [["threads", 16.6, "", 0, 0, "", 0.0], ["local:2", 24.0, "", 10, 1, "", 0.0],
                ["2 dask workers", 18.8, "", 10, 1, "", 0.0]])
    dist.save()
    objects = _results.Results("objects", "Object storage: a 4-term inverse, local vs S3")
    objects.table("runs", "Object storage: best of the repeats",
                  ["storage", "scheduler", "engine path", "seconds", "/ local"],
                  [["local directory", "threads", "out-of-core", 9.0, 1.0],
                   ["S3 on loopback", "threads", "out-of-core", 18.0, 2.0],
                   ["local directory", "threads", "in-memory", 2.0, 1.0],
                   ["S3 on loopback", "threads", "in-memory", 2.5, 1.25]])
    objects.save()
    model = _results.Results("cluster-model", "The cluster run")
    model.table("check", "check", ["from", "predicts", "predicted s", "measured s", "error %",
                                   "predicted MiB/worker", "measured MiB/worker",
                                   "memory error %"],
                [["local:1", "local:2", 10.0, 11.0, -9.1, 100, 110, -9],
                 ["local:1", "threads", 8.0, 8.4, 4.8, 100, 100, 0]])
    model.table("predicted", "predicted", ["n", "storage", "workers", "seconds",
                                           "GiB per worker", "batched"],
                [[8294400, "shared filesystem", 1, 5000.0, 6.0, False],
                 [8294400, "shared filesystem", 16, 600.0, 1.0, False],
                 [8294400, "shared filesystem", 64, 700.0, 0.5, True],
                 [2073600, "shared filesystem", 1, 900.0, 2.0, False]])
    model.save()
    records = report.load_records(tmp_path)
    assert report.summary_when(records)[-1] == (
        "On one machine, threads ran the inverse quickest of the 3 schedulers (16.6 s; "
        "local:2 24 s, 2 dask workers 18.8 s).")
    check, predicted = report.summary_cluster_model(records["cluster-model"])
    assert check.startswith("The cluster model predicted the 2 runs made here within 9.1 % "
                            "of their time (worst: local:2 from local:1")
    assert predicted == ("It predicts the inverse at n = 8,294,400 as shared filesystem: "
                         "5,000 s on 1 worker, 600 s at best on 16 workers.")
    objects_line, = report.summary_objects(records["objects"])
    # each S3 run beside the local run of its scheduler *and* engine path
    assert ("S3 on loopback took 18 s with threads, out-of-core (2× the local directory's "
            "9 s), 2.5 s with threads, in-memory (1.25× the local directory's 2 s)."
            in objects_line)


def test_the_payback_against_pardiso_and_the_matrix_free_path(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    res = _results.Results("alternatives", "alternatives")
    res.table("alternatives", "grey", ALT_COLUMNS,
              [["96x128", 12288, "MKL PARDISO (pypardiso)", 0.4, 0.004, 0.003, 300.0, 1e-12],
               ["96x128", 12288, "bigT explicit X (4 terms)", 3.0, 0.002, 0.0005, 500.0, 4e-5],
               ["96x128", 12288, "bigT matrix-free (4 terms)", 0.2, 0.02, 0.005, 200.0, 4e-5]])
    res.save()
    line = report.summary_alternatives(report.load_records(tmp_path)["alternatives"])[0]
    # (3 - 0.4) / (0.003 - 0.0005) = 1040 frames; (3 - 0.2) / (0.005 - 0.0005) = 622.2 -> 623
    assert ("bigT explicit X (4 terms), its setup included, catches up with MKL PARDISO "
            "(pypardiso) after 1,040 frames and with bigT matrix-free (4 terms) after 623 "
            "frames.") in line


def test_frames_are_batched_only_where_batching_pays():
    lu = report.Cost("scipy splu", 0.3, 0.004, 0.02, 1e-12, None)
    X = report.Cost("bigT explicit X", 2.0, 0.002, 0.0005, 4e-5, None)
    assert not lu.batched(1000) and lu.per_frame(1000) == 0.004
    assert X.batched(1000) and X.per_frame(1000) == 0.0005
    assert not X.batched(10) and X.per_frame(10) == 0.002  # too few frames to batch
    assert lu.total(1000) == pytest.approx(0.3 + 1000 * 0.004)


def test_the_target_table_prints_the_error_reached_beside_its_target():
    import bench_target

    assert bench_target.reached({"error": 9.996e-4, "E": 1e-3, "met": True}) == "9.996e-4"
    assert bench_target.reached({"error": 1.0004e-3, "E": 1e-3, "met": False}) == \
        "0.0010004 (not met)"
    assert bench_target.reached({"error": 2.26e-3, "E": 3.92e-3, "met": True}) == "0.00226"


def test_the_layout_sentence_sets_this_tree_beside_its_baseline(tmp_path, monkeypatch):
    monkeypatch.setenv(_results.OUT_ENV, str(tmp_path))
    for name, size, seconds in (("layout", "384x512", (18.0, 12.4)),
                                ("layout-fhd", "1080x1920", (95.8, 66.2))):
        res = _results.Results(name, f"Store layout: a 4-term inverse of the dense {size} corner")
        res.table("runs", "Whole run", ["code", "store format", "seconds"],
                  [["baseline 2789f82", 1, seconds[0]], ["this tree", 2, seconds[1]]])
        res.table("terms", "Per term", ["code", "term", "seconds", "files", "files written"],
                  [["baseline 2789f82", 0, 0.4, None, None],
                   ["baseline 2789f82", 1, 2.4, 1662, 1662],
                   ["baseline 2789f82", 2, 7.1, 1354, 1046],
                   ["this tree", 0, 0.3, None, None], ["this tree", 1, 1.5, 354, 354],
                   ["this tree", 2, 4.7, 354, 354]])
        res.save()
    records = report.load_records(tmp_path)
    small, large = report.summary_layout([records["layout"], records["layout-fhd"], None])
    assert small == ("Store layout, a 4-term inverse of the dense 384x512 corner: 12.4 s in "
                     "format 2 (this tree) against 18 s in format 1 (baseline 2789f82); a term "
                     "wrote 354 files against 1,046–1,662.")
    assert large.startswith("Store layout, a 4-term inverse of the dense 1080x1920 corner: "
                            "66.2 s in format 2")
    assert report.summary_layout([None]) == []
    assert any(line == f"- {small}" for line in report.summary(records))
