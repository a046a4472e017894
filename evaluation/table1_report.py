"""The Table-1 report: the Markdown table, the figure and the collected trial records.

Reads the JSON-lines records of :mod:`lampsam.evaluation.table1` and writes
``trials.json``, ``table1.md`` and ``table1.png``
(:func:`lampsam.evaluation.table1_plots.save_table1_figure`), beside the paper's
figures (paper 2, Table 1; DESIGN.md sec. 2).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lampsam.evaluation.table1_plots import save_table1_figure
from lampsam.safe_io import read_json_lines, write_text_atomic

PAPER = {  # paper 2, Table 1 (DESIGN.md sec. 2): success %, localisation time s, cm, deg
    "grid_only": (68.0, 41.7, 13.4, 9.2),
    "no_ceiling": (82.0, 5.2, 12.6, 8.7),
    "proposed": (98.0, 10.4 + 12.3, 12.0, 8.4),
}


def table(rows: list[dict[str, object]], modes: Sequence[str]) -> str:
    """The Markdown table: success, times (means; compute after the turn also median), errors.

    Errors are means over the successful trials (as the paper's); times and
    restarts over all trials.
    """
    lines = [
        "| configuration | trials | success | compute after turn (s), mean / median "
        "| compute total (s) | robot time (s) (turning) | localisation time (s) "
        "| position error (cm) | heading error (deg) | restarts | paper: success, time, error |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def vals(key: str, sel: list[dict[str, object]]) -> np.ndarray:
        return np.array([float(x[key]) for x in sel])  # type: ignore[arg-type]

    def mean(key: str, sel: list[dict[str, object]]) -> float:
        v = vals(key, sel)
        return float(np.mean(v)) if len(v) else float("nan")

    for mode in modes:
        r = [x for x in rows if x["mode"] == mode]
        if not r:
            continue
        ok = [x for x in r if x["success"]]
        after = vals("compute_after_turn_s", r)
        paper = PAPER.get(mode)
        ptxt = (
            "-" if paper is None
            else f"{paper[0]:.0f} %, {paper[1]:.1f} s, {paper[2]:.1f} cm / {paper[3]:.1f} deg"
        )  # fmt: skip
        lines.append(
            f"| {mode} | {len(r)} | {100.0 * len(ok) / len(r):.0f} % ({len(ok)}/{len(r)}) "
            f"| {np.mean(after):.2f} / {np.median(after):.2f} "
            f"| {mean('compute_s', r):.1f} "
            f"| {mean('robot_s', r):.1f} ({mean('turn_s', r):.1f}) | {mean('total_s', r):.1f} "
            f"| {100 * mean('error_m', ok):.1f} | {mean('error_deg', ok):.1f} "
            f"| {mean('restarts', r):.2f} | {ptxt} |"
        )
    return "\n".join(lines)


def answers_table(rows: list[dict[str, object]], modes: Sequence[str]) -> str:
    """The three answers per configuration: localized (right / wrong pose), ambiguous, failed.

    Right = within 30 cm and 10 deg of the truth (no time limit). Rows written
    before the answers existed are left out.
    """
    lines = ["| configuration | trials | localized | right | wrong_accepted | ambiguous | failed |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for mode in modes:
        r = [x for x in rows if x["mode"] == mode and "status" in x]
        if not r:
            continue
        loc = [x for x in r if x["status"] == "localized"]
        right = sum(bool(x["correct_pose"]) for x in loc)
        lines.append(
            f"| {mode} | {len(r)} | {len(loc)} | {right} | {len(loc) - right} "
            f"| {sum(x['status'] == 'ambiguous' for x in r)} "
            f"| {sum(x['status'] == 'failed' for x in r)} |"
        )
    return "\n".join(lines)


def write_report(rows: list[dict[str, object]], modes: Sequence[str], out: Path) -> str:
    """``OUT/trials.json``, ``OUT/table1.md`` and ``OUT/table1.png`` from the finished rows."""
    rows = sorted(rows, key=lambda x: (int(str(x["trial"])), str(x["mode"])))
    write_text_atomic(out / "trials.json", json.dumps(rows, indent=1))
    md = table(rows, modes) + "\n\n" + answers_table(rows, modes)
    write_text_atomic(out / "table1.md", md + "\n")
    save_table1_figure(rows, list(modes), out / "table1.png",
                       {k: v[0] for k, v in PAPER.items()})  # fmt: skip
    return md


def read_rows(out: Path) -> list[dict[str, object]]:
    """All rows of the per-worker line files ``OUT/trials.w*.jsonl`` (last one per pair wins)."""
    rows: dict[tuple[int, str], dict[str, object]] = {}
    for f in sorted(out.glob("trials.w*.jsonl")):
        for r in read_json_lines(f):
            rows[(int(str(r["trial"])), str(r["mode"]))] = r
    return list(rows.values())
