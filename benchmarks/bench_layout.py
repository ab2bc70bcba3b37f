"""The store layout's cost in a 4-term inverse: seconds, files and bytes per term.

Runs ``stratified_inverse`` of the dense corner (the README's recommended thresholds
unless given) in a child process per code tree, so that one run compares this tree's
store format with an older checkout's (``--baseline PATH``: a bigT source tree, e.g.
``git worktree add /tmp/bigT-old <commit>``), interleaved, best of ``--repeats``. After
each published term the child counts the files of the term's directory (X and P) and
how many of them are new (a hard link carried from the term before is not), their
bytes, and at the end its peak RSS. The callback makes every term published (in memory
too); ``--whole`` times the run without it, as a user's ``bigT invert`` runs, and counts
the last term's files only.

    python benchmarks/bench_layout.py                       # 384x512, this tree only
    python benchmarks/bench_layout.py --baseline /tmp/bigT-old --size 1080x1920

``--baseline-commit REV`` exports ``bigT/`` of a commit of this repository (``git
archive``) under the work folder and compares with it: ``make bench`` compares with
2789f82, the last commit that wrote format 1 (a group per tile). ``--scene PATH`` takes
this tree's T from a store already built by the same recipe (the scale run's full-HD
corner is the dense preset at 1080x1920) instead of building it again; the baseline
builds its own, in its own format.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _results import Results, run_name

HERE = Path(__file__).resolve().parent

#: The child: one inverse, one JSON line of what it saw.
CHILD = r"""
import json, os, resource, sys, time
from pathlib import Path
t_import = time.perf_counter()
import bigT
bigT.stratified_inverse  # bigT imports its subpackages on first use: what the run loads
t_import = time.perf_counter() - t_import

T, out, terms, prune, feed, operator, per_term = sys.argv[1:8]
seen = []

def tree(root):
    files = new = size = new_size = 0
    for d, _, names in os.walk(root):
        for name in names:
            st = os.lstat(os.path.join(d, name))
            files += 1
            size += st.st_size
            if st.st_nlink == 1:  # written by this term, not linked from the last
                new += 1
                new_size += st.st_size
    return files, new, size, new_size

def on_term(record):
    k = record.dir
    term = Path(out) / f"t{k:04d}"
    seen.append({"term": record.term, "files": tree(term), "t": time.perf_counter()})

t0 = time.perf_counter()
rep = bigT.stratified_inverse(T, out, terms=int(terms), prune=float(prune),
                              prune_feed=float(feed) or None,
                              prune_operator=float(operator) or None,
                              overwrite=True, progress=False,
                              on_term=on_term if per_term == "1" else None)
total = time.perf_counter() - t0
# the CPU seconds of the import and the run: they drift less than wall time on a
# machine other work shares (peak RSS read at the end)
usage = resource.getrusage(resource.RUSAGE_SELF)
if per_term != "1":  # the files of the term held, counted after the clock
    from types import SimpleNamespace
    held = bigT.open(out).metadata["inverse"]
    on_term(SimpleNamespace(dir=held["dir"], term=held["term"]))
