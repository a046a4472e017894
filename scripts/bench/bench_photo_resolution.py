"""Benchmark: lamp detection on the labelled real photos per resolution policy (issue 20).

For each photo of ``--photos`` (default ``../shared/data/ceiling_photos``), decoded once
(the JPEG decode, ~0.3 s CPU for 4000x3000, is the same for every policy and
is timed apart), the policies

* ``320``: reduce to 320 px and detect (the reference);
* ``640``: reduce to 640 px and detect;
* ``auto``: a first pass at 320 px, then the width that makes the median lamp
  10 px wide (:func:`lampsam.frontend.resolution.width_for_lamps`);
* ``320+look``: 320 px, then a second look at 4x (1280 px) inside the long or
  border-cut blobs (:mod:`lampsam.frontend.second_look`);
* ``auto+look``: both, the look at 2x the working width (what
  ``lampsam frontend-eval --photos`` runs by default);
* ``auto+look4``, ``auto+full``: the same with the second look at 4x the
  working width or at full resolution

are run in turn ``--runs`` times (default 5; each policy sees the same load).
Printed per photo and policy: the median process CPU time (ms, the resize
from full resolution included), its ratio to ``320`` in the same rounds, and
precision / recall against the labels; then the load average before and after.

    python scripts/bench/bench_photo_resolution.py [--photos DIR] [--runs N]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import cv2

from lampsam.datasets.logrun import CameraModel
from lampsam.evaluation.gallery import load_photo
from lampsam.evaluation.photo_eval import PhotoEvalSettings, score_photo
from lampsam.evaluation.photo_labels import read_labels
from lampsam.frontend.lamp_config import DEFAULT_CONFIG
from lampsam.frontend.resolution import ResolutionPolicy, detect_photo_lamps

ROOT = Path(__file__).resolve().parents[2]
POLICIES = {
    "320": ResolutionPolicy(width=320, auto=False, second_look=False),
    "640": ResolutionPolicy(width=640, auto=False, second_look=False),
    "auto": ResolutionPolicy(auto=True, second_look=False),
    "320+look": ResolutionPolicy(width=320, auto=False, second_look=True, look_factor=4.0),
    "auto+look": ResolutionPolicy(auto=True, second_look=True),
    "auto+look4": ResolutionPolicy(auto=True, second_look=True, look_factor=4.0),
    "auto+full": ResolutionPolicy(auto=True, second_look=True, look_factor=1e9),
}


def camera(width: int, height: int) -> CameraModel:
    """The evaluation's 70 deg pinhole at a working size."""
    return CameraModel.from_fov(width, height, 70.0)


def main() -> int:
    """Run the benchmark (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", default=str(ROOT.parent / "shared" / "data" / "ceiling_photos"))
    ap.add_argument("--labels", default=str(ROOT / "tests" / "data" / "ceiling_photo_labels.json"))
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"load average before: {os.getloadavg()}")
    labels = read_labels(args.labels)
    for name, pl in labels.items():
        path = Path(args.photos) / name
        if not path.exists():
            print(f"{path}: missing", file=sys.stderr)
            return 1
        c0 = time.process_time()
        full = load_photo(path, None)
        decode_ms = 1e3 * (time.process_time() - c0)
        times: dict[str, list[float]] = {k: [] for k in POLICIES}
        ratios: dict[str, list[float]] = {k: [] for k in POLICIES}
        figures: dict[str, str] = {}
        for _ in range(args.runs):
            ref = 0.0
            for key, policy in POLICIES.items():
                c0 = time.process_time()
                det, cfg = detect_photo_lamps(full, camera, DEFAULT_CONFIG, policy)
                dt = time.process_time() - c0
                ref = dt if key == "320" else ref
                times[key].append(1e3 * dt)
                ratios[key].append(dt / ref if ref > 0 else float("nan"))
                h, w = det.mask.shape
                sc = score_photo(det, pl, (w, h), cfg, PhotoEvalSettings(width=w))
                figures[key] = f"w {w:4d} P {sc.precision:.2f} R {sc.recall:.2f}"
        print(f"{name} (decode {decode_ms:.0f} ms CPU)")
        for key in POLICIES:
            print(
                f"  {key:10s} {statistics.median(times[key]):7.1f} ms CPU  "
                f"x{statistics.median(ratios[key]):5.2f}  {figures[key]}"
            )
    print(f"load average after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
