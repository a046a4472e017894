"""The ceiling feature map: lamps and corners of the ceiling SLAM (paper 2, sec. 2.2).

The ceiling SLAM (paper 1; ``backend/``) maps lamps (region features: the
paper's "arbitrarily shaped" features) and corners. Global localization uses
this layer to verify a pose (paper 2, sec. 4.2, eq. 10: a feature seen by the
upward camera must match a map feature projected at the estimated pose), so
each feature keeps what that projection and matching need: world position with
its height above the floor, type, lamp axis ``phi`` (mod pi) and size, and the
position covariance when the SLAM gave one.

Sources:

- a SLAM output's ``landmarks.csv`` (any CSV with a header containing ``id``,
  ``type``, ``x``, ``y``, ``z``; optional ``phi``, ``length``, ``width``,
  ``var_x`` or ``cov_xx``, ``cov_xy``, ``var_y`` or ``cov_yy``: the backend's
  ``landmarks.csv`` is read as it is). Its ``z`` is the height above the floor
  (backend/ceiling.py); for a file with ``z`` above the camera pass ``z_cam``;
- the run's true ``landmarks.csv`` (:func:`lampsam.datasets.logrun.read_landmarks`).

On disk: ``ceiling_features.csv`` with header
``id,type,x,y,z,phi,length,width,var_x,cov_xy,var_y`` (z above the floor,
metres; phi rad, NaN when the feature has no axis; variances m^2, NaN unknown).
"""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lampsam.arrays import BoolArray, FloatArray, IntArray
from lampsam.datasets.logrun import LandmarkTable
from lampsam.datasets.tables import lamp_mask
from lampsam.errors import DatasetError, LocalizationError
from lampsam.safe_io import atomic_path

log = logging.getLogger(__name__)

CEILING_FILE = "ceiling_features.csv"
CEILING_HEADER = ("id", "type", "x", "y", "z", "phi", "length", "width", "var_x", "cov_xy", "var_y")


class CeilingMapError(LocalizationError):
    """A ceiling feature map could not be built or read."""


@dataclass(frozen=True, eq=False)
class CeilingFeatureMap:
    """Lamps and corners in the world frame.

    Attributes:
        ids: (L,) landmark ids.
        types: L type names (``lamp_rect``, ``lamp_round``, ``lamp``, ``corner``, ...).
        xyz: (L, 3) world positions, metres; ``z`` = height above the floor.
        phi: (L,) lamp long axis in the world, rad mod pi; NaN for none.
        length: (L,) lamp length, metres (0 or NaN unknown).
        width: (L,) lamp width, metres.
        cov_xy: (L, 2, 2) horizontal position covariance, m^2 (NaN unknown).
        source: where the features came from (``groundtruth`` or a SLAM file).
    """

    ids: IntArray
    types: tuple[str, ...]
    xyz: FloatArray
    phi: FloatArray
    length: FloatArray
    width: FloatArray
    cov_xy: FloatArray
    source: str

    def __len__(self) -> int:
        """Number of features."""
        return int(len(self.ids))

    def is_lamp(self) -> BoolArray:
        """(L,) True for lamps (:func:`lampsam.datasets.tables.lamp_mask`)."""
        return lamp_mask(self.types)

    def save(self, path: str | Path) -> Path:
        """Write ``ceiling_features.csv`` (module docstring)."""
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(CEILING_HEADER)
            for i in range(len(self)):
                c = self.cov_xy[i]
                w.writerow(
                    [int(self.ids[i]), self.types[i]]
                    + [f"{v:.6f}" for v in self.xyz[i]]
                    + [
                        f"{v:.9g}"
                        for v in (
                            self.phi[i],
                            self.length[i],
                            self.width[i],
                            c[0, 0],
                            c[0, 1],
                            c[1, 1],
                        )
                    ]
                )
        return path

    @classmethod
    def load(cls, path: str | Path, source: str | None = None) -> CeilingFeatureMap:
        """Read ``ceiling_features.csv`` (or a SLAM ``landmarks.csv`` with z above the floor)."""
        return read_landmark_csv(path, z_cam=0.0, source=source)


