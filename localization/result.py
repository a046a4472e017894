"""What a global localization returns and writes (``OUT/result.json``)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray


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

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (lists instead of arrays)."""
        return {
            "success": self.success,
            "pose": [float(v) for v in self.pose],
            "covariance": np.asarray(self.covariance).tolist(),
            "mode": self.mode,
            "restarts": self.restarts,
            "robot_time_s": self.robot_time,
            "compute_time_s": self.compute_time,
            "attempts": [asdict(a) for a in self.attempts],
        }


def write_result(result: LocalizationResult, out_dir: str | Path) -> Path:
    """Write ``out_dir/result.json``; returns its path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "result.json"
    path.write_text(json.dumps(result.to_json(), indent=2))
    return path


