"""Fuzzing the acquisition readers (issue #33, point 7), as tests/storage's
test_hostile_stores.py fuzzes stores: valid pattern manifests and captures folders,
mutated structure-aware (JSON values and types, keys missing or extra, huge numbers,
NUL strings, deep nesting; capture files truncated, of another size, pixel type or
channel count, links out of the folder, FIFOs, names that break the
``<pattern>@<seconds>.<ext>`` layout, EXIF exposure times of any value), then read as
``bigT acquire build`` reads them (:func:`read_manifest`, :class:`Captures` and every
pattern's signal) under a time limit (an alarm) and a memory limit (tracemalloc's peak
of what numpy and Python allocate).

Every case must end in a read or one line (a :class:`bigT.BigTError` whose message is
one line), never another exception, a hang or memory beyond the limit. A sample runs
in the default suite, thousands with ``-m slow`` (``make test-all``);
:data:`OUTCOMES` keeps the counts, the slowest case and the largest peak for a report.
"""

from __future__ import annotations

import json
import os
import signal
import time
import tracemalloc
from contextlib import contextmanager
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bigT.acquisition.captures import Captures
from bigT.acquisition.manifest import make_manifest, read_manifest, write_manifest
from bigT.errors import BigTError
from bigT.images import write_image

#: a case's limits: far above what these tiny folders need (~1 MiB), far below a bomb
CASE_SECONDS = 20
CASE_BYTES = 256 << 20
#: outcome -> count, and the slowest case and largest peak seen (for the report)
OUTCOMES: dict = {"cases": 0, "read": 0, "one line": 0, "slowest": (0.0, ""),
                  "peak": (0, "")}

CAMERA = (6, 8)


class CaseTimeout(Exception):
    """A case ran past :data:`CASE_SECONDS` (a hang)."""


@contextmanager
def _time_limit(seconds: float):
    def expire(signum, frame):
        raise CaseTimeout(f"past {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


# --- valid templates -------------------------------------------------------------------

def _write_templates(root: Path, bracketed: bool) -> tuple[Path, Path]:
    """A grey brute-force pattern set for a 4x4 projector in 2x2 super-pixels (black,
    white, 4 super-pixels) and its captures: 6x8 8-bit PNGs, one per pattern or a
    bracket of two exposures each."""
    patterns, captures = root / "patterns", root / "captures"
    patterns.mkdir(parents=True)
    captures.mkdir()
    manifest = make_manifest("brute-force", (4, 4), 2, graycode=False)
    write_manifest(patterns, manifest)
    rng = np.random.default_rng(0)
    for k, p in enumerate(manifest.patterns):
        level = 0.05 if p.kind == "black" else 0.2 + 0.1 * k
        for seconds in ((0.01, 0.02) if bracketed else (None,)):
            scale = 1.0 if seconds is None else seconds / 0.02
            image = np.clip(level * scale + rng.uniform(0, 0.02, CAMERA), 0, 1)
            name = p.stem + ("" if seconds is None else f"@{seconds}") + ".png"
            write_image(captures / name, image, bits=8)
    return patterns, captures


def _read_all(patterns: Path, captures: Path) -> None:
    """What ``bigT acquire build`` reads before it solves: the manifest, the captures
    matched to it, every pattern's signal."""
    manifest = read_manifest(patterns)
    cap = Captures(manifest, captures)
    for p in manifest.patterns:
        signal_ = cap.signal(p)
        assert signal_.shape[:2] == cap.shape and np.isfinite(signal_).all()


# --- mutations -------------------------------------------------------------------------

_SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(-2**70, 2**70), st.sampled_from([10**400, -1, 0]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20), st.sampled_from(["\x00", "a\x00b", "black", "R", "col", "1e999"]))
_JSON = st.recursive(_SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=12)


def _paths(value, prefix=()):
    """Every key path of a JSON value (dict keys and list indices)."""
    yield prefix
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _paths(v, prefix + (i,))


def _set(doc, path, value, delete=False):
    if not path:
        return value
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return doc