def _col(
    row: dict[str, str], key: str, path: Path, line: int, default: float | None = None
) -> float:
    """Column ``key`` of a CSV row as a float (``default`` when empty/absent and given)."""
    text = row.get(key)
    if text is None or text == "":
        if default is None:
            raise DatasetError(f"missing column {key!r}", path, line)
        return default
    try:
        return float(text)
    except ValueError as exc:
        raise DatasetError(f"column {key!r}: bad number {text!r}", path, line) from exc


def read_landmark_csv(
    path: str | Path, z_cam: float = 0.0, source: str | None = None
) -> CeilingFeatureMap:
    """A ceiling map from a landmarks CSV (module docstring).

    Args:
        path: the CSV.
        z_cam: added to every ``z`` (metres): the camera height when the file's ``z``
            is the height above the camera, 0 when it is above the floor.
        source: recorded as :attr:`CeilingFeatureMap.source` (default the path).

    Returns:
        The map (non-finite positions are skipped with a warning).

    Raises:
        DatasetError: missing file, missing column, bad number.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError("landmarks file not found", path)
    ids: list[int] = []
    types: list[str] = []
    rows: list[list[float]] = []
    with open(path, encoding="utf-8", newline="") as fh:
        reader = csv.DictReader(line for line in fh if not line.startswith("#"))
        if reader.fieldnames is None or not {"id", "x", "y", "z"} <= set(reader.fieldnames):
            raise DatasetError(f"header must contain id,x,y,z (got {reader.fieldnames})", path, 1)
        for k, row in enumerate(reader, start=2):
            x, y, z = (_col(row, c, path, k) for c in ("x", "y", "z"))
            if not all(math.isfinite(v) for v in (x, y, z)):
                log.warning("%s:%d: non-finite landmark position skipped", path, k)
                continue
            phi = _col(row, "phi", path, k, _col(row, "orientation", path, k, math.nan))
            try:
                lid = int(float(row["id"]))
            except (TypeError, ValueError) as exc:
                raise DatasetError(f"bad id {row.get('id')!r}", path, k) from exc
            ids.append(lid)
            types.append(str(row.get("type") or "lamp"))
            rows.append(
                [x, y, z + z_cam, phi]
                + [_col(row, c, path, k, math.nan) for c in ("length", "width")]
                + [
                    _col(row, c, path, k, _col(row, alt, path, k, math.nan))
                    for c, alt in (("var_x", "cov_xx"), ("cov_xy", "cov_xy"), ("var_y", "cov_yy"))
                ]
            )
    a = np.array(rows, dtype=float).reshape(-1, 9)
    cov = np.stack([np.stack([a[:, 6], a[:, 7]], -1), np.stack([a[:, 7], a[:, 8]], -1)], -2)
    # corners and round lamps carry no axis
    no_axis = np.array([t in ("corner", "lamp_round") for t in types], dtype=bool)
    axis = np.where(no_axis, np.nan, a[:, 3])
    return CeilingFeatureMap(
        np.array(ids, np.int64),
        tuple(types),
        a[:, :3],
        axis,
        a[:, 4],
        a[:, 5],
        cov,
        source or str(path),
    )


def from_landmark_table(table: LandmarkTable, source: str = "groundtruth") -> CeilingFeatureMap:
    """Ceiling map of a :class:`lampsam.datasets.logrun.LandmarkTable` (truth, z above floor)."""
    ids = np.asarray(table.ids, np.int64)
    types = tuple(table.types)
    no_axis = np.array([t in ("corner", "lamp_round") for t in types], dtype=bool)
    phi = np.where(no_axis, np.nan, np.asarray(table.phi, dtype=np.float64))
    n = len(ids)
    return CeilingFeatureMap(
        ids,
        types,
        np.asarray(table.xyz, dtype=np.float64).reshape(n, 3),
        phi.reshape(n),
        np.asarray(table.length, dtype=np.float64),
        np.asarray(table.width, dtype=np.float64),
        np.full((n, 2, 2), np.nan),
        source,
    )
