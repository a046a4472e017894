"""The Table-1 experiment's success criterion and report (evaluation/table1*.py, `lampsam table1`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from lampsam.evaluation.table1 import trial_success


def test_trial_success_is_the_papers_criterion() -> None:
    assert trial_success(True, 0.29, math.radians(9.9), 59.0)
    assert not trial_success(False, 0.0, 0.0, 10.0)  # not accepted by the localizer
    assert not trial_success(True, 0.31, 0.0, 10.0)  # 31 cm off
    assert not trial_success(True, 0.0, math.radians(10.5), 10.0)  # 10.5 deg off
    assert not trial_success(True, 0.0, 0.0, 60.5)  # over 60 s


def _row(trial: int, mode: str, ok: bool, err: float) -> dict[str, object]:
    return {"trial": trial, "mode": mode, "success": ok, "claimed_success": True,
            "error_m": err, "error_deg": 1.0, "compute_s": 1.0, "robot_s": 20.0,
            "turn_s": 12.0, "total_s": 21.0, "restarts": 1 - int(ok),
            "compute_after_turn_s": 0.5}  # fmt: skip


def test_cli_table1_report_only_rebuilds_the_table(tmp_path: Path) -> None:
    from lampsam.cli import main

    rows = [_row(0, "proposed", True, 0.05), _row(1, "proposed", False, 2.0),
            _row(0, "ours", True, 0.01), _row(1, "ours", True, 0.03)]  # fmt: skip
    # two workers' line files; a later line for the same pair replaces the earlier one
    (tmp_path / "trials.w0.jsonl").write_text(
        "\n".join(json.dumps(r) for r in rows[:2]) + "\n" + json.dumps(_row(0, "proposed", True, 0.07))
    )
    (tmp_path / "trials.w1.jsonl").write_text("\n".join(json.dumps(r) for r in rows[2:]))
    rc = main(["table1", "--out", str(tmp_path), "--report-only", "--modes", "proposed,ours"])
    assert rc == 0
    md = (tmp_path / "table1.md").read_text()
    line = {ln.split("|")[1].strip(): ln for ln in md.splitlines() if ln.startswith("| p") or
            ln.startswith("| o")}  # fmt: skip
    assert "50 % (1/2)" in line["proposed"] and "| 7.0 |" in line["proposed"]  # mean over successes
    assert "100 % (2/2)" in line["ours"] and "| 2.0 |" in line["ours"]
    assert len(json.loads((tmp_path / "trials.json").read_text())) == 4
    assert (tmp_path / "table1.png").stat().st_size > 10_000


def test_cli_table1_rejects_an_unknown_mode(tmp_path: Path) -> None:
    from lampsam.cli import main

    assert main(["table1", "--out", str(tmp_path), "--report-only", "--modes", "best"]) == 2
