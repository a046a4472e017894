"""Configuration of the environment map build: depth grid, laser grid, SIFT layer.

Frozen dataclasses with documented defaults (STYLE.md sec. 5); the CLI (``commands/``) fills
them from a TOML ``[envmap]`` table and passes them to ``build_map``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lampsam.config_loader import check_limits, limits
from lampsam.localization.grid import LogOddsConfig
from lampsam.localization.map_tables import TableConfig
from lampsam.localization.spatial_map import SpatialMapConfig


@dataclass(frozen=True)
class DepthGridConfig:
    """Grid map from depth images.

    Attributes:
        resolution: cell size, metres (default 0.05).
        height_band: ``(lo, hi)`` heights of obstacle points, metres above the floor
            (default ``(0.08, 1.8)``: above floor noise, up to the robot's height).
        band_reference: ``"floor"`` (``z = 0``, simulated runs), ``"fit"`` (the floor
            plane fitted to the fused cloud with Open3D RANSAC: sets "up" and the
            floor height, for hand-held data) or ``"camera"`` (heights relative to
            the first camera); default ``"floor"``.
        depth_stride: use every n-th pixel in both directions (default 2).
        free_bucket: floor rays clear free space to within this distance of the
            farthest floor point of their bearing, metres (default 0.25).
        bearing_bin_deg: bearing bin of the floor rays, degrees (default 0.5).
        margin: grid border beyond the sensor positions' reach, metres (default 0.3).
        log_odds: the inverse sensor model (grid.py's defaults).
    """

    resolution: float = field(default=0.05, metadata=limits(gt=0.0))
    height_band: tuple[float, float] = (0.08, 1.8)
    band_reference: str = "floor"
    depth_stride: int = field(default=2, metadata=limits(ge=1))
    free_bucket: float = field(default=0.25, metadata=limits(ge=0.0))
    bearing_bin_deg: float = field(default=0.5, metadata=limits(gt=0.0))
    margin: float = field(default=0.3, metadata=limits(ge=0.0))
    log_odds: LogOddsConfig = field(default_factory=LogOddsConfig)

    def __post_init__(self) -> None:
        check_limits(self)


@dataclass(frozen=True)
class LaserGridConfig:
    """Grid map from planar laser scans.

    Attributes:
        resolution: cell size, metres (default 0.1).
        max_range: ranges beyond are no obstacle, metres (default 25).
        min_move: use a scan when the pose moved this far since the last used one,
            metres (default 0.1) ...
        min_turn: ... or turned this much, rad (default 0.1).
        margin: grid border, metres (default 1.0).
        log_odds: the inverse sensor model.
        min_scans: ``build_map`` refuses a laser map from fewer scans used (after
            the ``min_move``/``min_turn`` selection), default 10: a building is not
            covered by fewer, and a log that yields so few is more likely misread
            (time stamps, poses) than short.
        consistency_chunks: the keyframes are split into this many chunks in time
            and each chunk's hits are checked against the other chunks' grid, to
            tell a log whose poses disagree (raw odometry, not corrected poses);
            default 6, 0 turns the check off
            (:mod:`lampsam.localization.laser_consistency`).
        min_consistency: ``build_map`` warns, and the manifest says ``poor``, when
            the fraction of checked hits near the other chunks' walls is below this
            (default 0.75; the Intel log's corrected poses: 0.865, with 0.5 m of
            simulated odometry drift: 0.653).
        min_chunk_consistency: the same, for the worst single chunk (default 0.70;
            the Intel log's corrected poses: worst chunk 0.761, with 0.58 m of drift
            0.598; held out, the simulated campus: true poses 0.984, 4.75 m of drift
            0.543 while its whole-log fraction, 0.761, passes; docs/envmap.md).
    """

    resolution: float = field(default=0.1, metadata=limits(gt=0.0))
    max_range: float = field(default=25.0, metadata=limits(gt=0.0))
    min_move: float = field(default=0.1, metadata=limits(ge=0.0))
    min_turn: float = field(default=0.1, metadata=limits(ge=0.0))
    margin: float = field(default=1.0, metadata=limits(ge=0.0))
    log_odds: LogOddsConfig = field(default_factory=LogOddsConfig)
    min_scans: int = field(default=10, metadata=limits(ge=1))
    consistency_chunks: int = field(default=6, metadata=limits(ge=0))
    min_consistency: float = field(default=0.75, metadata=limits(ge=0.0, le=1.0))
    min_chunk_consistency: float = field(default=0.70, metadata=limits(ge=0.0, le=1.0))

    def __post_init__(self) -> None:
        check_limits(self)


@dataclass(frozen=True)
class EnvMapConfig:
    """Everything ``build_map`` needs.

    Attributes:
        depth: grid from depth.
        laser: grid from laser scans.
        spatial: SIFT extraction and merging.
        feature_every: SIFT on every n-th frame (default 1).
        pose_tolerance: a frame may lie this far outside the trajectory's time span, s
            (default 0.2); farther is a missing pose.
        tables: the lookups precomputed for the localizer (``map_tables.py``).
    """

    depth: DepthGridConfig = field(default_factory=DepthGridConfig)
    laser: LaserGridConfig = field(default_factory=LaserGridConfig)
    spatial: SpatialMapConfig = field(default_factory=SpatialMapConfig)
    feature_every: int = 1
    pose_tolerance: float = 0.2
    tables: TableConfig = field(default_factory=TableConfig)
