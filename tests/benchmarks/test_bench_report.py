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
    assert "| Fig. 6 | T_7^-1 more than 8x faster than the true inverse | 11.2x faster | yes |" in md
    assert "1 of 2 of the paper's claims checked hold" in md
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
