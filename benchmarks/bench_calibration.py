"""Calibration: what HDR brackets and the projector ramp buy T on a nonlinear rig (#29).

The simulated nonlinear rig (``bigT acquire simulate --projector-gamma ...``: a projector
of gamma 2.2 over a black of 0.02 under a shoulder of 0.3, an 8-bit camera of gamma 2.2,
shot noise of a 20,000-electron full well and read noise 0.001) captures a dense corner
scene's patterns (brute force with Gray code and a 17-level ramp) with one exposure and
with brackets of 2, 3 and 4 exposures, 8x apart (the white pattern's brightest pixel at
0.9 of full well in the shortest). ``acquire build --camera-response gamma:2.2`` (the
known curve, and ``recover`` -- Debevec, from the brackets -- for comparison) gives T,
compared with the scene's truth as the simulation documents it
(``expected_scale * T_scene * (1 - black)``):

* T's relative error (Frobenius), its direct part (the diagonal) and its
  interreflection part (the off-diagonal entries);
* the fitted projector response against the rig's true curve above black (max error
  over 1,001 values).

Reports, never asserts.

    python benchmarks/bench_calibration.py                     # 12x16 and 24x32 grids
    python benchmarks/bench_calibration.py --grids 24x32 --cameras 60x80
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _results import Results, run_name  # noqa: E402

BRACKETS = {1: (1.0,), 2: (1.0, 8.0), 3: (1.0, 8.0, 64.0), 4: (1.0, 8.0, 64.0, 512.0)}


def _size(text: str) -> tuple[int, int]:
    h, w = text.lower().split("x")
    return int(h), int(w)


def measure(scene, workdir: Path, camera, exposures, response: str) -> dict:
    from bigT.acquisition import (build_transport, make_manifest, read_camera_model,
                                  simulate_captures, write_patterns)
    from bigT.acquisition.ramp import PROJECTOR_RESPONSE_FILE
    from bigT.calibration import NonlinearRig, load_projector_response
    from bigT.storage import open as open_store

    grid = scene.pixel_order.image_shape
    patterns = workdir / "patterns"
    if not patterns.exists():
        write_patterns(patterns, make_manifest("brute-force", (2 * grid[0], 2 * grid[1]), 2,
                                               graycode=True, ramp_levels=17), progress=False)
    rig = NonlinearRig()  # the documented defaults
    captures = workdir / f"captures-{len(exposures)}"
    if not captures.exists():
        simulate_captures(scene.path, patterns, captures, camera=camera, rig=rig, fmt="png8",
                          exposures=exposures, seed=1, progress=False)
    out = workdir / f"T-{len(exposures)}-{response.replace(':', '')}.zarr"
    t0 = time.perf_counter()
    report = build_transport(patterns, captures, out, overwrite=True, progress=False,
                             camera_response=response)
    seconds = time.perf_counter() - t0
    model = read_camera_model(captures)
    scale = model.expected_scale(scene.pixel_order) * (1 - rig.projector_black)
    truth = scene.T.to_scipy(output_order="matrix").toarray() * scale[:, None]
    truth[:, scale == 0] = 0  # super-pixels no camera pixel sees: left out
    built = open_store(out).to_scipy(output_order="matrix").toarray()
    off = ~np.eye(len(truth), dtype=bool)
    fitted = load_projector_response(out / PROJECTOR_RESPONSE_FILE)
    v = np.linspace(0, 1, 1001)
    true_curve = (rig.project(v) - rig.projector_black) / (1 - rig.projector_black)
    return {"exposures": len(exposures), "response": response,
            "camera": report.camera, "seconds": seconds, "nnz_per_row": report.nnz / report.n,
            "error": float(np.linalg.norm(built - truth) / np.linalg.norm(truth)),
            "direct": float(np.linalg.norm(np.diag(built) - np.diag(truth))
                            / np.linalg.norm(np.diag(truth))),
            "interreflection": float(np.linalg.norm((built - truth)[off])
                                     / np.linalg.norm(truth[off])),
            "kept_light_off": float(built[off].sum() / truth[off].sum()),
            "projector_max_error": float(np.abs(fitted.to_linear(v, above_black=True)
                                                - true_curve).max())}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grids", default="12x16,24x32",
                   help="projector super-pixel grids = the scenes' images (default 12x16,24x32)")
    p.add_argument("--cameras", default="30x40,60x80", help="one camera per grid")
    p.add_argument("--brackets", default="1,2,3,4", help="exposure counts to try")
    p.add_argument("--workdir", default=None)
    args = p.parse_args(argv)

    import bigT.scenes as scenes

    root = Path(args.workdir or tempfile.mkdtemp(prefix="bench_calibration_"))
    res = Results(run_name("calibration"), "Calibration: HDR brackets and the projector ramp "
                  "on a simulated nonlinear rig",
                  "python benchmarks/bench_calibration.py " + " ".join(sys.argv[1:]))
    header = (f"{'grid':>6} {'camera':>6} {'exp':>3} {'camera response':<44} {'nnz/row':>7} "
              f"{'T err':>7} {'direct':>7} {'interrefl':>9} {'off kept':>8} "
              f"{'proj max':>8} {'build s':>7}")
    rows = []
    for grid, camera in zip(map(_size, args.grids.split(",")), map(_size, args.cameras.split(","))):
        workdir = root / f"{grid[0]}x{grid[1]}"
        scene = scenes.make("corner", grid, workdir / "scene.zarr", overwrite=True,
                            preview=False, progress=False)
        print(f"scene: corner {grid[0]}x{grid[1]} (n = {scene.T.shape[0]}, "
              f"{scene.T.nnz / scene.T.shape[0]:.0f} entries per row); camera "
              f"{camera[0]}x{camera[1]}")
        print(header)
        counts = [int(k) for k in args.brackets.split(",")]
        runs = [(k, "gamma:2.2") for k in counts] + [(k, "recover") for k in counts if k >= 3]
        for k, response in runs:
            r = measure(scene, workdir, camera, BRACKETS[k], response)
            print(f"{grid[0]}x{grid[1]:<3} {camera[0]}x{camera[1]:<3} {k:>3} {r['camera']:<44.44} "
                  f"{r['nnz_per_row']:>7.1f} {r['error']:>7.4f} {r['direct']:>7.4f} "
                  f"{r['interreflection']:>9.4f} {r['kept_light_off']:>8.3f} "
                  f"{r['projector_max_error']:>8.1e} {r['seconds']:>7.2f}", flush=True)
            rows.append([f"{grid[0]}x{grid[1]}", f"{camera[0]}x{camera[1]}", k, r["camera"],
                         round(r["nnz_per_row"], 1), r["error"], r["direct"],
                         r["interreflection"], r["kept_light_off"],
                         r["projector_max_error"], r["seconds"]])
    res.table("hdr", "T against the scene's truth on the nonlinear rig (8-bit gamma-2.2 "
              "camera; brackets 8x apart)",
              ["grid", "camera", "exposures", "camera response", "nnz/row", "T rel. error",
               "direct (diagonal)", "interreflection (off-diagonal)",
               "off-diagonal light kept", "projector response max error", "build s"], rows,
              note="relative Frobenius errors; off-diagonal light kept: sum of T's "
                   "off-diagonal entries over the truth's; projector response: max |fitted - "
                   "true| above black over 1,001 values")
    res.save()
    (root / "calibration.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
