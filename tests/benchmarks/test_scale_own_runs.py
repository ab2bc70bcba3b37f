"""bench_scale's ``--own-runs``: the rows of an earlier run at a size the full plan leaves
out (full HD, 4K) join the scale table, each marked with that run's commit and date, and
the summary says which sizes this run measured and which come from an own run."""

from __future__ import annotations

import json
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))

import bench_scale  # noqa: E402
import report  # noqa: E402


def _row(size: str, n: int, seconds: float, peak: float) -> dict:
    return {"size": size, "n": n, "nnz_T_per_row": 70.0, "build_s": 10.0 * seconds,
            "build_peak_gib": peak + 0.1, "invert_s": seconds, "term_s": [0.5, 1.25],
            "peak_gib": peak, "X_disk_gib": 0.1, "sampled_error": 3e-5, "residual": 2e-5,
            "compensate_s": 1.0, "compensated_error": 0.001}


def _record(path: Path, rows: list[dict], commit: str) -> None:
    columns = [c for c, _ in bench_scale.TABLE_COLUMNS]
    values = [[" ".join(f"{t:.1f}" for t in r["term_s"]) if k == "term_s" else r[k]
               for _, k in bench_scale.TABLE_COLUMNS] for r in rows]
    path.write_text(json.dumps({
        "name": "scale", "command": "python benchmarks/bench_scale.py --min-size 8294400",
        "started": 1795730119.0, "code": {"commit": commit, "clean": True},
        "tables": [{"key": "scale", "title": "t", "columns": columns, "rows": values,
                    "note": ""}]}))


def test_own_run_rows_are_read_back_marked_and_skip_sizes_measured_here(tmp_path):
    own = tmp_path / "scale-4k.json"
    _record(own, [_row("768x1024", 786432, 45.0, 1.3), _row("2160x3840", 8294400, 511.0, 5.7)],
            "71262ba")
    rows, line = bench_scale.own_run_rows(str(own), {"768x1024"})
    assert [r["size"] for r in rows] == ["2160x3840"]  # this run's size is not taken twice
    r = rows[0]
    assert r["invert_s"] == 511.0 and r["peak_gib"] == 5.7 and r["term_s"] == [0.5, 1.2]
    assert r["measured"].startswith("own run, 71262ba, 2026-")
    assert "1 row(s)" in line and "--min-size 8294400" in line


def test_a_missing_own_run_is_noted_not_fatal(tmp_path):
    rows, line = bench_scale.own_run_rows(str(tmp_path / "none.json"), set())
    assert rows == [] and "not found" in line


def test_summary_fits_this_run_and_names_the_own_run(tmp_path):
    here = [_row("96x128", 12288, 2.0, 0.25), _row("768x1024", 786432, 45.0, 1.3)]
    own = tmp_path / "scale-4k.json"
    _record(own, [_row("2160x3840", 8294400, 511.0, 5.7)], "71262ba")
    taken, line = bench_scale.own_run_rows(str(own), {r["size"] for r in here})

    class Args:
        terms, memory_limit, sample = 4, "4GiB", 2048
        prune, prune_feed, prune_operator = 3e-6, 1e-4, 1e-5

    class Res:
        def table(self, key, title, columns, rows, note=""):
            self.saved = report.Table(key, title, list(columns), [list(r) for r in rows], note)

    res = Res()
    bench_scale.record_rows(res, here + taken, Args(), [line])
    assert res.saved.columns[-1] == "measured"
    assert [r[-1] for r in res.saved.rows] == ["this run", "this run", taken[0]["measured"]]
    rec = report.Record("scale", "", "", [res.saved], [], {
        "exponent:time": report.Value("exponent:time", 0.72, ""),
        "exponent:peak": report.Value("exponent:peak", 0.41, "")}, [], [], None, None, None)
    text = report.summary_scale(rec)
    assert text[0].startswith("At 768x1024") and "from 96x128 to 768x1024" in text[0]
    assert len(text) == 2 and text[1].startswith("At 2160x3840") and "71262ba" in text[1]
    assert "not this run" in text[1]


def test_the_plot_draws_own_rows_apart(tmp_path):
    here = [_row("96x128", 12288, 2.0, 0.25), _row("768x1024", 786432, 45.0, 1.3)]
    own = [{**_row("2160x3840", 8294400, 511.0, 5.7), "measured": "own run, abc, 2026-11-26"}]
    path = bench_scale.plot(here, str(tmp_path / "scale.png"), own)
    assert Path(path).stat().st_size > 0