@st.composite
def manifest_mutation(draw):
    """A function editing the manifest file of a pattern folder."""
    kind = draw(st.sampled_from(["value", "value", "value", "delete", "extra", "nesting",
                                 "truncate", "bytes", "directory", "fifo", "link out",
                                 "huge"]))
    choice = draw(st.integers(0, 10**6))
    value = draw(_JSON)
    cut = draw(st.integers(0, 2000))

    def mutate(file: Path, outside: Path) -> str:
        text = file.read_text()
        doc = json.loads(text)
        paths = list(_paths(doc))
        path = paths[choice % len(paths)]
        if kind == "value":
            file.write_text(json.dumps(_set(doc, path, value)))
        elif kind == "delete" and path:
            file.write_text(json.dumps(_set(doc, path, None, delete=True)))
        elif kind == "extra":
            target = doc if not path else _set(doc, (), doc)
            target["extra\x00"] = value
            file.write_text(json.dumps(doc))
        elif kind == "nesting":  # past the parser's recursion limit
            depth = 10_000 + choice % 200_000
            file.write_text("[" * depth + "]" * depth)
        elif kind == "truncate":
            file.write_text(text[:cut % max(1, len(text))])
        elif kind == "bytes":
            file.write_bytes(text.encode()[:cut] + bytes([0xff, 0xfe, 0]) + text.encode()[cut:])
        elif kind == "directory":
            file.unlink()
            file.mkdir()
        elif kind == "fifo":
            file.unlink()
            os.mkfifo(file)
        elif kind == "link out":
            (outside / "manifest.json").write_text(text)
            file.unlink()
            file.symlink_to(outside / "manifest.json")
        elif kind == "huge":  # a manifest far past any pattern list's size
            with open(file, "a") as f:
                f.write(" " * (64 << 20))
        return f"manifest {kind} {path!r:.60} {value!r:.60}"

    return mutate


_LAYOUT_BREAKERS = ["@", "@@0.01", "@0.01@0.02", "@1e999", "@0", "@1-0", "@nan", "@inf",
                    "@-1", "@ 0.01", "@1e-999", "@0.01s", "@a", "@1-250", "@" + "9" * 240,
                    ".0.01", "@0.01.png"]


@st.composite
def captures_mutation(draw):
    """A function editing one capture file (or the folder) of a captures folder."""
    kind = draw(st.sampled_from(["truncate", "size", "dtype", "channels", "garbage",
                                 "rename", "link out", "dangling link", "link to dir",
                                 "fifo", "directory", "delete", "extra", "exif",
                                 "npy header"]))
    which = draw(st.integers(0, 10**6))
    cut = draw(st.integers(0, 400))
    suffix = draw(st.sampled_from(_LAYOUT_BREAKERS))
    exif_time = draw(st.one_of(
        st.tuples(st.integers(-2**31, 2**32 - 1), st.integers(-2**31, 2**32 - 1)),
        st.sampled_from([(0, 0), (1, 0), (0, 1), (2**32 - 1, 1)])))
    shape = draw(st.sampled_from([(1, 1), (6, 7), (60, 80), (1, 8), (6, 8, 4), (6, 8, 2)]))

    def mutate(folder: Path, outside: Path) -> str:
        files = sorted(folder.iterdir())
        file = files[which % len(files)]
        stem, ext = file.name.split("@")[0].split(".")[0], file.suffix
        if kind == "truncate":
            data = file.read_bytes()
            file.write_bytes(data[:cut % len(data)])
        elif kind in ("size", "channels"):
            # imageio: write_image refuses the 2- and 4-channel images wanted here
            iio.imwrite(file, np.full(shape if kind == "size" else CAMERA + (3,), 128,
                                      np.uint8), extension=ext or ".png")
        elif kind == "dtype":
            write_image(file, np.full(CAMERA, 0.5), bits=16)
        elif kind == "garbage":
            file.write_bytes(np.random.default_rng(which).bytes(cut))
        elif kind == "rename":
            file.rename(folder / f"{stem}{suffix}{ext}")
        elif kind == "link out":
            (outside / file.name).write_bytes(file.read_bytes())
            file.unlink()
            file.symlink_to(outside / file.name)
        elif kind == "dangling link":
            file.unlink()
            file.symlink_to(outside / "nothing.png")
        elif kind == "link to dir":
            file.unlink()
            file.symlink_to(outside)
        elif kind == "fifo":
            file.unlink()
            os.mkfifo(file)
        elif kind == "directory":
            file.unlink()
            file.mkdir()
        elif kind == "delete":
            file.unlink()
        elif kind == "extra":
            (folder / f"{stem}{suffix}{ext}").write_bytes(file.read_bytes())
        elif kind == "exif":
            _write_exif_png(file, exif_time)
        elif kind == "npy header":  # an .npy declaring a huge array, in the pattern's place
            file.unlink()
            header = "{'descr': '<f8', 'fortran_order': False, 'shape': (100000, 100000), }"
            (folder / f"{stem}.npy").write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(
                2, "little") + header.encode() + b"\x00" * 64)
        return f"capture {kind} {file.name} {suffix!r} {exif_time} {shape}"

    return mutate


