"""Run ``lampsam slam FILE`` on every file of GTSAM's ``Data/`` folder, as a new user would.

For each top-level file, one run per backend (``isam2``, ``batch``, ``ekf``) and, where the
file has landmark sightings, the same with ``--no-ids``; each run is a subprocess of the CLI
with a time limit. Files longer than ``--max-lines`` are run on a truncated copy in a
temporary folder (the first lines; named in the table). Each run is classified:

- ``works``: exit 0 (the warnings the CLI printed are counted);
- ``clear error``: exit 2 with a one-line ``lampsam slam: error: ...`` message;
- ``TRACEBACK``: exit 1 with ``internal error`` (a defect), or any Python traceback;
- ``timeout`` / ``exit N``: anything else.

Where the known-id batch works and GTSAM reads the file (``gtsam.load2D`` for iSAM text,
``gtsam.readG2o(path, False)`` for ``.g2o``), GTSAM's Levenberg-Marquardt is run on GTSAM's
own graph of the same (possibly truncated) file, loop closures included (lampsam's iSAM2 and
batch use them; until issue #15 they were left out of both), with a tight prior on the
first pose at lampsam's start, starting from lampsam's batch estimate (poses and the
landmarks of ``landmarks.csv``, 6 significant digits). If lampsam builds the same graph and
reached its minimum, LM does not move: the table gives the largest position and heading
change and GTSAM's graph error before and after. This checks the reader against GTSAM's
(covariance layouts, landmark conversions), not the estimator's accuracy. (Started from
GTSAM's own initial landmarks instead, LM stops in a worse local minimum on Victoria Park:
error 2078 against lampsam's 902 on the first 3000 lines.)

Usage (from the worktree's parent, outputs in a temporary folder)::

    PYTHONPATH=.. python scripts/sweep_gtsam_data.py [--max-lines 3000] [--timeout 300]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

BACKENDS = ("isam2", "batch", "ekf")
LANDMARK_TAGS = ("LANDMARK", "LANDMARK2", "BR", "EDGE_SE2_XY")


def data_dir() -> Path:
    """GTSAM's ``Data/`` folder (next to ``victoria_park.txt``)."""
    import gtsam

    return Path(gtsam.findExampleDataFile("victoria_park.txt")).parent


def first_tags(path: Path, n: int = 5000) -> set[str]:
    """The first word of the first ``n`` lines (bytes that are not UTF-8 are replaced)."""
    tags: set[str] = set()
    with path.open("rb") as fh:
        for k, raw in enumerate(fh):
            if k >= n:
                break
            parts = raw.decode("utf-8", "replace").split()
            if parts:
                tags.add(parts[0])
    return tags


def maybe_truncate(path: Path, max_lines: int, tmp: Path) -> tuple[Path, int | None]:
    """``(file to run, lines kept or None)``: a copy of the first ``max_lines`` lines if longer."""
    with path.open("rb") as fh:
        lines = fh.readlines()
    if len(lines) <= max_lines:
        return path, None
    out = tmp / "truncated" / path.name
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(b"".join(lines[:max_lines]))
    return out, max_lines


def run_cli(args: list[str], timeout: float) -> tuple[str, str, int | None]:
    """``(outcome, message, exit code)`` of one ``lampsam`` run."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    try:
        p = subprocess.run([sys.executable, "-m", "lampsam", *args], capture_output=True,
                           text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return "timeout", f"> {timeout:g} s", None
    err = [ln for ln in p.stderr.splitlines() if ln.strip()]
    if "Traceback" in p.stderr or "internal error" in p.stderr:
        msg = next((ln for ln in err if "internal error" in ln), err[-1] if err else "")
        return "TRACEBACK", msg, p.returncode
    if p.returncode == 0:
        n_warn = sum(ln.startswith("WARNING") for ln in err)
        out = p.stdout.strip().splitlines()
        return "works", (f"{n_warn} warning(s); " if n_warn else "") + (out[-1] if out else ""), 0
    if p.returncode == 2 and err and "error:" in err[-1]:
        return "clear error", err[-1], 2
    return f"exit {p.returncode}", err[-1] if err else "", p.returncode


def read_tum_xyyaw(path: Path) -> np.ndarray:
    """(N, 3) ``x, y, yaw`` of a planar TUM file written by lampsam."""
    rows = np.loadtxt(path, comments="#", ndmin=2)
    yaw = 2.0 * np.arctan2(rows[:, 6], rows[:, 7])
    return np.column_stack([rows[:, 1], rows[:, 2], yaw])


def read_landmarks_xy(path: Path) -> dict[int, np.ndarray]:
    """``{id: (x, y)}`` of a ``landmarks.csv`` written by lampsam (pruned ones included)."""
    import csv

    with path.open() as fh:
        return {int(r["id"]): np.array([float(r["x"]), float(r["y"])]) for r in csv.DictReader(fh)}


def landmark_id(key: int) -> int:
    """The file's landmark id of a GTSAM key: ``L(id)`` (``load2D``) or the plain id (g2o)."""
    import gtsam

    sym = gtsam.Symbol(key)
    return int(sym.index()) if chr(sym.chr()) == "l" else int(key)


