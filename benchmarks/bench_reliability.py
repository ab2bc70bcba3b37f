"""Crash points and failing disks, every command that writes (reported, never
asserted; the assertions are in tests/reliability/).

Two tables, printed as markdown (and written to ``--out``/tables.md):

1. Crash-point loops (tests/reliability/crash_checks.py): each command killed just
   before its k-th file-system mutation (as SIGKILL would: no cleanup), then rerun.
   ``invert`` must resume to a bit-identical inverse; ``convert --overwrite`` and
   ``export`` must leave the old output or the new one, whole, and the rerun the new.
2. Failing disks (tests/reliability/disk_faults.py): each writing command's k-th
   mutation fails with ENOSPC (full) or EROFS (read-only); it must exit 2 with one
   line, keep the earlier output, and succeed when rerun.

Run:  nice -n 10 .venv/bin/python benchmarks/bench_reliability.py [--quick] [--every-point]
"""

from __future__ import annotations

import argparse
import errno
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "reliability"))

from crash_checks import check_convert_overwrite, check_export, check_invert  # noqa: E402
from disk_faults import COMMANDS, build_inputs, check_command  # noqa: E402


def crash_table(scratch: Path, sample: int, every_point: bool) -> list[str]:
    rows = ["| command | mutations in one run | kinds | points tried | resumed or rolled "
            "back | failures | seconds |", "|---|---|---|---|---|---|---|"]
    for name, check in (("invert", check_invert), ("convert", check_convert_overwrite),
                        ("export", check_export)):
        t0 = time.perf_counter()
        r = check(scratch / name, sample if name == "invert" else 1,
                  every_point or name != "invert")
        rows.append(f"| {r.command} | {r.mutations} | {r.kinds} | {r.points} | "
                    f"{r.recovered} | {list(r.problems[:2]) or 0} | "
                    f"{time.perf_counter() - t0:.0f} |")
        print(rows[-1], flush=True)
    return rows


def disk_table(scratch: Path, sample: int) -> list[str]:
    rows = ["| command | error | points tried | refused (exit 2, one line, earlier output "
            "kept, rerun OK) | carried on (a cleanup failed, exit 0) | failures |",
            "|---|---|---|---|---|---|"]
    inputs = build_inputs(scratch / "inputs")
    for name in COMMANDS:
        for error in (errno.ENOSPC, errno.EROFS):
            r = check_command(inputs, scratch / f"{name}-{error}", name, error, sample)
            rows.append(f"| {r.command} | {r.error} | {r.points} | {r.refused} | "
                        f"{r.carried_on} | {list(r.problems[:2]) or 0} |")
            print(rows[-1], flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true",
                   help="every 16th kind of crash point of invert, every 3rd kind of "
                        "mutation for the disks (a minute or two)")
    p.add_argument("--every-point", action="store_true",
                   help="invert: every mutation, not one of each kind (about 2000; "
                        "50 minutes)")
    p.add_argument("--disk-sample", type=int, default=None,
                   help="fail every N-th kind of mutation of each command (default 1, "
                        "3 with --quick)")
    p.add_argument("--out", default="bench-out/reliability")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# Reliability", "", "## Crash points", ""]
    with tempfile.TemporaryDirectory(prefix="bigT-reliability-") as tmp:
        print("crash points:", flush=True)
        lines += crash_table(Path(tmp), 16 if args.quick else 1, args.every_point)
        print("failing disks:", flush=True)
        lines += ["", "## Failing disks", ""]
        lines += disk_table(Path(tmp), args.disk_sample or (3 if args.quick else 1))
    (out / "tables.md").write_text("\n".join(lines) + "\n")
    print(f"-> {out / 'tables.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
