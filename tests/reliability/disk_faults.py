"""Failing disks for every command that writes (issue #17, item 3): the commands, the
inputs they run on, and the check (used by ``tests/reliability/test_full_disk.py`` and
``benchmarks/bench_reliability.py``).

Each command runs in a forked child whose k-th file-system mutation fails as the disk
would (:mod:`crash_harness`), for a sample of k over its kinds of mutation, with an
output of an earlier run in place. It must exit with status 2 and one line on
standard error naming the problem (no traceback), leave the earlier output exactly as
it was, and succeed when rerun once the disk has room again.
"""

from __future__ import annotations

import errno
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "algorithms"))

from crash_harness import first_of_each_kind, run_forked  # noqa: E402
from inverse_helpers import random_dominant  # noqa: E402

from bigT.cli import main  # noqa: E402
from bigT.images import write_image  # noqa: E402

H, W = 8, 8
#: Commands with at most this many kinds of mutation have every kind tried.
SAMPLE_ABOVE = 12
#: The commands that write, in the order of the tables.
COMMANDS = ["convert", "export", "scene", "invert", "compensate", "relight", "bounces"]


def build_inputs(tmp: Path) -> Path:
    """T (8x8 image, 64 pixels) as .npz and store, its 2-term inverse, an image, in
    ``tmp``."""
    tmp.mkdir(parents=True, exist_ok=True)
    sp.save_npz(tmp / "T.npz", sp.csr_array(random_dominant(H * W, seed=7)))
    for argv in (["convert", str(tmp / "T.npz"), "-o", str(tmp / "T.zarr"), "--image-shape",
                  f"{H}x{W}", "--tile-size", "16"],
                 ["invert", str(tmp / "T.zarr"), "-o", str(tmp / "X.zarr"), "--terms", "2"]):
        assert main(argv + ["-q"]) == 0
    write_image(tmp / "image.png", np.linspace(0.2, 0.6, H * W).reshape(H, W))
    return tmp


def commands(d: Path) -> dict[str, tuple[list[str], Path]]:
    """Each writing command, with the output it writes (inside ``d / 'out'``)."""
    out = d / "out"
    return {
        "convert": (["convert", str(d / "T.npz"), "-o", str(out / "S.zarr"), "--tile-size",
                     "16", "--overwrite"], out / "S.zarr"),
        "export": (["export", str(d / "X.zarr"), "-o", str(out / "X.mtx")], out / "X.mtx"),
        "scene": (["scene", "corner", "--size", "8x8", "-o", str(out / "scene.zarr"),
                   "--overwrite"], out / "scene.zarr"),
        "invert": (["invert", str(d / "T.zarr"), "-o", str(out / "X.zarr"), "--terms", "3"],
                   out / "X.zarr"),
        "compensate": (["compensate", str(d / "X.zarr"), str(d / "image.png"), "-o",
                        str(out / "c.png")], out / "c.png"),
        "relight": (["relight", str(d / "T.zarr"), str(d / "image.png"), "-o",
                     str(out / "r.png")], out / "r.png"),
        "bounces": (["bounces", str(d / "T.zarr"), str(d / "X.zarr"), str(d / "image.png"),
                     "-o", str(out / "b"), "--bounces", "2"], out / "b"),
    }


def snapshot(path: Path) -> dict[str, bytes]:
    """Every file under ``path`` (or ``path`` itself) and its bytes; locks excluded."""
    if path.is_file():
        return {path.name: path.read_bytes()}
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file() and not p.name.startswith(".bigT-")}


def output_is_whole(output: Path) -> bool:
    """Whether ``output`` reads back complete: a store verifies, a matrix or an image
    loads (every image of a folder)."""
    import imageio.v3 as iio
    import scipy.io

    from bigT.storage import open as open_store

    try:
        if output.suffix == ".zarr":
            open_store(output).verify()
        elif output.suffix == ".mtx":
            scipy.io.mmread(output)
        else:
            for image in ([output] if output.is_file() else sorted(output.glob("*.png"))):
                iio.imread(image)
    except Exception:  # noqa: BLE001 - any failure to read back is the finding
        return False
    return True


