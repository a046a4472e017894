"""The sensor rig of a logged run (``rig.yaml``): ceiling camera and wheel odometry.

``rig.yaml`` has two sections, ``camera`` (:class:`~lampsam.datasets.camera.CameraModel`
fields; or ``hfov_deg`` instead of ``fx, fy, cx, cy``; or ``calibration``, a ROS /
OpenCV calibration file) and ``odometry`` (:class:`OdometryModel` fields); see
``docs/log-format.md``. A run's ``rig.yaml`` is read strictly: every key of
:data:`REQUIRED` must be there (a rig that silently ran on the simulator's wheel
base is worse than an error), only :data:`CAMERA_DEFAULTS` have defaults, and
unknown keys or wrong types are errors naming the key and the file (types and
unknown keys through the project's strict loader, :mod:`lampsam.config_loader`;
presence through :data:`REQUIRED`, since every field has a default for the
simulator's world files).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import yaml

from lampsam.config_loader import ConfigError, from_mapping
from lampsam.datasets.camera import CameraModel
from lampsam.datasets.odometry import Pose2OdometryModel
from lampsam.datasets.textio import read_yaml
from lampsam.errors import DatasetError
from lampsam.safe_io import write_text_atomic


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
        pose2_odometry: optional section ``pose2_odometry``: the noise model of a
            run whose odometry is Pose2 increments or poses (samples without a
            covariance, the floor; :class:`~lampsam.datasets.odometry.Pose2OdometryModel`
            keys, each optional); None: the SLAM config's ``[pose2_odometry]``.
    """

    camera: CameraModel = field(default_factory=CameraModel)
    odometry: OdometryModel = field(default_factory=OdometryModel)
    pose2_odometry: Pose2OdometryModel | None = None

    @classmethod
    def from_dict(cls, data: Any, path: Path | None = None, strict: bool = False) -> Rig:
        """Build from the mapping of ``rig.yaml`` (sections ``camera``, ``odometry``).

        Every key is type-checked and unknown keys are errors. With ``strict`` (how
        :meth:`from_yaml` reads a run's ``rig.yaml``) every key of :data:`REQUIRED`
        must be present; only :data:`CAMERA_DEFAULTS` may be left out. Without it
        (simulator world files) missing keys take the :class:`CameraModel` /
        :class:`OdometryModel` defaults. The camera gives ``fx, fy, cx, cy`` or
        ``hfov_deg``, or ``calibration``: a ROS ``camera_info`` or OpenCV YAML file
        (relative to the rig file's folder) that gives size, intrinsics and lens model.

        Raises:
            DatasetError: a missing section or key, an unknown key or a bad value,
                naming the key (``camera.cx``) and ``path``.
        """
        return cls(*_rig_parts(data, path, strict))

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python mapping for YAML."""
        out = {"camera": self.camera.to_dict(), "odometry": self.odometry.to_dict()}
        if self.pose2_odometry is not None:
            out["pose2_odometry"] = {k: float(v) for k, v in vars(self.pose2_odometry).items()}
        return out

    @classmethod
    def from_yaml(cls, path: str | Path) -> Rig:
        """Read a run's ``rig.yaml`` strictly (see :meth:`from_dict`).

        Raises:
            DatasetError: missing file, invalid YAML, a missing, unknown or bad key.
        """
        path = Path(path)
        return cls.from_dict(read_yaml(path), path, strict=True)

    def to_yaml(self, path: str | Path) -> None:
        """Write ``rig.yaml``."""
        write_text_atomic(path, yaml.safe_dump(self.to_dict(), sort_keys=False))


# --------------------------------------------------------------------------- strict reading
REQUIRED = {
    "camera": ("width", "height", "body_t_camera"),
    "odometry": ("wheel_base", "k_r", "k_l"),
}
"""Keys a run's ``rig.yaml`` must give (plus the camera's intrinsics, see below)."""

CAMERA_DEFAULTS = {
    "dist": "no distortion (zeros)",
    "body_R_camera": "optical axis up, image top = robot forward (conventions.md)",
    "model": "pinhole",
}
"""The only camera keys with a documented default in a run's ``rig.yaml``."""

_INTRINSICS = ("fx", "fy", "cx", "cy")
_FROM_CALIBRATION = ("width", "height", "fx", "fy", "cx", "cy", "hfov_deg", "dist", "model")

T = TypeVar("T")