def compare_with_gtsam(path: Path, traj: np.ndarray, landmarks: dict[int, np.ndarray]) -> str:
    """Largest position / heading difference between lampsam's batch poses and GTSAM's LM,
    and GTSAM's graph error at both (lampsam's at its poses and written landmarks)."""
    import gtsam

    from lampsam.datasets.graph_text import read_graph_text

    glog = read_graph_text(path)
    if path.suffix == ".g2o":
        graph, initial = gtsam.readG2o(str(path), False)
    else:
        graph, initial = gtsam.load2D(str(path))
    pose_keys = set(glog.pose_ids)
    kept = gtsam.NonlinearFactorGraph()
    for k in range(graph.size()):
        f = graph.at(k)
        if f is not None:
            kept.add(f)
    n_sightings = sum(len(ss) for ss in glog.sightings)
    n_gtsam = sum(1 for k in range(kept.size()) if kept.at(k) is not None
                  and not all(key in pose_keys for key in kept.at(k).keys()))
    if n_gtsam != n_sightings:
        return (f"not comparable: GTSAM's reader gives {n_gtsam} landmark factors, the file "
                f"{n_sightings} sightings (GTSAM skips records it does not know, e.g. LANDMARK2)")
    start = traj[0]
    kept.add(gtsam.PriorFactorPose2(glog.pose_ids[0], gtsam.Pose2(*start),
                                    gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    values = gtsam.Values()
    for key, pose in zip(glog.pose_ids, traj, strict=True):
        values.insert(key, gtsam.Pose2(*pose))
    for key in initial.keys():
        if not values.exists(key):  # landmarks: lampsam's estimate, so LM starts at it
            if landmark_id(key) not in landmarks:
                return f"landmark key {key} not in lampsam's landmarks.csv"
            values.insert(key, landmarks[landmark_id(key)])
    missing = [key for key in kept.keyVector() if not values.exists(key)]
    if missing:
        return f"GTSAM's graph has keys lampsam does not ({len(missing)})"
    lm = gtsam.LevenbergMarquardtOptimizer(kept, values, gtsam.LevenbergMarquardtParams()).optimize()
    ref = np.array([[lm.atPose2(key).x(), lm.atPose2(key).y(), lm.atPose2(key).theta()]
                    for key in glog.pose_ids])
    err_ours, err_lm = kept.error(values), kept.error(lm)
    dpos = np.hypot(*(ref[:, :2] - traj[:, :2]).T)
    dyaw = np.abs(np.angle(np.exp(1j * (ref[:, 2] - traj[:, 2]))))
    return (f"max |dp| {dpos.max():.2e} m, max |dtheta| {dyaw.max():.2e} rad over {len(ref)} poses;"
            f" GTSAM graph error {err_ours:.6g} (lampsam) vs {err_lm:.6g} (LM)"
            + (f" ({len(glog.closures)} loop closures in both)" if glog.closures else ""))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-lines", type=int, default=3000, help="truncate longer files (default 3000)")
    ap.add_argument("--timeout", type=float, default=300.0, help="per run, s (default 300)")
    ap.add_argument("--only", nargs="*", default=None, help="file names to run (default all)")
    args = ap.parse_args()
    data = data_dir()
    files = sorted(p for p in data.iterdir() if p.is_file() and not p.name.startswith("."))
    if args.only:
        files = [p for p in files if p.name in args.only]
    with tempfile.TemporaryDirectory(prefix="lampsam_sweep_") as td:
        tmp = Path(td)
        print("| file | run | outcome | message |")
        print("|---|---|---|---|")
        for path in files:
            src, kept = maybe_truncate(path, args.max_lines, tmp)
            name = path.name + (f" (first {kept} lines)" if kept else "")
            tags = first_tags(src)
            has_landmarks = bool(tags & set(LANDMARK_TAGS))
            runs = [(b, False) for b in BACKENDS] + [(b, True) for b in BACKENDS if has_landmarks]
            for backend, no_ids in runs:
                out = tmp / "out" / f"{path.name}_{backend}_{int(no_ids)}"
                cli = ["slam", str(src), "--backend", backend, "--out", str(out)]
                cli += ["--no-ids"] if no_ids else []
                outcome, msg, _ = run_cli(cli, args.timeout)
                label = backend + (" --no-ids" if no_ids else "")
                print(f"| {name} | {label} | {outcome} | {msg.replace('|', '/')} |", flush=True)
                if backend == "batch" and not no_ids and outcome == "works":
                    try:
                        cmp = compare_with_gtsam(src, read_tum_xyyaw(out / "trajectory.tum"),
                                                 read_landmarks_xy(out / "landmarks.csv"))
                    except Exception as exc:  # GTSAM cannot read it: say so
                        cmp = f"GTSAM: {type(exc).__name__}: {exc}"
                    print(f"| {name} | batch vs GTSAM LM | compare | {cmp} |", flush=True)


if __name__ == "__main__":
    main()
