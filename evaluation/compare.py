"""Compare SLAM backends (EKF against smoothing) over runs and Monte Carlo seeds.

``lampsam compare RUN [RUN ...] --backends ekf,isam2,batch --seeds N --out REPORT``:

* ``RUN`` is a run directory, a built-in world name or world YAML (then ``N`` runs
  are simulated with seeds ``0..N-1``: the same world and path, independent
  odometry and image noise), or ``mrclam`` / ``mrclam-gated`` (the shared MRCLAM
  data with known association, or association by the gate alone).
* Every (run, backend) job runs in a fresh process (so its peak memory is its own),
  in parallel, with a progress bar; or, with ``dask``, on a Dask ``distributed``
  cluster (:mod:`lampsam.evaluation.fleet`: the same results; the peak memory is
  then the worker process's so far). A job that fails (indeterminate system,
  unusable input, a crash, a lost worker) is recorded as failed with its reason;
  it is never dropped from the table.
* Metrics (``evaluation.metrics``; trajectory statistics through evo): position
  and heading error without alignment (the start pose is known), RPE per metre,
  map error after association with the truth, pose NEES over time with the
  chi-square 95 % bounds, time per frame, total time, peak memory.

Outputs (written by ``evaluation.compare_report``): ``REPORT/report.md``,
``REPORT/report.html`` (rendered from the Markdown, images embedded),
``REPORT/summary.json`` (every number in the table), ``REPORT/figures/*.png`` and
one directory per job with the backend's own outputs (``trajectory.tum``,
``landmarks.csv``, ``summary.json``) and ``arrays.npz``.
"""

from __future__ import annotations

import json
import logging
import resource
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.errors import LampsamError
from lampsam.evaluation import metrics as M
from lampsam.evaluation.fleet import run_jobs
from lampsam.evaluation.outputs import ensure_dir
from lampsam.interrupt import stop_on_signals
from lampsam.safe_io import atomic_path, write_json_atomic

log = logging.getLogger(__name__)

MRCLAM_NAMES = ("mrclam", "mrclam-gated")
JOB_RESULT = "job_result.json"  #: a finished job's status and metrics, written last


class CompareError(LampsamError):
    """The comparison could not be set up (unknown run, no backends)."""


@dataclass(frozen=True)
class Job:
    """One backend on one run."""

    group: str  # world name or run directory name: rows of the table are (group, backend)
    seed: int
    run_dir: str
    backend: str
    out_dir: str
    frames: str = "auto"
    features: tuple[str, ...] | None = None
    config: SlamConfig | None = None  # None: the defaults


@dataclass
class JobResult:
    """What a job returns to the parent (small and picklable; arrays stay on disk)."""

    job: Job
    status: str
    metrics: dict[str, Any] = field(default_factory=dict)
    arrays: str | None = None  # path of arrays.npz


# --------------------------------------------------------------------------- runs
def _is_world(name: str) -> bool:
    """True for a built-in world name or an existing world YAML file."""
    from lampsam.datasets.world import builtin_worlds

    return name in builtin_worlds() or (name.endswith((".yaml", ".yml")) and Path(name).is_file())


def prepare_runs(
    runs: list[str], seeds: int, out: Path, duration: float | None
) -> list[tuple[str, int, Path]]:
    """Resolve RUN arguments into ``(group, seed, run_dir)``; simulate worlds.

    Args:
        runs: run directories, world names / YAML files, or ``mrclam[-gated]``.
        seeds: Monte Carlo seeds per simulated world.
        out: the report directory (simulated and adapted runs go to ``out/runs``).
        duration: simulated seconds per run (None: the world's whole path).

    Raises:
        CompareError: an argument is none of the above.
    """
    resolved: list[tuple[str, int, Path]] = []
    for name in runs:
        if name in MRCLAM_NAMES:
            from lampsam.datasets.mrclam import write_mrclam_run
            from lampsam.datasets.paths import shared_dataset

            root = shared_dataset("mrclam_ds0")
            if root is None:
                raise CompareError("mrclam: the shared dataset mrclam_ds0 was not found (set LAMPSAM_DATA)")
            run_dir = out / "runs" / name
            if not (run_dir / "odometry.csv").exists():
                kw: dict[str, Any] = {"known_ids": name == "mrclam"}
                if duration is not None:
                    kw["duration"] = duration
                write_mrclam_run(root, run_dir, **kw)
            resolved.append((name, 0, run_dir))
        elif _is_world(name):
            from lampsam.datasets.simulator import simulate_world

            group = Path(name).stem
            for seed in range(seeds):
                run_dir = out / "runs" / f"{group}-seed{seed:02d}"
                if not (run_dir / "meta.yaml").exists():
                    log.info("simulating %s seed %d", group, seed)
                    simulate_world(name, run_dir, seed=seed, duration=duration)
                resolved.append((group, seed, run_dir))
        elif Path(name).is_dir():
            resolved.append((Path(name).name, 0, Path(name)))
        else:
            raise CompareError(f"{name}: not a run directory, a world, or mrclam")
    return resolved


