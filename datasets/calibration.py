"""Camera calibration files: ROS ``camera_info`` YAML and OpenCV ``FileStorage`` YAML.

Both give the image size, the intrinsic matrix ``K`` and the distortion
coefficients; the lens model follows from ROS's ``distortion_model``
(``plumb_bob`` / ``rational_polynomial`` -> OpenCV pinhole with 5 / 8
coefficients, ``equidistant`` or ``fisheye`` -> ``cv2.fisheye`` with 4) or
OpenCV's ``distortion_model`` / ``fisheye_model`` entries (pinhole when absent).

ROS ``camera_info`` (as ``camera_calibration`` and ``camera_info_manager`` write it)::

    image_width: 640
    image_height: 480
    camera_name: ceiling
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: plumb_bob
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
    rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}
    projection_matrix: {rows: 3, cols: 4, data: [...]}

OpenCV ``FileStorage`` (``%YAML:1.0`` first line, as OpenCV's calibration sample
writes it): ``image_width``, ``image_height``, ``camera_matrix`` (or ``K``) and
``distortion_coefficients`` (or ``D``) as ``!!opencv-matrix``. Pixels are
undistorted from the raw image with ``K`` and the coefficients; the
rectification and projection matrices (stereo) are not used.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from lampsam.arrays import FloatArray
from lampsam.datasets.camera import PINHOLE_DIST_SIZES, CameraModel
from lampsam.datasets.textio import read_yaml
from lampsam.errors import DatasetError
from lampsam.safe_io import write_text_atomic

log = logging.getLogger(__name__)

ROS_MODELS = {
    "plumb_bob": "pinhole",
    "rational_polynomial": "pinhole",
    "pinhole": "pinhole",
    "radtan": "pinhole",
    "equidistant": "fisheye",
    "fisheye": "fisheye",
    "kannala_brandt": "fisheye",
}
"""ROS (and Kalibr) distortion-model names -> :class:`CameraModel` lens models."""


@dataclass(frozen=True, eq=False)
class Intrinsics:
    """What a calibration file says about a camera (no mounting).

    Attributes:
        width, height: image size, px.
        fx, fy, cx, cy: ``K``, px (OpenCV pixel convention).
        dist: distortion coefficients (length fits ``model``).
        model: ``"pinhole"`` or ``"fisheye"``.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: FloatArray
    model: str

    def camera(self, **mounting: Any) -> CameraModel:
        """The :class:`CameraModel` with these intrinsics and the given mounting fields.

        Raises:
            ValueError: invalid values (e.g. a coefficient count the model does not take).
        """
        return CameraModel(
            width=self.width, height=self.height, fx=self.fx, fy=self.fy, cx=self.cx,
            cy=self.cy, dist=self.dist, model=self.model, **mounting,
        )  # fmt: skip

    def to_camera_info(self) -> dict[str, Any]:
        """The ROS ``camera_info`` YAML mapping (identity rectification, ``P = [K | 0]``)."""
        k = [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]
        p = [self.fx, 0.0, self.cx, 0.0, 0.0, self.fy, self.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        return {
            "image_width": int(self.width),
            "image_height": int(self.height),
            "camera_name": "ceiling",
            "camera_matrix": {"rows": 3, "cols": 3, "data": [float(x) for x in k]},
            "distortion_model": ros_distortion_model(self.model, len(self.dist)),
            "distortion_coefficients": {
                "rows": 1, "cols": len(self.dist), "data": [float(x) for x in self.dist],
            },  # fmt: skip
            "rectification_matrix": {"rows": 3, "cols": 3, "data": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]},
            "projection_matrix": {"rows": 3, "cols": 4, "data": [float(x) for x in p]},
        }


def ros_distortion_model(model: str, n_coeffs: int) -> str:
    """The ROS ``distortion_model`` name of a lens model with ``n_coeffs`` coefficients."""
    if model == "fisheye":
        return "equidistant"
    return "rational_polynomial" if n_coeffs >= 8 else "plumb_bob"


def intrinsics_from_k(
    width: int, height: int, k: Any, dist: Any, distortion_model: str, where: Path | str | None
) -> Intrinsics:
    """Intrinsics from a row-major ``K`` (9 numbers), coefficients and a ROS model name.

    Shared by the calibration files and ``sensor_msgs/CameraInfo`` messages (whose
    fields ``width, height, k, d, distortion_model`` it takes). An empty ``dist`` is
    no distortion.

    Raises:
        DatasetError: unknown model, wrong coefficient count, bad ``K`` (naming ``where``).
    """
    name = str(distortion_model or "plumb_bob").strip().lower()
    if name not in ROS_MODELS:
        raise DatasetError(
            f"distortion_model {distortion_model!r} is not supported; "
            f"use one of {sorted(ROS_MODELS)}", where,
        )  # fmt: skip
    model = ROS_MODELS[name]
    kk = np.asarray(k, dtype=np.float64).ravel()
    d = np.asarray(dist, dtype=np.float64).ravel()
    if kk.shape != (9,) or not np.all(np.isfinite(kk)) or kk[0] <= 0 or kk[4] <= 0:
        raise DatasetError(f"camera matrix must be 9 finite numbers with fx, fy > 0, got {kk}", where)
    if len(d) == 0:
        d = np.zeros(4 if model == "fisheye" else 5)
    sizes = (4,) if model == "fisheye" else PINHOLE_DIST_SIZES
    if len(d) not in sizes or not np.all(np.isfinite(d)):
        raise DatasetError(
            f"distortion_model {name!r} takes {' or '.join(map(str, sizes))} finite "
            f"coefficients, got {len(d)}", where,
        )  # fmt: skip
    if int(width) <= 0 or int(height) <= 0:
        raise DatasetError(f"image size must be positive, got {width}x{height}", where)
    return Intrinsics(
        width=int(width), height=int(height), fx=float(kk[0]), fy=float(kk[4]),
        cx=float(kk[2]), cy=float(kk[5]), dist=d, model=model,
    )  # fmt: skip


