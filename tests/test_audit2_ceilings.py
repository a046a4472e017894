"""Audit 2: ceilings of other buildings (docs/failures.md, "audit 2").

``frontend-eval`` on a ceiling of round downlights only used to exit 1 ("job failed")
with every lamp found: its axis target was checked on no lamp (RMS NaN) and failed.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from lampsam.cli import main
from lampsam.datasets.world import WORLDS_DIR
from lampsam.evaluation.frontend_eval import FrontendMetrics, targets_met


def test_a_target_with_nothing_to_measure_is_left_out() -> None:
    round_only = FrontendMetrics(n_truth_lamps_full=40, n_found=40, n_detections=40,
                                    lamp_recall=1.0, centroid_rms_px=0.05, n_axis=0)
    assert targets_met(round_only) == {"recall>=99%": True, "no_false_lamps": True,
                                       "centroid_rms<=0.3px": True}
    assert "axis not checked" in FrontendMetrics(targets_met={}).summary()
    strips = FrontendMetrics(n_truth_lamps_full=40, n_found=40, lamp_recall=1.0,
                                centroid_rms_px=0.05, n_axis=12, axis_rms_deg=0.9)
    assert targets_met(strips)["axis_rms<=0.5deg"] is False


def test_frontend_eval_on_round_downlights_only_exits_0(tmp_path: Path) -> None:
    world = yaml.safe_load((WORLDS_DIR / "lab.yaml").read_text())
    world["name"] = "downlights"
    world["ceiling"]["lamps"] = [
        {"id": lamp["id"], "shape": "round", "center": lamp["center"], "height": lamp["height"],
         "diameter": 0.2, "brightness": 320} for lamp in world["ceiling"]["lamps"]]
    path = tmp_path / "downlights.yaml"
    path.write_text(yaml.safe_dump(world, sort_keys=False))
    run = tmp_path / "run"
    assert main(["simulate", str(path), "--out", str(run), "--duration", "4", "--seed", "1"]) == 0
    assert main(["frontend-eval", str(run), "--max-frames", "20",
                 "--out", str(tmp_path / "eval")]) == 0
