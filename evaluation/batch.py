"""Offline optimisation of many logs: one result folder per run and a summary.

``lampsam batch RUN [RUN ...] --out DIR [--backend batch] [--dask ADDRESS|local]``:
every run directory is optimised by one backend (by default ``batch``: full
Levenberg-Marquardt over the whole log) in its own job, on a local process pool or
a Dask cluster (:mod:`lampsam.evaluation.fleet`). Outputs:

- ``DIR/<run name>/``: the backend's ``trajectory.tum``, ``landmarks.csv`` and
  ``summary.json`` (:func:`lampsam.backend.slam.write_results`); two runs with the
  same folder name get ``-2``, ``-3``... suffixes in input order.
- A stop request (SIGINT/SIGTERM) cancels the runs not started: their rows say
  ``not run: interrupted``; the summary is still written.
- ``DIR/summary.json`` (one row per run plus how it was run) and ``DIR/summary.csv``
  (the rows). A run that fails (unreadable, no frames, indeterminate system, a crash,
  a lost worker) is a row with ``status = "failed: <reason>"``, never dropped.
"""

from __future__ import annotations

import csv
import json
import logging
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lampsam.backend.config import SlamConfig
from lampsam.errors import LampsamError
from lampsam.evaluation.fleet import run_jobs
from lampsam.evaluation.outputs import ensure_dir
from lampsam.safe_io import atomic_path, write_text_atomic

log = logging.getLogger(__name__)

#: Columns of ``summary.csv`` and of the printed table, in order.
COLUMNS = ("run", "backend", "status", "steps", "keyframes", "landmarks", "pos_rms_m",
           "pos_max_m", "head_rms_deg", "frame_ms_median", "frame_ms_p95",
           "final_optimisation_s", "total_time_s", "out")


class BatchError(LampsamError):
    """The batch could not be set up (no runs, unknown backend, unusable output folder)."""


@dataclass(frozen=True)
class BatchJob:
    """One backend over one run (picklable: sent to the workers)."""

    name: str  # the result folder's name (unique in the batch)
    run_dir: str
    out_dir: str
    backend: str = "batch"
    frames: str = "auto"
    features: tuple[str, ...] | None = None
    config: SlamConfig | None = None


@dataclass
class BatchResult:
    """What a job returns (small; the trajectory and map stay in ``job.out_dir``)."""

    job: BatchJob
    status: str
    summary: dict[str, Any] = field(default_factory=dict)


def batch_job(job: BatchJob) -> BatchResult:
    """Run one backend over one run and write its folder (runs in a worker)."""
    from lampsam.backend.slam import run_slam, summary
    from lampsam.datasets.logrun import read_run

    try:
        run = read_run(job.run_dir)
        result = run_slam(job.run_dir, job.backend, job.features, job.out_dir, job.config,
                          frames=job.frames, run=run)
    except LampsamError as exc:
        return BatchResult(job, f"failed: {exc}")
    except Exception as exc:  # a crash inside a backend is a failed row, not a lost one
        log.debug("batch job crashed", exc_info=True)
        return BatchResult(job, f"failed: {type(exc).__name__}: {exc}",
                           {"traceback": traceback.format_exc(limit=5)})
    return BatchResult(job, result.status, summary(result, run.groundtruth))


def _failed(job: BatchJob, reason: str) -> BatchResult:
    return BatchResult(job, reason)


def summary_row(res: BatchResult) -> dict[str, Any]:
    """One flat row of the summary (:data:`COLUMNS`; absent figures are None)."""
    s = res.summary
    err = s.get("error") or {}
    per_frame = s.get("time_per_frame_ms") or {}
    return {
        "run": res.job.name, "backend": res.job.backend, "status": res.status,
        "steps": s.get("steps"), "keyframes": s.get("keyframes"), "landmarks": s.get("landmarks"),
        "pos_rms_m": err.get("position_rms_m"), "pos_max_m": err.get("position_max_m"),
        "head_rms_deg": err.get("heading_rms_deg"),
        "frame_ms_median": per_frame.get("median"), "frame_ms_p95": per_frame.get("p95"),
        "final_optimisation_s": s.get("final_optimisation_s"),
        "total_time_s": s.get("total_time_s"), "out": res.job.out_dir,
        "run_dir": res.job.run_dir,
    }


def folder_names(runs: list[str]) -> list[str]:
    """Unique result-folder names: each run's folder name, ``-2``, ``-3``... on repeats."""
    seen: dict[str, int] = {}
    names = []
    for run in runs:
        base = Path(run).resolve().name or "run"
        seen[base] = seen.get(base, 0) + 1
        names.append(base if seen[base] == 1 else f"{base}-{seen[base]}")
    return names


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """The summary rows as a Markdown table (numbers rounded for reading)."""
    cols = [c for c in COLUMNS if c != "out"]

    def fmt(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def batch(
    runs: list[str],
    out: str | Path,
    backend: str = "batch",
    workers: int = 2,
    dask: str | None = None,
    progress: bool = True,
    config: SlamConfig | None = None,
    frames: str = "auto",
    features: tuple[str, ...] | None = None,
) -> list[dict[str, Any]]:
    """Optimise every run; write one folder per run and the summary; return the rows.

    Args:
        runs: run directories.
        out: the output directory (created).
        backend: ``batch`` (default), ``isam2`` or ``ekf``.
        workers: parallel processes (local pool, or the workers of ``dask="local"``).
        dask: None (local process pool), ``"local"`` or a Dask scheduler address.
        progress: show a progress bar on stderr.
        config: SLAM configuration of every run (None: the defaults).
        frames: measurement source (see :func:`lampsam.backend.slam.make_frames`).
        features: ceiling features (None: the config's).

    Returns:
        One row per run in input order (:func:`summary_row`).

    Raises:
        BatchError: no runs, an unknown backend, or an unusable output folder.
        lampsam.evaluation.fleet.FleetError: the Dask engine cannot be set up.
    """
    from lampsam.backend.slam import BACKENDS

    if not runs:
        raise BatchError("give at least one run directory")
    if backend not in BACKENDS:
        raise BatchError(f"unknown backend {backend!r}; choose from {', '.join(BACKENDS)}")
    out = Path(out)
    ensure_dir(out, BatchError)
    t0 = time.perf_counter()
    jobs = [BatchJob(name, str(run), str(out / name), backend, frames, features, config)
            for name, run in zip(folder_names(runs), runs, strict=True)]
    results, unfinished = run_jobs(batch_job, jobs, _failed, workers=workers, dask=dask,
                                   progress=progress, desc="batch")
    by_name = {r.job.name: r for r in results}
    for job in unfinished:  # cancelled by a stop request: a row saying so
        by_name.setdefault(job.name, BatchResult(job, "not run: interrupted"))
    rows = [summary_row(by_name[job.name]) for job in jobs]
    engine = f"dask {dask}" if dask else f"local process pool ({max(1, workers)} processes)"
    doc = {"engine": engine, "elapsed_s": time.perf_counter() - t0, "backend": backend,
           "failed": sum(r["status"] != "ok" for r in rows), "runs": rows}
    write_text_atomic(out / "summary.json", json.dumps(doc, indent=2))
    with atomic_path(out / "summary.csv") as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=[*COLUMNS, "run_dir"])
        writer.writeheader()
        writer.writerows(rows)
    return rows