def _ros_matrix(doc: dict[str, Any], key: str, path: Path) -> list[float]:
    """The ``data`` list of a ROS ``{rows, cols, data}`` entry, or DatasetError naming key."""
    entry = doc.get(key)
    if not isinstance(entry, dict) or "data" not in entry:
        raise DatasetError(f"key {key!r} missing or not a {{rows, cols, data}} mapping", path)
    data = entry["data"]
    if not isinstance(data, list) or not all(isinstance(x, int | float) for x in data):
        raise DatasetError(f"{key}.data must be a list of numbers", path)
    rows, cols = entry.get("rows"), entry.get("cols")
    if isinstance(rows, int) and isinstance(cols, int) and rows * cols != len(data):
        raise DatasetError(f"{key}: {rows}x{cols} but {len(data)} numbers", path)
    return [float(x) for x in data]


def _read_ros(path: Path) -> Intrinsics:
    """A ROS ``camera_info`` YAML file."""
    doc = read_yaml(path)
    if not isinstance(doc, dict):
        raise DatasetError("calibration must be a YAML mapping", path)
    for key in ("image_width", "image_height"):
        if not isinstance(doc.get(key), int) or isinstance(doc.get(key), bool):
            raise DatasetError(f"key {key!r} missing or not an integer", path)
    k = _ros_matrix(doc, "camera_matrix", path)
    d = _ros_matrix(doc, "distortion_coefficients", path) if "distortion_coefficients" in doc else []
    rect = doc.get("rectification_matrix")
    if isinstance(rect, dict) and isinstance(rect.get("data"), list) and len(rect["data"]) == 9:
        if not np.allclose(np.asarray(rect["data"], dtype=float).reshape(3, 3), np.eye(3), atol=1e-9):
            log.info("%s: rectification_matrix is not identity (stereo); it is not used", path)
    return intrinsics_from_k(
        doc["image_width"], doc["image_height"], k, d, doc.get("distortion_model", "plumb_bob"), path
    )


def _read_opencv(path: Path) -> Intrinsics:
    """An OpenCV ``FileStorage`` YAML file."""
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise DatasetError(f"cannot parse OpenCV FileStorage: {exc}", path) from exc
    try:
        if not fs.isOpened():
            raise DatasetError("cannot open OpenCV FileStorage", path)

        def node(*names: str) -> Any:
            for n in names:
                nd = fs.getNode(n)
                if not nd.empty():
                    return nd
            return None

        k_node = node("camera_matrix", "K", "cameraMatrix")
        if k_node is None or k_node.mat() is None:
            raise DatasetError("no camera_matrix (or K) matrix", path)
        k = k_node.mat()
        d_node = node("distortion_coefficients", "D", "distCoeffs", "dist_coeffs")
        d = d_node.mat() if d_node is not None and d_node.mat() is not None else np.zeros(0)
        sizes = []
        for names in (("image_width", "width"), ("image_height", "height")):
            nd = node(*names)
            if nd is None or not math.isfinite(nd.real()):
                raise DatasetError(f"no {names[0]}", path)
            sizes.append(int(nd.real()))
        model_node = node("distortion_model", "model")
        fisheye_node = node("fisheye_model")
        if model_node is not None and model_node.isString():
            model = model_node.string()
        elif fisheye_node is not None and fisheye_node.real() != 0:
            model = "equidistant"
        else:
            model = "plumb_bob"
        return intrinsics_from_k(sizes[0], sizes[1], k, d, model, path)
    finally:
        fs.release()


def read_calibration(path: str | Path) -> Intrinsics:
    """Read a ROS ``camera_info`` or OpenCV ``FileStorage`` YAML (module docstring).

    The format is told by the first line (``%YAML:1.0`` = OpenCV) or by
    ``!!opencv-matrix`` tags.

    Raises:
        DatasetError: missing file, missing key, bad values, unsupported model; the
            message names the file and the key.
    """
    path = Path(path)
    if path.is_dir():
        raise DatasetError("is a directory, expected a calibration file", path)
    try:
        head = path.read_text(encoding="utf-8", errors="replace")[:4096]
    except FileNotFoundError as exc:
        raise DatasetError("calibration file not found", path) from exc
    except OSError as exc:
        raise DatasetError(f"cannot read: {exc.strerror or exc}", path) from exc
    if head.lstrip().startswith("%YAML") or "!!opencv-matrix" in head:
        return _read_opencv(path)
    return _read_ros(path)


def write_camera_info(path: str | Path, intrinsics: Intrinsics) -> None:
    """Write a ROS ``camera_info`` YAML (readable by :func:`read_calibration` and ROS)."""
    write_text_atomic(path, yaml.safe_dump(intrinsics.to_camera_info(), sort_keys=False))


def intrinsics_of(camera: CameraModel) -> Intrinsics:
    """The intrinsics part of a :class:`CameraModel`."""
    return Intrinsics(
        width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy,
        cx=camera.cx, cy=camera.cy, dist=np.asarray(camera.dist), model=camera.model,
    )  # fmt: skip