def _fail(msg: str, path: Path | None) -> DatasetError:
    """The rig error (one prefix so every message says where it comes from)."""
    return DatasetError(f"invalid rig: {msg}", path)


def _build(cls: type[T], data: dict[str, Any], key: str, path: Path | None,
           base: T | None = None) -> T:
    """``cls`` from a section with the project's strict loader (types, unknown keys)."""
    try:
        return from_mapping(cls, data, source=path, key=key, base=base)
    except ConfigError as exc:
        raise _fail(f"{exc.key}: {exc.problem}" if exc.key else exc.problem, path) from exc


def _section(data: dict[str, Any], name: str, strict: bool, path: Path | None) -> dict[str, Any]:
    """One section as a dict (missing: an error when strict, else empty)."""
    raw = data.get(name)
    if raw is None:
        if strict:
            raise _fail(f"section {name!r} is missing", path)
        return {}
    if not isinstance(raw, dict):
        raise _fail(f"section {name!r} must be a mapping, got {raw!r}", path)
    return dict(raw)


def _require(section: dict[str, Any], name: str, keys: Any, path: Path | None) -> None:
    """DatasetError naming the first of ``keys`` missing from a section."""
    for key in keys:
        if key not in section:
            raise _fail(f"{name}.{key} is missing (required in rig.yaml)", path)


def _camera(cam: dict[str, Any], path: Path | None, strict: bool) -> CameraModel:
    """The camera section as a model (intrinsics given, from the FOV or from a file)."""
    from lampsam.datasets.calibration import read_calibration

    if "calibration" in cam:
        clash = [k for k in _FROM_CALIBRATION if k in cam]
        if clash:
            raise _fail(f"camera.{clash[0]} given together with camera.calibration", path)
        if strict:
            _require(cam, "camera", ("body_t_camera",), path)
        cal = cam.pop("calibration")
        if not isinstance(cal, str):
            raise _fail(f"camera.calibration must be a file name, got {cal!r}", path)
        cal_path = Path(cal)
        if not cal_path.is_absolute() and path is not None:
            cal_path = path.parent / cal_path
        try:
            base = read_calibration(cal_path).camera()
        except ValueError as exc:
            raise _fail(f"camera: {exc}", path) from exc
        return _build(CameraModel, cam, "camera", path, base=base)
    if strict:
        _require(cam, "camera", REQUIRED["camera"], path)
        if "hfov_deg" not in cam:
            _require(cam, "camera", _INTRINSICS, path)
    if "hfov_deg" not in cam:
        return _build(CameraModel, cam, "camera", path)
    if any(k in cam for k in _INTRINSICS):
        raise _fail("camera: give hfov_deg or fx, fy, cx, cy, not both", path)
    hfov = cam.pop("hfov_deg")
    if isinstance(hfov, bool) or not isinstance(hfov, int | float) or not 0 < hfov < 360:
        raise _fail(f"camera.hfov_deg: must be a number in (0, 360), got {hfov!r}", path)
    cam0 = _build(CameraModel, cam, "camera", path)
    try:
        return CameraModel.from_fov(
            cam0.width, cam0.height, float(hfov), dist=cam0.dist, model=cam0.model,
            body_t_camera=cam0.body_t_camera, body_R_camera=cam0.body_R_camera,
        )  # fmt: skip
    except ValueError as exc:
        raise _fail(f"camera: {exc}", path) from exc


def _rig_parts(data: Any, path: Path | None, strict: bool
               ) -> tuple[CameraModel, OdometryModel, Pose2OdometryModel | None]:
    """Camera and odometry of a ``rig.yaml`` mapping (see :meth:`Rig.from_dict`)."""
    if not isinstance(data, dict):
        raise _fail("the rig must be a mapping with sections 'camera' and 'odometry'", path)
    unknown = sorted(set(data) - {"camera", "odometry", "pose2_odometry"})
    if unknown:
        raise _fail(f"unknown section {unknown[0]!r} (known: camera, odometry, pose2_odometry)",
                    path)
    cam = _section(data, "camera", strict, path)
    odo = _section(data, "odometry", strict, path)
    if strict:
        _require(odo, "odometry", REQUIRED["odometry"], path)
    pose2 = (_build(Pose2OdometryModel, _section(data, "pose2_odometry", False, path),
                    "pose2_odometry", path) if "pose2_odometry" in data else None)
    return _camera(cam, path, strict), _build(OdometryModel, odo, "odometry", path), pose2
