"""The sensor rig of a logged run (``rig.yaml``): ceiling camera and wheel odometry.

``rig.yaml`` has two sections, ``camera`` (:class:`~lampsam.datasets.camera.CameraModel`
fields; or ``hfov_deg`` instead of ``fx, fy, cx, cy``; or ``calibration``, a ROS /
OpenCV calibration file) and ``odometry`` (:class:`OdometryModel` fields); see
``docs/log-format.md``. A run's ``rig.yaml`` is read strictly: every key of
:data:`REQUIRED` must be there (a rig that silently ran on the simulator's wheel
base is worse than an error), only :data:`CAMERA_DEFAULTS` have defaults, and
unknown keys or wrong types are errors naming the key and the file. The checks
are a key table (:data:`REQUIRED`, ``_KINDS``) so that they can move onto a
project-wide strict config loader.
"""

from __future__ import annotations

import math
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
        return {"camera": self.camera.to_dict(), "odometry": self.odometry.to_dict()}

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
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))


# --------------------------------------------------------------------------- strict reading
_KINDS = {
    "width": "int", "height": "int", "fx": "num", "fy": "num", "cx": "num", "cy": "num",
    "hfov_deg": "num", "dist": "vector", "body_t_camera": "vec3", "body_R_camera": "mat3",
    "model": "str", "calibration": "str", "wheel_base": "num", "k_r": "num", "k_l": "num",
}  # fmt: skip
"""Expected kind of every rig key (``num``: int or float, finite)."""

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


def _fail(msg: str, path: Path | None) -> DatasetError:
    """The rig error (one prefix so every message says where it comes from)."""
    return DatasetError(f"invalid rig: {msg}", path)


def _check_kind(where: str, value: Any, kind: str, path: Path | None) -> None:
    """DatasetError naming ``where`` (``camera.cx``) when ``value`` is not of ``kind``."""

    def num(x: Any) -> bool:
        return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)

    ok = {
        "int": isinstance(value, int) and not isinstance(value, bool),
        "num": num(value),
        "str": isinstance(value, str),
        "vector": isinstance(value, list) and all(num(x) for x in value),
        "vec3": isinstance(value, list) and len(value) == 3 and all(num(x) for x in value),
        "mat3": isinstance(value, list) and len(value) == 3
        and all(isinstance(r, list) and len(r) == 3 and all(num(x) for x in r) for r in value),
    }[kind]
    if not ok:
        want = {
            "int": "an integer", "num": "a finite number", "str": "a string",
            "vector": "a list of numbers", "vec3": "a list of 3 numbers",
            "mat3": "a 3x3 list of lists of numbers",
        }[kind]  # fmt: skip
        raise _fail(f"{where} must be {want}, got {value!r}", path)


def _section(data: dict[str, Any], name: str, strict: bool, path: Path | None) -> dict[str, Any]:
    """One section as a dict with known, type-checked keys."""
    raw = data.get(name)
    if raw is None:
        if strict:
            raise _fail(f"section {name!r} is missing", path)
        return {}
    if not isinstance(raw, dict):
        raise _fail(f"section {name!r} must be a mapping, got {raw!r}", path)
    known = set(REQUIRED[name]) | (
        set(_KINDS) - {"wheel_base", "k_r", "k_l"} if name == "camera" else set()
    )
    for key, value in raw.items():
        if key not in known:
            raise _fail(f"{name}.{key}: unknown key (known: {', '.join(sorted(known))})", path)
        _check_kind(f"{name}.{key}", value, _KINDS[key], path)
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
        cal_path = Path(cam.pop("calibration"))
        if not cal_path.is_absolute() and path is not None:
            cal_path = path.parent / cal_path
        try:
            return read_calibration(cal_path).camera(**cam)
        except ValueError as exc:
            raise _fail(f"camera: {exc}", path) from exc
    if strict:
        _require(cam, "camera", REQUIRED["camera"], path)
        if "hfov_deg" not in cam:
            _require(cam, "camera", _INTRINSICS, path)
    if "hfov_deg" in cam and any(k in cam for k in _INTRINSICS):
        raise _fail("camera: give hfov_deg or fx, fy, cx, cy, not both", path)
    try:
        if "hfov_deg" in cam:
            return CameraModel.from_fov(**cam)
        return CameraModel(**cam)
    except ValueError as exc:
        raise _fail(f"camera: {exc}", path) from exc


def _rig_parts(data: Any, path: Path | None, strict: bool) -> tuple[CameraModel, OdometryModel]:
    """Camera and odometry of a ``rig.yaml`` mapping (see :meth:`Rig.from_dict`)."""
    if not isinstance(data, dict):
        raise _fail("the rig must be a mapping with sections 'camera' and 'odometry'", path)
    unknown = sorted(set(data) - {"camera", "odometry"})
    if unknown:
        raise _fail(f"unknown section {unknown[0]!r} (known: camera, odometry)", path)
    cam = _section(data, "camera", strict, path)
    odo = _section(data, "odometry", strict, path)
    if strict:
        _require(odo, "odometry", REQUIRED["odometry"], path)
    camera = _camera(cam, path, strict)
    try:
        odometry = OdometryModel(**odo)
    except ValueError as exc:
        raise _fail(f"odometry: {exc}", path) from exc
    return camera, odometry