# --------------------------------------------------------------------------- one job
def _truth_landmarks(run_dir: Path, run: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(ids, types, xyz) of the true landmarks, or None."""
    if getattr(run, "landmarks", None) is not None:
        lt = run.landmarks
        types = np.array(["lamp" if str(t).startswith("lamp") else str(t) for t in lt.types])
        return np.asarray(lt.ids), types, np.asarray(lt.xyz, float)
    meta = run_dir / "landmarks_xy.csv"  # written by the MRCLAM adapter, if at all
    if meta.exists():
        arr = np.loadtxt(meta, delimiter=",", skiprows=1, ndmin=2)
        xyz = np.column_stack([arr[:, 1:3], np.full(len(arr), np.nan)])
        return arr[:, 0].astype(int), np.array(["point2"] * len(arr)), xyz
    return None


def _map_error(result: Any, truth: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
               ids_are_true: bool) -> dict[str, Any]:
    """Landmark error on the floor plane, per landmark type.

    Estimated landmarks are associated with true landmarks of the same type: by id
    when the measurements carried the true ids (``ids_are_true``: frames from the
    simulator's truth, or a dataset with known association); otherwise each estimate
    is paired with the nearest true landmark within 0.5 m (a backend's own ids mean
    nothing to the truth).

    Returns:
        ``map_rms_m``/``map_max_m``/``map_associated`` for the headline type (lamps
        for ceiling runs, planar landmarks otherwise), and ``map_<type>_rms_m`` /
        ``map_<type>_associated`` for every type. Corner figures include FAST corners
        on tile lines that have no true counterpart nearby only if one lies within 0.5 m.
    """
    if truth is None or not result.landmarks:
        return {}
    tid, ttype, txyz = truth
    out: dict[str, Any] = {"map_landmarks": len(result.landmarks)}
    kinds = sorted({lm.type for lm in result.landmarks})
    for kind in kinds:
        ests = [lm for lm in result.landmarks if lm.type == kind]
        sel = ttype == kind if kind != "point2" else np.ones(len(tid), bool)
        if not np.any(sel):
            continue
        k_ids, k_xyz = tid[sel], txyz[sel]
        est_ids = np.array([lm.id for lm in ests])
        est_xyz = np.array([np.asarray(lm.position, float) for lm in ests])
        if not ids_are_true:
            d = np.linalg.norm(est_xyz[:, None, :2] - k_xyz[None, :, :2], axis=2)
            nearest = np.argmin(d, axis=1)
            est_ids = np.where(d[np.arange(len(d)), nearest] < 0.5, k_ids[nearest], -1)
        try:
            stats, n = M.map_error(est_ids, est_xyz, k_ids, k_xyz, dims=2)
        except M.MetricsError:
            out[f"map_{kind}_associated"] = 0
            continue
        out[f"map_{kind}_rms_m"] = stats.rms
        out[f"map_{kind}_max_m"] = stats.max
        out[f"map_{kind}_associated"] = n
    headline = "lamp" if "map_lamp_rms_m" in out else "point2" if "map_point2_rms_m" in out else None
    if headline is None and kinds:
        headline = next((k for k in kinds if f"map_{k}_rms_m" in out), None)
    if headline is not None:
        out["map_rms_m"] = out[f"map_{headline}_rms_m"]
        out["map_max_m"] = out[f"map_{headline}_max_m"]
        out["map_associated"] = out[f"map_{headline}_associated"]
        out["map_type"] = headline
    return out


def run_job(job: Job) -> JobResult:
    """Run one backend on one run and compute its metrics (runs in a worker process).

    Writes ``job_result.json`` last (atomically) unless the job was interrupted, so
    that ``compare --resume`` can tell finished jobs (:func:`finished_job`).
    """
    with stop_on_signals():  # SIGINT/SIGTERM in the worker: finish the step, keep the steps
        result = _run_job(job)
    if result.status != "interrupted":
        write_json_atomic(Path(job.out_dir) / JOB_RESULT, {
            "status": result.status, "arrays": result.arrays,
            "metrics": {k: v for k, v in result.metrics.items() if k != "traceback"}})
    return result


def finished_job(job: Job) -> JobResult | None:
    """The result of a job finished by an earlier ``compare`` (for ``--resume``), or None.

    A job is finished when its directory holds ``job_result.json`` (written last,
    atomically, by :func:`run_job`) and, for a successful job, its ``arrays.npz``.
    Interrupted jobs write no ``job_result.json`` and are run again.
    """
    path = Path(job.out_dir) / JOB_RESULT
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        status, arrays, metrics = str(doc["status"]), doc.get("arrays"), dict(doc["metrics"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("%s: unreadable (%s): the job runs again", path, exc)
        return None
    if arrays is not None and not Path(arrays).is_file():
        return None
    return JobResult(job, status, metrics, arrays)


def _run_job(job: Job) -> JobResult:
    from lampsam.backend.slam import run_slam
    from lampsam.datasets.logrun import read_run

    out = Path(job.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    try:
        run = read_run(job.run_dir)
        t0 = time.perf_counter()
        result = run_slam(job.run_dir, job.backend, features=job.features, out=out,
                          config=job.config, frames=job.frames, run=run)
        total = time.perf_counter() - t0
    except LampsamError as exc:
        return JobResult(job, f"failed: {exc}")
    except Exception as exc:  # a crash inside a backend is a failed job, not a lost row
        log.debug("job crashed", exc_info=True)
        return JobResult(job, f"failed: {type(exc).__name__}: {exc}",
                         metrics={"traceback": traceback.format_exc(limit=5)})
    m: dict[str, Any] = {"total_time_s": total, "steps": len(result.times),
                         "keyframes": int(np.sum(result.keyframes))}
    st = np.asarray(result.step_times_s) * 1e3
    kf = st[np.asarray(result.keyframes, bool)] if np.any(result.keyframes) else st
    if kf.size:
        m["frame_ms_median"] = float(np.median(kf))
        m["frame_ms_p95"] = float(np.percentile(kf, 95))
    m["final_optimisation_s"] = float(result.final_time_s)
    arrays: dict[str, FloatArray] = {"t": result.times, "poses": result.poses, "covs": result.pose_covs}
    gt = run.groundtruth
    if gt is not None and len(result.times):
        inside = (result.times >= gt.t[0]) & (result.times <= gt.t[-1])
        t = result.times[inside]
        est = result.poses[inside]
        truth = gt.interpolate(t)
        pos, head = M.pose_errors(est, truth)
        ps, hs = M.error_stats(pos), M.error_stats(np.degrees(head))
        m.update(pos_rms_m=ps.rms, pos_max_m=ps.max, head_rms_deg=hs.rms, head_max_deg=hs.max)
        e = M.coordinate_errors(est, truth)
        nees = M.nees(e, result.pose_covs[inside])
        ns = M.nees_summary(nees, dof=3)
        m.update(nees_mean=ns.mean, nees_inside=ns.fraction_inside, nees_above=ns.fraction_above)
        try:
            m.update(M.evo_ape_rpe(t, est, gt.t, gt.poses))
        except M.MetricsError as exc:
            log.warning("%s: evo metrics skipped: %s", job.run_dir, exc)
        arrays.update(t_err=t, truth=truth, pos_err=pos, head_err=head, nees=nees,
                      gt_xy=gt.poses[:, :2])
    ids_are_true = job.frames == "truth" or (job.frames in ("auto", "rangebearing")
                                             and run.range_bearing is not None
                                             and bool(np.any(run.range_bearing.landmark_id >= 0)))
    truth_lm = _truth_landmarks(Path(job.run_dir), run)
    m.update(_map_error(result, truth_lm, ids_are_true))
    if result.landmarks:
        arrays["lm_xy"] = np.array([lm.position[:2] for lm in result.landmarks], float)
        arrays["lm_cov"] = np.array([np.asarray(lm.cov)[:2, :2] for lm in result.landmarks], float)
        arrays["lm_type"] = np.array([lm.type for lm in result.landmarks])
    if truth_lm is not None:
        arrays["true_lm_xy"] = truth_lm[2][:, :2]
        arrays["true_lm_type"] = truth_lm[1]
    m["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    with atomic_path(out / "arrays.npz") as tmp:
        np.savez_compressed(tmp, **arrays)  # type: ignore[arg-type]
    return JobResult(job, result.status, m, str(out / "arrays.npz"))


# --------------------------------------------------------------------------- aggregate
TABLE_COLUMNS: list[tuple[str, str, str]] = [
    # key, header, format
    ("pos_rms_m", "pos RMS [m]", "{:.3f}"),
    ("pos_max_m", "pos max [m]", "{:.3f}"),
    ("head_rms_deg", "head RMS [deg]", "{:.2f}"),
    ("head_max_deg", "head max [deg]", "{:.2f}"),
    ("rpe_trans_per_m", "RPE [m/m]", "{:.4f}"),
    ("map_rms_m", "map RMS [m] (lamps)", "{:.3f}"),
    ("nees_mean", "NEES (3 ideal)", "{:.2f}"),
    ("nees_inside", "in 95% bound", "{:.0%}"),
    ("frame_ms_median", "frame median [ms]", "{:.1f}"),
    ("frame_ms_p95", "frame p95 [ms]", "{:.1f}"),
    ("total_time_s", "total [s]", "{:.1f}"),
    ("peak_rss_mb", "peak mem [MB]", "{:.0f}"),
]


def aggregate(results: list[JobResult]) -> list[dict[str, Any]]:
    """One row per (group, backend): means over seeds; failures counted, never dropped.

    ``pos_max_m`` and ``head_max_deg`` are maxima over seeds; NEES is averaged over
    seeds step by step (runs of one world share their time stamps) and summarised
    with the chi-square bounds of that number of runs.
    """
    rows: list[dict[str, Any]] = []
    keys = sorted({(r.job.group, r.job.backend) for r in results},
                  key=lambda k: (k[0], ["ekf", "isam2", "batch"].index(k[1])
                                 if k[1] in ("ekf", "isam2", "batch") else 9))
    for group, backend in keys:
        rs = [r for r in results if r.job.group == group and r.job.backend == backend]
        ok = [r for r in rs if not r.status.startswith("failed")]
        row: dict[str, Any] = {"run": group, "backend": backend, "seeds": len(rs),
                               "failed": len(rs) - len(ok),
                               "failures": [r.status for r in rs if r.status.startswith("failed")]}
        for key, _, _ in TABLE_COLUMNS:
            vals = [r.metrics[key] for r in ok if key in r.metrics and np.isfinite(r.metrics[key])]
            if vals:
                row[key] = float(np.max(vals) if key.endswith("_max_m") or key.endswith("max_deg")
                                 else np.mean(vals))
        if ok:
            pos = [r.metrics["pos_rms_m"] for r in ok if "pos_rms_m" in r.metrics]
            if pos:
                row["pos_rms_per_seed"] = pos
        nees_runs = []
        for r in ok:
            if r.arrays and Path(r.arrays).exists():
                with np.load(r.arrays) as z:
                    if "nees" in z:
                        nees_runs.append(z["nees"])
        if nees_runs:
            n = min(len(x) for x in nees_runs)
            ns = M.nees_summary(np.array([x[:n] for x in nees_runs]), dof=3)
            row.update(nees_mean=ns.mean, nees_inside=ns.fraction_inside,
                       nees_bounds=[ns.lower, ns.upper], nees_overconfident=ns.overconfident,
                       nees_underconfident=ns.underconfident,
                       nees_mean_bounds=[ns.mean_lower, ns.mean_upper])
        rows.append(row)
    return rows


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """The comparison table in Markdown (failed seeds are counted in their own column)."""
    head = ["run", "backend", "seeds ok"] + [h for _, h, _ in TABLE_COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        cells = [row["run"], row["backend"], f"{row['seeds'] - row['failed']}/{row['seeds']}"]
        for key, _, fmt in TABLE_COLUMNS:
            v = row.get(key)
            cells.append(fmt.format(v) if v is not None else "–")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- driver
def _failed_job(job: Job, reason: str) -> JobResult:
    """The result of a job whose worker raised or died."""
    return JobResult(job, reason)


def compare(
    runs: list[str],
    backends: tuple[str, ...] = ("ekf", "isam2", "batch"),
    seeds: int = 1,
    out: str | Path = "out/compare",
    workers: int = 2,
    frames: str = "auto",
    features: tuple[str, ...] | None = None,
    duration: float | None = None,
    progress: bool = True,
    config: SlamConfig | None = None,
    resume: bool = False,
    dask: str | None = None,
) -> list[dict[str, Any]]:
    """Run every backend on every run; write the report; return the table rows.

    Args:
        runs: see the module docstring.
        backends: subset of ``ekf, isam2, batch``.
        seeds: Monte Carlo seeds per simulated world.
        out: report directory.
        workers: parallel processes.
        frames: measurement source for every job (``auto``, ``images``, ``truth``).
        features: ceiling features (None: the backend default).
        duration: simulated seconds per world run (None: the whole path).
        progress: show a progress bar (tqdm, on stderr).
        config: the SLAM configuration of every job (None: the defaults).
        resume: skip the jobs an earlier run into ``out`` finished (:func:`finished_job`).
        dask: None (local process pool), ``"local"`` (a Dask ``LocalCluster``) or the
            address of a Dask scheduler (:mod:`lampsam.evaluation.fleet`).

    On a stop request (SIGINT, SIGTERM) the report of the jobs finished so far is
    written, naming the unfinished ones.

    Returns:
        The aggregated rows (as in ``summary.json``).
    """
    from lampsam.backend.slam import BACKENDS

    bad = [b for b in backends if b not in BACKENDS]
    if not backends or bad:
        raise CompareError(f"backends must be a non-empty subset of {', '.join(BACKENDS)}; got {bad or backends}")
    if seeds < 1:
        raise CompareError("--seeds must be at least 1")
    out = Path(out)
    ensure_dir(out, CompareError)
    t_start = time.perf_counter()
    resolved = prepare_runs(runs, seeds, out, duration)
    jobs = [
        Job(group, seed, str(run_dir), b, str(out / "jobs" / f"{run_dir.name}-{b}"), frames, features,
            config)
        for group, seed, run_dir in resolved
        for b in backends
    ]
    results: list[JobResult] = []
    todo = jobs
    if resume:
        done = [r for r in (finished_job(j) for j in jobs) if r is not None]
        results.extend(done)
        finished_dirs = {r.job.out_dir for r in done}
        todo = [j for j in jobs if j.out_dir not in finished_dirs]
        log.warning("--resume: %d of %d jobs already finished, %d to run",
                    len(done), len(jobs), len(todo))
    ran, unfinished = run_jobs(run_job, todo, _failed_job, workers=workers, dask=dask,
                               progress=progress, desc="compare",
                               interrupted=lambda r: r.status == "interrupted")
    results += [r for r in ran if r.status != "interrupted"]
    results.sort(key=lambda r: (r.job.group, r.job.seed, r.job.backend))
    rows = aggregate(results)
    from lampsam.evaluation.compare_plots import make_figures
    from lampsam.evaluation.compare_report import write_report

    figures = make_figures(out / "figures", results)
    write_report(out, rows, results, figures, time.perf_counter() - t_start, unfinished)
    if unfinished:
        log.warning("interrupted: report of the %d finished jobs written to %s; %d jobs not "
                    "finished (rerun with --resume to run only those)",
                    len(results), out, len(unfinished))
    return rows


