"""The demo job (``lampsam demo`` / ``make demo``): simulate the lab, show the truth.

For now: simulate a short run of the built-in ``lab`` world into ``out/run`` and
write a contact sheet of its frames with the true lamp and corner projections
(``out/contact_sheet.png``). Later stages extend this with SLAM and reports.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from lampsam.datasets.simulator import simulate_world
from lampsam.evaluation.contact_sheet import write_contact_sheet

log = logging.getLogger(__name__)

DEMO_WORLD = "lab"
DEMO_SEED = 0
DEMO_DURATION = 40.0
"""Seconds of the lab path simulated by the demo (the whole path is about 3 minutes)."""


@dataclass(frozen=True)
class DemoResult:
    """What the demo wrote.

    Attributes:
        out: the demo's output directory.
        run: the simulated run directory.
        contact_sheet: the contact-sheet PNG.
    """

    out: Path
    run: Path
    contact_sheet: Path


def run_demo(out: Path, duration: float = DEMO_DURATION) -> DemoResult:
    """Simulate a short ``lab`` run into ``out/run`` and write ``out/contact_sheet.png``.

    Args:
        out: output directory (created).
        duration: seconds of the lab path to simulate.

    Returns:
        The paths written.
    """
    out = Path(out)
    run = simulate_world(DEMO_WORLD, out / "run", seed=DEMO_SEED, duration=duration)
    sheet = write_contact_sheet(run, out / "contact_sheet.png")
    log.info("demo: run in %s, contact sheet %s", run, sheet)
    return DemoResult(out=out, run=run, contact_sheet=sheet)
