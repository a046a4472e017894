"""The sensor rig of a logged run (``rig.yaml``): ceiling camera and wheel odometry.

``rig.yaml`` has two sections, ``camera`` (:class:`~lampsam.datasets.camera.CameraModel`
fields, or ``hfov_deg`` instead of ``fx, fy, cx, cy``) and ``odometry``
(:class:`OdometryModel` fields); see ``docs/log-format.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from lampsam.datasets.camera import CameraModel
from lampsam.datasets.textio import read_yaml
from lampsam.errors import DatasetError


@dataclass(frozen=True)
class OdometryModel:
    """Differential-drive wheel odometry (paper 1, eqs. 13-15).

    Attributes:
        wheel_base: distance between the wheels ``b``, m (default 0.4).
        k_r: right-wheel slip constant, m: ``var(ds_r) = k_r |ds_r|`` (eq. 15; default 2e-5).
        k_l: left-wheel slip constant, m (default 2e-5).
    """

    wheel_base: float = 0.4
    k_r: float = 2e-5
    k_l: float = 2e-5

    def __post_init__(self) -> None:
        """Validate (ValueError on non-positive base or negative constants)."""
        if not (self.wheel_base > 0 and self.k_r >= 0 and self.k_l >= 0):
            raise ValueError("wheel_base must be > 0 and k_r, k_l >= 0")

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python mapping for YAML."""
        return {
            "wheel_base": float(self.wheel_base),
            "k_r": float(self.k_r),
            "k_l": float(self.k_l),
        }


@dataclass(frozen=True)
class Rig:
    """The sensor rig of a run: the ceiling camera and the wheel odometry.

    Attributes:
        camera: the upward camera.
        odometry: the wheel-odometry model.
    """

    camera: CameraModel = field(default_factory=CameraModel)
    odometry: OdometryModel = field(default_factory=OdometryModel)

    @classmethod
    def from_dict(cls, data: Any, path: Path | None = None) -> Rig:
        """Build from the mapping of ``rig.yaml`` (sections ``camera``, ``odometry``).

        The camera may give ``hfov_deg`` instead of ``fx, fy, cx, cy``.

        Raises:
            DatasetError: a missing section, unknown key or bad value (naming ``path``).
        """
        if not isinstance(data, dict):
            raise DatasetError("rig must be a mapping with 'camera' and 'odometry'", path)
        try:
            cam = dict(data.get("camera") or {})
            odo = dict(data.get("odometry") or {})
            if "hfov_deg" in cam:
                camera = CameraModel.from_fov(**cam)
            else:
                camera = CameraModel(**cam)
            odometry = OdometryModel(**odo)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"invalid rig: {exc}", path) from exc
        return cls(camera=camera, odometry=odometry)

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python mapping for YAML."""
        return {"camera": self.camera.to_dict(), "odometry": self.odometry.to_dict()}

    @classmethod
    def from_yaml(cls, path: str | Path) -> Rig:
        """Read ``rig.yaml``.

        Raises:
            DatasetError: missing file, invalid YAML or invalid rig.
        """
        path = Path(path)
        return cls.from_dict(read_yaml(path), path)

    def to_yaml(self, path: str | Path) -> None:
        """Write ``rig.yaml``."""
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))