X = bigT.open(out)
record = json.loads((Path(out) / "zarr.json").read_text())["attributes"]["bigT_inverse"]
hist = record["history"]
print(json.dumps({"seconds": total, "import_seconds": t_import, "terms": seen, "history": hist,
                  "residual": record.get("residual"),
                  "rows": X.grid[0], "version": X.attrs.version, "bigT": bigT.__file__,
                  "cpu_seconds": usage.ru_utime + usage.ru_stime,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def build_scene(size: str, root: Path, label: str, tree: Path) -> Path:
    """The dense corner of ``size`` (HxW), built once under ``root`` by the code of
    ``tree``, in that code's store format."""
    path = root / f"corner-{size}-dense-{label.replace(' ', '-')}.zarr"
    if not (path / "zarr.json").exists():
        subprocess.run([sys.executable, "-m", "bigT.cli", "scene", "corner", "--size", size,
                        "--density", "dense", "-o", str(path.resolve()), "-q"], check=True,
                       env={**os.environ, "PYTHONPATH": str(tree.resolve())}, cwd=root)
    return path


def export_commit(rev: str, root: Path) -> Path:
    """``bigT/`` of commit ``rev`` of this repository, exported once under ``root``
    (``git archive``: no worktree, nothing of this checkout touched)."""
    # absolute: the children run in the work folder, where a relative PYTHONPATH
    # would miss the tree and import the installed bigT instead
    tree = (root / f"tree-{rev}").resolve()
    if not (tree / "bigT" / "__init__.py").exists():
        shutil.rmtree(tree, ignore_errors=True)
        tree.mkdir(parents=True)
        archive = subprocess.run(["git", "-C", str(HERE.parent), "archive", rev, "bigT"],
                                 capture_output=True, check=False)
        if archive.returncode:
            sys.exit(f"--baseline-commit {rev}: git archive failed (a shallow clone lacks "
                     f"old commits): {archive.stderr.decode().strip()}")
        subprocess.run(["tar", "-x", "-C", str(tree)], input=archive.stdout, check=True)
    return tree


def run_child(tree: Path, T: Path, out: Path, args) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree.resolve())}
    shutil.rmtree(out, ignore_errors=True)  # another format's store is not overwritten
    # run from the scratch folder: ``python -c`` puts its working directory first on
    # sys.path, which must not be a bigT tree other than ``tree``
    proc = subprocess.run([sys.executable, "-c", CHILD, str(T.resolve()), str(out.resolve()),
                           str(args.terms), str(args.prune), str(args.prune_feed or 0),
                           str(args.prune_operator or 0), "0" if args.whole else "1"],
                          env=env, capture_output=True, text=True, cwd=args.workdir)
    if proc.returncode:
        sys.exit(f"{tree}: the inverse failed:\n{proc.stderr[-3000:]}")
    run = json.loads(proc.stdout.strip().splitlines()[-1])
    imported = Path(run["bigT"]).resolve()
    if not imported.is_relative_to(tree.resolve()):  # the comparison would be with itself
        sys.exit(f"{tree}: the child imported bigT from {imported}, not from this tree")
    return run


def once_seconds(run: dict) -> float:
    """What the run paid outside its terms' records (set-up: T read, F, M; the spectral
    radius; the final waits): the whole run less the sum of its terms' seconds."""
    return run["seconds"] - sum(h["seconds"] for h in run["history"] or ())


def term_rows(label: str, run: dict) -> list[list]:
    """One row per term of the history: its seconds, and the files of its directory
    where they were counted (every term with the callback, else the last)."""
    files_of = {rec["term"]: rec["files"] for rec in run["terms"]}
    history = run["history"] or [{"term": k, "seconds": None} for k in files_of]
    rows = []
    for h in history:
        counted = files_of.get(h["term"])
        files, new, size, new_size = counted or (None,) * 4
        rows.append([label, h["term"], None if h["seconds"] is None else round(h["seconds"], 2),
                     files, new, None if counted is None else round(new / max(run["rows"], 1), 1),
                     None if counted is None else round(size / 2**20, 1),
                     None if counted is None else round(new_size / 2**20, 1)])
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="384x512")
    p.add_argument("--terms", type=int, default=4)
    p.add_argument("--prune", type=float, default=3e-6)
    p.add_argument("--prune-feed", type=float, default=1e-4)
    p.add_argument("--prune-operator", type=float, default=1e-5)
    p.add_argument("--baseline", type=Path, default=None,
                   help="an older bigT source tree to compare with (its bigT/ is imported)")
    p.add_argument("--baseline-commit", default=None, metavar="REV",
                   help="compare with bigT/ of this commit of the repository (exported "
                        "with git archive under --workdir), e.g. 2789f82 (format 1)")
    p.add_argument("--scene", type=Path, default=None,
                   help="this tree's T, already built by the same recipe (the dense "
                        "corner of --size), instead of building it")
    p.add_argument("--baseline-scene", type=Path, default=None,
                   help="the baseline's T, already built (a baseline that reads the "
                        "format of this tree's stores, e.g. an earlier commit of format 2: "
                        "the same store as --scene)")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--whole", action="store_true",
                   help="no per-term callback: the run a user makes (in memory, the terms "
                        "it goes past are not written); files counted for the last term")
    p.add_argument("--workdir", type=Path, default=Path("bench-out/layout"))
    args = p.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    trees = [("this tree", HERE.parent)]
    if args.baseline is not None and args.baseline_commit is not None:
        p.error("--baseline and --baseline-commit: give one")
    if args.baseline is not None:
        trees.insert(0, ("baseline", args.baseline.resolve()))
    if args.baseline_commit is not None:
        trees.insert(0, (f"baseline {args.baseline_commit}",
                         export_commit(args.baseline_commit, args.workdir)))
    given = {"this tree": args.scene}
    given.update({label: args.baseline_scene for label, _ in trees if label != "this tree"})
    for path in given.values():
        if path is not None and not (path / "zarr.json").exists():
            p.error(f"{path}: not a store (no zarr.json)")
    scenes = {label: given[label] or build_scene(args.size, args.workdir, label, tree)
              for label, tree in trees}
    best: dict[str, dict] = {}
    for _ in range(args.repeats):
        for label, tree in trees:  # interleaved: drift hits both alike
            run = run_child(tree, scenes[label], args.workdir / f"X-{label.replace(' ', '-')}.zarr", args)
            print(f"{label}: {run['seconds']:.2f} s ({run['cpu_seconds']:.1f} CPU s), "
                  f"{once_seconds(run):.2f} s outside the terms, "
                  f"import {run.get('import_seconds', 0):.2f} s, format {run['version']}, "
                  f"peak {run['peak_rss_mb']:.0f} MB, residual {run.get('residual')}, "
                  f"terms {[round(h['seconds'], 2) for h in run['history']]}", flush=True)
            if label not in best or run["seconds"] < best[label]["seconds"]:
                best[label] = run
    res = Results(run_name("layout"), f"Store layout: a {args.terms}-term inverse of the "
                  f"dense {args.size} corner",
                  " ".join(["python benchmarks/bench_layout.py"] + (argv or sys.argv[1:])))
    res.table("runs", "Whole run (best of the repeats)",
              ["code", "store format", "seconds", "CPU seconds", "outside the terms s",
               "import s", "peak RSS MB", "residual"],
              [[k, v["version"], round(v["seconds"], 2), round(v["cpu_seconds"], 1),
                round(once_seconds(v), 2), round(v.get("import_seconds", 0), 2),
                round(v["peak_rss_mb"]),
                v.get("residual")] for k, v in best.items()])
    rows = [r for label, run in best.items() for r in term_rows(label, run)]
    res.table("terms", "Per term: seconds, files of the term's directory (X and P) and "
              "those written by it (not hard-linked from the term before), per tile row, "
              "and their MiB", ["code", "term", "seconds", "files", "files written",
                                "written per tile row", "MiB", "MiB written"], rows)
    for label, run in best.items():
        res.value(f"layout:seconds:{label}", run["seconds"], f"whole run, {label}")
    res.save()
    print(json.dumps({k: {"seconds": v["seconds"], "terms": term_rows(k, v)}
                      for k, v in best.items()}, indent=1))


if __name__ == "__main__":
    started = time.time()
    main()
    print(f"done in {time.time() - started:.0f} s")