def replaced_file_by_file(name: str, output: Path) -> bool:
    """The outputs allowed to change before a failure: an inverse (it resumes, checked
    by the rerun), and the outputs made of several files, replaced one whole file at a
    time: the bounce folder (every image in it must read) and a scene (its store is
    replaced before its preview picture is written; the store must verify)."""
    if name == "invert":
        return True
    if name == "scene":
        from bigT.storage import open as open_store

        open_store(output).verify()  # raises on damage
        return True
    if name != "bounces":
        return False
    import imageio.v3 as iio

    for image in output.glob("*.png"):
        iio.imread(image)  # raises on a truncated file
    return True


def earlier_run(argv: list[str]) -> list[str]:
    """The command that writes the earlier output: the same, but for ``invert``, which
    extends an inverse of fewer terms."""
    if argv[0] == "invert":
        return [a if a != "3" else "1" for a in argv]
    return argv


def copy(source: Path, dest: Path) -> None:
    """Replace ``dest`` by a copy of ``source`` (a file or a folder)."""
    if dest.is_dir():
        shutil.rmtree(dest)
    if source.is_dir():
        shutil.copytree(source, dest)
    else:
        shutil.copy2(source, dest)


@dataclass(frozen=True)
class DiskFaultResult:
    """What failing one command's writes, one kind of mutation at a time, gave.

    Attributes
    ----------
    points : crash points tried (a sample of the kinds of mutation)
    refused : runs that stopped with exit 2 and one line, the earlier output kept
    carried_on : runs where the failing call was a cleanup the command did without
        (exit 0, a complete output)
    problems : (point, kind, what went wrong) of every other run
    """

    command: str
    error: str
    points: int
    refused: int
    carried_on: int
    problems: tuple

    @property
    def ok(self) -> bool:
        return not self.problems


def check_command(inputs: Path, tmp: Path, name: str, error: int,
                  sample: int, offset: int = 0) -> DiskFaultResult:
    """Fail ``name``'s writes with ``error`` at every ``sample``-th kind of mutation,
    starting at the ``offset``-th (0-based) when there are more than SAMPLE_ABOVE."""
    d = tmp / "run"
    shutil.copytree(inputs, d)
    argv, output = commands(d)[name]
    argv = argv + ["-q"]
    assert run_forked(earlier_run(argv))[0] == 0  # the output no failure may harm
    saved = tmp / "saved"
    copy(output, saved)
    status, kinds = run_forked(argv)
    assert status == 0
    points = first_of_each_kind(kinds)
    if len(points) > SAMPLE_ABOVE:
        points = points[offset::sample]
    problems, carried_on = [], 0
    for k in points:
        copy(saved, output)  # every point starts from the same earlier output
        before = snapshot(output)
        err_file = tmp / "stderr"
        status, _ = run_forked(argv, crash_at=k, fail_with=error, stderr_file=str(err_file))
        err = err_file.read_text()
        if status == 0:  # the failing call was a cleanup the command could do without
            if output_is_whole(output):
                carried_on += 1
            else:
                problems.append((k, kinds[k - 1], "exit 0 with a damaged output"))
            continue
        if status != 2 or err.count("\n") != 1 or "Traceback" in err:
            problems.append((k, kinds[k - 1], status, err[-300:]))
        elif snapshot(output) != before and not replaced_file_by_file(name, output):
            problems.append((k, kinds[k - 1], "earlier output changed", err.strip()))
        elif main(argv) != 0:
            problems.append((k, kinds[k - 1], "rerun failed"))
    return DiskFaultResult(name, errno.errorcode[error], len(points),
                           len(points) - carried_on - len(problems), carried_on,
                           tuple(problems))
