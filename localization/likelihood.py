"""Measurement models of the particle filter: scan log-likelihood per particle.

Paper 2, eqs. 8-9 weight a particle by the squared differences between its
ray-cast ranges and the measured scan; as printed, eq. 9 squares the sum of
squares again (DESIGN.md sec. 2). Here every beam is an independent mixture of
a Gaussian around the expected range and a uniform "random return" term
(Thrun, Burgard & Fox, *Probabilistic Robotics*, sec. 6.3, eq. 6.12 without the
short/max components), and the scan's log-likelihood is the sum over beams:

    log p(z | x) = w * sum_b log( z_hit N(z_b; zhat_b(x), sigma^2) + z_rand / r_max )

``w`` (``beam_weight``, default 1) tempers the product of beams, which are not
really independent. Beams without a return (NaN, or ``>= r_max``) are left out,
so a 180-degree laser or any subset of beams works unchanged.

Three models share the interface ``log_likelihood(poses, ranges, angles) -> (P,)``:

- :class:`RayCastModel` (``method="march"``): expected ranges by sphere tracing
  (:func:`lampsam.localization.raycast.cast_rays`).
- :class:`RayCastModel` (``method="table"``): expected ranges from a
  :class:`~lampsam.localization.raycast.RangeTable`.
- :class:`LikelihoodFieldModel`: no ray casting; each beam endpoint is scored by
  its distance ``d`` to the nearest occupied cell (Euclidean distance transform,
  ``scipy.ndimage.distance_transform_edt``), ``N(d; 0, sigma^2)`` in place of
  ``N(z; zhat, sigma^2)`` (Probabilistic Robotics, sec. 6.4, table 6.3). The
  per-cell log-likelihood is precomputed, so an update is one gather per beam.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from lampsam.arrays import FloatArray
from lampsam.errors import LocalizationError
from lampsam.localization.grid import OccupancyGrid, occupied_mask
from lampsam.localization.raycast import RangeTable, RayMarchConfig, cast_rays, distance_field

log = logging.getLogger(__name__)


class LikelihoodError(LocalizationError):
    """Bad input to a measurement model (shapes, settings)."""


@dataclass(frozen=True)
class BeamModelConfig:
    """Per-beam measurement model.

    Attributes:
        sigma_hit: standard deviation of a beam's range around the expected
            one (or of the endpoint's distance to the nearest wall), metres
            (default 0.10).
        z_hit: weight of the Gaussian (default 0.9).
        z_rand: weight of the uniform random return over ``[0, max_range]``
            (default 0.1; 0 gives a pure Gaussian).
        max_range: the sensor's maximum range, metres; longer readings are no
            return (default 10.0).
        beam_weight: exponent applied to each beam's likelihood (default 1.0,
            independent beams; < 1 tempers over-confident scans).
    """

    sigma_hit: float = 0.10
    z_hit: float = 0.9
    z_rand: float = 0.1
    max_range: float = 10.0
    beam_weight: float = 1.0

    def __post_init__(self) -> None:
        if not (self.sigma_hit > 0 and self.max_range > 0 and self.z_hit > 0
                and self.z_rand >= 0 and self.beam_weight > 0):
            raise LikelihoodError(f"invalid beam model settings: {self}")


class MeasurementModel(Protocol):
    """What the particle filter needs from a measurement model."""

    config: BeamModelConfig

    def log_likelihood(self, poses: FloatArray, ranges: FloatArray,
                       angles: FloatArray) -> FloatArray:
        """Scan log-likelihood (P,) of poses (P, 3) for ranges (B,) at angles (B,)."""
        ...


def valid_beams(ranges: FloatArray, max_range: float) -> np.ndarray:
    """Beams with a usable return: finite, positive, below ``max_range``.

    Args:
        ranges: (B,) metres.
        max_range: metres.

    Returns:
        (B,) bool.
    """
    r = np.asarray(ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.isfinite(r) & (r > 0) & (r < max_range)


def beam_log_likelihood(error: FloatArray, config: BeamModelConfig) -> FloatArray:
    """Per-beam log-likelihood of range errors (the mixture in the module docstring).

    Args:
        error: (...,) ``z - zhat`` (or endpoint distance to the nearest wall), metres.
        config: the model.

    Returns:
        (...,) ``log(z_hit N(error; 0, sigma^2) + z_rand / max_range)``, same dtype
        family as ``error`` (float32 stays float32).
    """
    sigma = config.sigma_hit
    dtype = np.result_type(error, np.float32)
    e = np.asarray(error, dtype=dtype)
    quad = (e * dtype.type(1.0 / sigma)) ** 2 * dtype.type(-0.5)
    log_norm = dtype.type(math.log(config.z_hit / (math.sqrt(2 * math.pi) * sigma)))
    if config.z_rand == 0:
        return quad + log_norm
    # log(a e^q + c) with c > 0 cannot underflow to -inf, so no log-sum-exp shift is needed.
    a = dtype.type(config.z_hit / (math.sqrt(2 * math.pi) * sigma))
    c = dtype.type(config.z_rand / config.max_range)
    return np.log(a * np.exp(quad) + c)


def scan_log_likelihood(expected: FloatArray, measured: FloatArray,
                        config: BeamModelConfig) -> FloatArray:
    """Scan log-likelihood of each particle from its expected ranges (paper eqs. 8-9, corrected).

    Args:
        expected: (P, B) ray-cast ranges, metres.
        measured: (B,) measured ranges, metres; NaN / ``>= max_range`` = no return (skipped).
        config: the model.

    Returns:
        (P,) float64 ``beam_weight * sum_b beam_log_likelihood(measured_b - expected_pb)``.
    """
    expected = np.asarray(expected)
    measured = np.asarray(measured, dtype=np.float64).reshape(-1)
    if expected.ndim != 2 or expected.shape[1] != measured.size:
        raise LikelihoodError(f"expected {expected.shape} does not match {measured.size} beams")
    ok = valid_beams(measured, config.max_range)
    if not ok.any():
        return np.zeros(expected.shape[0])
    err = measured[ok].astype(expected.dtype)[None, :] - expected[:, ok]
    ll = beam_log_likelihood(err, config).sum(axis=1, dtype=np.float64)
    return config.beam_weight * ll


def _check_inputs(poses: FloatArray, ranges: FloatArray,
                  angles: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Poses (P, 3), ranges (B,), angles (B,) as float arrays; LikelihoodError on mismatched shapes."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    ranges = np.asarray(ranges, dtype=np.float64).reshape(-1)
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    if ranges.shape != angles.shape:
        raise LikelihoodError(f"ranges {ranges.shape} and angles {angles.shape} differ")
    return poses, ranges, angles


class RayCastModel:
    """Per-beam Gaussian on ray-cast ranges, by marching or by a range table.

    Args:
        grid: the map.
        config: the beam model (``max_range`` also bounds the ray casting).
        method: ``"march"`` (cast every update) or ``"table"`` (precompute).
        n_angles: heading bins of the table (``method="table"``), default 360.
        march: sphere-tracing settings (default ``RayMarchConfig()``).
        table: a table already built for ``grid`` (``method="table"``; its
            ``max_range`` must be at least ``config.max_range``). Default None:
            build one over every non-occupied cell (free and unknown, where the
            marcher casts too), so both methods cover the same poses.
    """

    def __init__(self, grid: OccupancyGrid, config: BeamModelConfig,
                 method: Literal["march", "table"] = "march", n_angles: int = 360,
                 march: RayMarchConfig | None = None, table: RangeTable | None = None) -> None:
        self.grid = grid
        self.config = config
        self.method = method
        self.march = march if march is not None else RayMarchConfig()
        self.occupied = occupied_mask(grid)
        self.dist = distance_field(self.occupied)
        self.table: RangeTable | None = None
        if method == "table":
            if table is None:
                table = RangeTable.build(grid, n_angles, config.max_range, cells=~self.occupied,
                                         config=self.march)
            elif table.grid_shape != (grid.height, grid.width) or table.max_range < config.max_range - 1e-9:
                raise LikelihoodError(
                    f"range table {table.grid_shape} up to {table.max_range} m does not fit "
                    f"the grid {(grid.height, grid.width)} and max_range {config.max_range} m")
            self.table = table
        elif method != "march":
            raise LikelihoodError(f"unknown ray-casting method {method!r}")

    def expected_ranges(self, poses: FloatArray, angles: FloatArray) -> FloatArray:
        """(P, B) expected ranges, metres."""
        if self.table is not None:
            r = self.table.lookup(poses, angles)
            if self.table.max_range > self.config.max_range:
                np.minimum(r, np.float32(self.config.max_range), out=r)
            return r
        return cast_rays(self.grid, poses, angles, self.config.max_range, self.march,
                         self.occupied, self.dist)

    def log_likelihood(self, poses: FloatArray, ranges: FloatArray,
                       angles: FloatArray) -> FloatArray:
        """Scan log-likelihood of each pose.

        Args:
            poses: (P, 3) world poses of the sensor, metres/rad.
            ranges: (B,) measured ranges, metres (NaN = no return).
            angles: (B,) beam angles, sensor frame, rad.

        Returns:
            (P,) float64.
        """
        poses, ranges, angles = _check_inputs(poses, ranges, angles)
        ok = valid_beams(ranges, self.config.max_range)
        expected = self.expected_ranges(poses, angles[ok])
        return scan_log_likelihood(expected, ranges[ok], self.config)


class LikelihoodFieldModel:
    """Likelihood field: beam endpoints scored by their distance to the nearest wall.

    The per-cell log-likelihood ``field`` (H, W) is precomputed; an update
    computes all endpoints in map cell coordinates with one (2P, 3) x (3, B)
    matrix product and gathers the field with ``cv2.remap`` (nearest cell, or
    bilinear with ``interpolate=True``); endpoints outside the map score as if
    far from any wall.

    Args:
        grid: the map.
        config: the beam model.
        interpolate: bilinear interpolation of the field (default False).
        dist_cells: (H, W) the grid's distance field in cells, as stored with
            the map (:func:`lampsam.localization.map_tables.load_distance_field`);
            default None: computed here.
    """

    #: cv2.remap handles at most 32767 rows at once.
    _CHUNK = 32_000

    def __init__(self, grid: OccupancyGrid, config: BeamModelConfig,
                 interpolate: bool = False, dist_cells: FloatArray | None = None) -> None:
        self.grid = grid
        self.config = config
        self.interpolate = interpolate
        if dist_cells is None:
            dist_cells = distance_field(occupied_mask(grid))
        elif np.shape(dist_cells) != (grid.height, grid.width):
            raise LikelihoodError(f"distance field {np.shape(dist_cells)} is not the grid's "
                                  f"{(grid.height, grid.width)}")
        dist_m = np.asarray(dist_cells, dtype=np.float64) * grid.resolution
        self.far = float(beam_log_likelihood(np.array([np.inf if config.z_rand > 0 else 1e3]),
                                             config)[0])
        self.field = np.ascontiguousarray(beam_log_likelihood(dist_m, config), dtype=np.float32)

    def endpoint_log_likelihood(self, poses: FloatArray, ranges: FloatArray,
                                angles: FloatArray) -> NDArray[np.float32]:
        """Per-beam log-likelihood of every pose's endpoints (all beams used as given).

        Args:
            poses: (P, 3) world poses, metres/rad.
            ranges: (B,) ranges, metres (all finite).
            angles: (B,) beam angles, rad.

        Returns:
            (P, B) float32.
        """
        g = self.grid
        inv_res = 1.0 / g.resolution
        # Beam vectors in map cell units (map axes rotated by the origin yaw).
        phi = angles - g.origin[2]
        beams = np.vstack([ranges * np.cos(phi) * inv_res, ranges * np.sin(phi) * inv_res,
                           np.ones_like(ranges)]).astype(np.float32)
        # cv2.remap's nearest neighbour rounds; cell ix covers map coordinates [ix, ix + 1).
        uv = g.world_to_map(poses[:, :2]) - 0.5
        heading = poses[:, 2] - g.origin[2]
        c, s = np.cos(heading), np.sin(heading)
        out = np.empty((len(poses), len(ranges)), dtype=np.float32)
        interp = cv2.INTER_LINEAR if self.interpolate else cv2.INTER_NEAREST
        for start in range(0, len(poses), self._CHUNK):
            sl = slice(start, min(start + self._CHUNK, len(poses)))
            n = sl.stop - sl.start
            # Rows [c, -s, u0] give u = u0 + c bx - s by; rows [s, c, v0] give v.
            a = np.empty((2 * n, 3), dtype=np.float32)
            a[:n, 0], a[:n, 1], a[:n, 2] = c[sl], -s[sl], uv[sl, 0]
            a[n:, 0], a[n:, 1], a[n:, 2] = s[sl], c[sl], uv[sl, 1]
            end = a @ beams
            out[sl] = cv2.remap(self.field, end[:n], end[n:], interp,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=self.far)
        return out

    def log_likelihood(self, poses: FloatArray, ranges: FloatArray,
                       angles: FloatArray) -> FloatArray:
        """Scan log-likelihood of each pose (see :meth:`RayCastModel.log_likelihood`)."""
        poses, ranges, angles = _check_inputs(poses, ranges, angles)
        ok = valid_beams(ranges, self.config.max_range)
        if not ok.any():
            return np.zeros(len(poses))
        ll = self.endpoint_log_likelihood(poses, ranges[ok], angles[ok])
        return self.config.beam_weight * ll.sum(axis=1, dtype=np.float64)
