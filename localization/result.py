"""What a global localization returns and writes (``OUT/result.json``).

Every run ends with one of three answers (:data:`Status`): ``localized`` (a pose
one would stake the robot on: verified, with its covariance and the evidence),
``ambiguous`` (the candidate modes that could not be told apart, e.g. a
half-turn twin under a symmetric ceiling) or ``failed``. The JSON is strict
(no NaN: missing numbers are ``null``).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.safe_io import write_text_atomic

#: The three answers of a localization.
Status = Literal["localized", "ambiguous", "failed"]

#: The paper's success bounds (paper 2, Table 1): metres, radians.
SUCCESS_XY, SUCCESS_THETA = 0.30, math.radians(10.0)


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (strict JSON), arrays as lists."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclass(frozen=True)
class AttemptRecord:
    """One try (turn, filter, verification).

    Attributes:
        n_candidates: candidates found during the turn.
        filter_updates: measurement updates until convergence (or the limit).
        converged: the particle spread fell below the bound.
        verdict: the verifier's final verdict (``accepted`` without verification).
        r_loc: ``R_loc`` at the end (NaN for the sequential verifier / none).
        verify_distance: distance driven while verifying (m).
        pose: (3,) the estimate at the end of the attempt.
    """

    n_candidates: int
    filter_updates: int
    converged: bool
    verdict: str
    r_loc: float
    verify_distance: float
    pose: list[float]


@dataclass(frozen=True)
class LocalizationResult:
    """What ``OUT/result.json`` holds.

    Attributes:
        success: the last attempt was accepted.
        pose: (3,) ``world_T_body`` at the end (m, m, rad), in the world frame.
        covariance: (3, 3) particle covariance of the pose (heading wrapped).
        mode: the configuration's name.
        restarts: attempts minus one.
        robot_time: seconds of robot time (turning + driving), by stage.
        compute_time: seconds of computation, by stage.
        attempts: one record per attempt.
        odom: (3,) the odometry reading that goes with ``pose`` (to re-check
            or track it later).
        status: the answer (:data:`Status`): ``localized`` when ``success``.
        modes: (M, 3) the poses that could not be told apart when ``ambiguous``.
        evidence: what the answer rests on (verifier, ``R_loc``, margins).
    """

    success: bool
    pose: FloatArray
    covariance: FloatArray
    mode: str
    restarts: int
    robot_time: dict[str, float]
    compute_time: dict[str, float]
    attempts: list[AttemptRecord]
    odom: FloatArray = field(default_factory=lambda: np.zeros(3))
    status: Status = "failed"
    modes: list[list[float]] = field(default_factory=list)
    evidence: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (lists instead of arrays, null instead of NaN)."""
        return json_safe({
            "status": self.status,
            "success": self.success,
            "pose": [float(v) for v in self.pose],
            "covariance": np.asarray(self.covariance).tolist(),
            "mode": self.mode,
            "restarts": self.restarts,
            "robot_time_s": self.robot_time,
            "compute_time_s": self.compute_time,
            "attempts": [asdict(a) for a in self.attempts],
            "modes": self.modes,
            "evidence": self.evidence,
        })  # fmt: skip


def write_result(
    result: LocalizationResult, out_dir: str | Path, extra: dict[str, Any] | None = None
) -> Path:
    """Write ``out_dir/result.json`` (the result, plus ``extra`` keys); returns its path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "result.json"
    doc = result.to_json() | json_safe(extra or {})
    write_text_atomic(path, json.dumps(doc, indent=2, allow_nan=False))
    return path


def is_correct(pose: FloatArray, truth: FloatArray) -> bool:
    """Within the paper's bounds (30 cm, 10 deg) of the true pose."""
    d = np.asarray(pose, dtype=float) - np.asarray(truth, dtype=float)
    dth = abs(math.remainder(float(d[2]), 2 * math.pi))
    return bool(math.hypot(d[0], d[1]) <= SUCCESS_XY and dth <= SUCCESS_THETA)


def summarize(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """The summary of trials, each a dict with ``status``, ``correct`` (bool or None) and times.

    ``correct`` counts localized trials within the paper's bounds of the truth;
    ``wrong_accepted`` the localized ones outside them (None without truth);
    ``success_rate = correct / trials``.
    """
    n = len(trials)
    scored = all(t.get("correct") is not None for t in trials)
    loc = [t for t in trials if t["status"] == "localized"]
    correct = sum(bool(t.get("correct")) for t in loc) if scored else None
    comp = [float(t.get("compute_s", 0.0)) for t in trials]
    robot = [float(t.get("robot_s", 0.0)) for t in trials]
    return json_safe({
        "trials": n,
        "localized": len(loc),
        "correct": correct,
        "wrong_accepted": None if correct is None else len(loc) - correct,
        "ambiguous": sum(t["status"] == "ambiguous" for t in trials),
        "failed": sum(t["status"] == "failed" for t in trials),
        "success_rate": None if correct is None or n == 0 else correct / n,
        "compute_s_mean": float(np.mean(comp)) if n else None,
        "compute_s_max": float(np.max(comp)) if n else None,
        "robot_s_mean": float(np.mean(robot)) if n else None,
    })  # fmt: skip