def _write_exif_png(file: Path, exposure: tuple[int, int]) -> None:
    """The capture rewritten as a PNG whose EXIF records ``exposure`` (numerator,
    denominator) as its exposure time."""
    from PIL import Image

    image = Image.open(file)
    image.load()
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0x829A] = exposure  # Exif IFD, ExposureTime
    try:
        image.save(file, exif=exif)
    except (ValueError, OverflowError, TypeError, Exception):  # Pillow refuses to write it
        image.save(file)


# --- one case --------------------------------------------------------------------------

def _case(tmp_path_factory, mutation, target: str, bracketed: bool) -> None:
    root = tmp_path_factory.mktemp("fuzz")
    patterns, captures = _write_templates(root / "set", bracketed)
    outside = root / "outside"
    outside.mkdir()
    if target == "manifest":
        what = mutation(patterns / "manifest.json", outside)
    else:
        what = mutation(captures, outside)
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with _time_limit(CASE_SECONDS):
            _read_all(patterns, captures)
        outcome = "read"
    except BigTError as exc:
        text = str(exc)
        assert "\n" not in text and len(text) < 2000, (what, text)
        outcome = "one line"
    finally:
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < CASE_BYTES, (what, peak)
    OUTCOMES["cases"] += 1
    OUTCOMES[outcome] += 1
    if seconds > OUTCOMES["slowest"][0]:
        OUTCOMES["slowest"] = (seconds, what)
    if peak > OUTCOMES["peak"][0]:
        OUTCOMES["peak"] = (peak, what)


_SAMPLE = settings(max_examples=30, deadline=None, database=None,
                   suppress_health_check=[HealthCheck.function_scoped_fixture,
                                          HealthCheck.too_slow, HealthCheck.data_too_large])


@_SAMPLE
@given(mutation=manifest_mutation())
def test_fuzz_mutated_manifest_reads_or_fails_in_one_line(tmp_path_factory, mutation):
    _case(tmp_path_factory, mutation, "manifest", bracketed=False)


@_SAMPLE
@given(mutation=captures_mutation(), bracketed=st.booleans())
def test_fuzz_mutated_captures_read_or_fail_in_one_line(tmp_path_factory, mutation, bracketed):
    _case(tmp_path_factory, mutation, "captures", bracketed)


@pytest.mark.slow
@settings(_SAMPLE, max_examples=1000)
@given(mutation=manifest_mutation())
def test_fuzz_mutated_manifest_many(tmp_path_factory, mutation):
    _case(tmp_path_factory, mutation, "manifest", bracketed=False)


@pytest.mark.slow
@settings(_SAMPLE, max_examples=2000)
@given(mutation=captures_mutation(), bracketed=st.booleans())
def test_fuzz_mutated_captures_many(tmp_path_factory, mutation, bracketed):
    _case(tmp_path_factory, mutation, "captures", bracketed)


def test_fuzz_report():
    """The counts so far (run after the fuzz tests: pytest -s prints them)."""
    import resource

    # tracemalloc sees Python's and numpy's allocations, not Pillow's own: the process's
    # peak resident size bounds those too (every case so far, pytest's own included)
    max_rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("acquisition fuzz:", OUTCOMES, f"process max RSS {max_rss_mib:.0f} MiB")
    assert OUTCOMES["cases"] == OUTCOMES["read"] + OUTCOMES["one line"]


# --- what the fuzzing found, kept as plain tests ---------------------------------------

@pytest.mark.parametrize("make", ["nesting", "directory", "fifo", "huge"])
def test_manifest_that_is_no_manifest_is_one_line(tmp_path, make):
    """Found by the fuzzer: a manifest nested past the parser's recursion (a
    RecursionError), a directory in its place (IsADirectoryError), a FIFO (the read
    waited for ever); and one past the size limit is refused, not read whole."""
    from bigT.acquisition import manifest as m

    patterns, _ = _write_templates(tmp_path, bracketed=False)
    file = patterns / "manifest.json"
    file.unlink()
    if make == "nesting":
        file.write_text("[" * 100_000 + "]" * 100_000)
    elif make == "directory":
        file.mkdir()
    elif make == "fifo":
        os.mkfifo(file)
    else:
        file.write_text(" " * 2048)
    with _time_limit(CASE_SECONDS):
        if make == "huge":
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(m, "MANIFEST_MAX_BYTES", 1024)
                with pytest.raises(BigTError, match="larger than 1024 bytes"):
                    read_manifest(patterns)
        else:
            with pytest.raises(BigTError, match="pattern manifest") as info:
                read_manifest(patterns)
            assert "\n" not in str(info.value)
