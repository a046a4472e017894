"""The demo job (``lampsam demo`` / ``make demo``): the main job on the built-in world.

1. Simulate a short run of the built-in ``lab`` world into ``OUT/lab`` (ceiling
   images rendered from geometry, noisy wheel odometry, ground truth).
2. Write a contact sheet of its frames with the true lamp and corner projections
   (``OUT/contact_sheet.png``).
3. Run ceiling SLAM with the EKF, iSAM2 and batch backends on the frontend's
   detections in the images, and compare them (``OUT/compare/report.md``,
   ``report.html``, ``summary.json``, ``figures/``).
4. When rerun-sdk is installed (``lampsam[viz]``), record the EKF run in Rerun
   (``OUT/live.rrd``; open with ``rerun OUT/live.rrd``): the EKF is the backend whose
   map exists at every step, so the recording shows the map and the image
   associations as they grow.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lampsam.datasets.simulator import simulate_world
from lampsam.evaluation.compare import compare
from lampsam.evaluation.contact_sheet import write_contact_sheet

log = logging.getLogger(__name__)

DEMO_WORLD = "lab"
DEMO_SEED = 0
DEMO_DURATION = 40.0
"""Seconds of the lab path simulated by the demo (the whole path is about 3 minutes)."""
DEMO_FEATURES: tuple[str, ...] = ("lamps", "corners")
"""Ceiling features the demo's SLAM uses: lamps and FAST corners, as in paper 1."""


@dataclass(frozen=True)
class DemoResult:
    """What the demo wrote.

    Attributes:
        out: the demo's output directory.
        run: the simulated run directory.
        contact_sheet: the contact-sheet PNG.
        report: the comparison report (Markdown; HTML beside it).
        rows: the comparison table rows (as in ``summary.json``).
        recording: the Rerun recording of the EKF run, or None (rerun-sdk absent).
    """

    out: Path
    run: Path
    contact_sheet: Path
    report: Path
    rows: list[dict[str, Any]]
    recording: Path | None = None


def run_demo(out: Path, duration: float = DEMO_DURATION, workers: int = 2,
             progress: bool = True) -> DemoResult:
    """Simulate a short ``lab`` run, draw its truth, and compare the three backends on it.

    Args:
        out: output directory (created).
        duration: seconds of the lab path to simulate.
        workers: parallel processes for the comparison.
        progress: show the comparison's progress bar.

    Returns:
        The paths written and the comparison rows.
    """
    out = Path(out)
    run = simulate_world(DEMO_WORLD, out / DEMO_WORLD, seed=DEMO_SEED, duration=duration)
    sheet = write_contact_sheet(run, out / "contact_sheet.png")
    log.info("demo: run in %s, contact sheet %s", run, sheet)
    rows = compare([str(run)], backends=("ekf", "isam2", "batch"), seeds=1,
                   out=out / "compare", workers=workers, frames="images",
                   features=DEMO_FEATURES, progress=progress)
    recording = record_live(run, out / "live.rrd")
    return DemoResult(out=out, run=run, contact_sheet=sheet, report=out / "compare" / "report.md",
                      rows=rows, recording=recording)


def record_live(run_dir: Path, rrd: Path, backend: str = "ekf") -> Path | None:
    """Run ``backend`` on the demo run once more with the Rerun live view saving ``rrd``.

    Returns:
        ``rrd``, or None when rerun-sdk is not installed (logged, not an error).
    """
    import importlib.util

    if importlib.util.find_spec("rerun") is None:
        log.info("demo: rerun-sdk not installed (lampsam[viz]): no live recording")
        return None
    from lampsam.backend.slam import run_slam
    from lampsam.datasets.logrun import read_run
    from lampsam.evaluation.live import live_view

    run = read_run(run_dir)
    with live_view(str(rrd), f"demo {backend} {run_dir.name}", run=run):
        run_slam(run_dir, backend, DEMO_FEATURES, None, frames="images", run=run)
    return rrd
