"""lampsam.localization: Global localization on an environment map (paper 2): grid maps, the spatial and
ceiling feature maps, ray casting and scan likelihoods, the particle filter, SVD
candidates and verification on the ceiling map; laser-scan localization.

Entry points (loaded on first use)::

    build_map                build an environment map from a run (map_build)
    load_env_map             read an environment map directory (map_store)
    localize                 global localization of a steerable robot (localizer)
    localize_run             global localization of a logged run (replay)
    GlobalLocalizerConfig    global localizer settings (filter_config)
    localize_scans           laser-scan global localization (laser)
    OccupancyGrid            log-odds occupancy grid, map_server I/O (grid)

Modules:

* :mod:`~lampsam.localization.acceptance` -- Whether a scan-only estimate can be trusted: its margin over the best competing mode.
* :mod:`~lampsam.localization.alignment` -- SVD alignment of matched 3-D points, with RANSAC over the correspondences.
* :mod:`~lampsam.localization.candidates` -- Pose candidates from SIFT matches to the spatial feature map (paper 2, sec. 3).
* :mod:`~lampsam.localization.ceiling_map` -- The ceiling feature map: lamps and corners of the ceiling SLAM (paper 2, sec. 2.2).
* :mod:`~lampsam.localization.correlative` -- Global scan matching over a whole grid map by branch and bound.
* :mod:`~lampsam.localization.depth_grid` -- Grid map and spatial feature map from RGB-D frames (paper 2, sec. 2.1-2.2).
* :mod:`~lampsam.localization.filter_config` -- Settings of the global localizer: the Table-1 configuration and each stage's options.
* :mod:`~lampsam.localization.grid` -- Log-odds occupancy grids and ROS map_server files.
* :mod:`~lampsam.localization.laser` -- Global localization from planar laser scans on a grid map, from no prior knowledge.
* :mod:`~lampsam.localization.laser_consistency` -- Do a laser log's poses agree with each other? A cross-check of its scans.
* :mod:`~lampsam.localization.laser_grid` -- Grid map from planar laser scans at known poses (CARMEN logs, LaserScan runs).
* :mod:`~lampsam.localization.likelihood` -- Measurement models of the particle filter: scan log-likelihood per particle.
* :mod:`~lampsam.localization.localizer` -- Global localization on the environment map (paper 2, secs. 3-4, Fig. 11).
* :mod:`~lampsam.localization.map_build` -- Building the environment map of a mapping run (paper 2, sec. 2).
* :mod:`~lampsam.localization.map_config` -- Configuration of the environment map build: depth grid, laser grid, SIFT layer.
* :mod:`~lampsam.localization.map_layers` -- The environment map's layers as the global localizer uses them (paper 2, sec. 2).
* :mod:`~lampsam.localization.map_poses` -- Where the mapping sensor was: pose sources for the map build.
* :mod:`~lampsam.localization.map_quality` -- Grid-map quality against a known floor plan: occupied-cell precision and recall.
* :mod:`~lampsam.localization.map_store` -- The environment map directory: its files, its manifest, reading and writing it.
* :mod:`~lampsam.localization.map_tables` -- Lookup tables precomputed from the grid and stored in the map directory.
* :mod:`~lampsam.localization.open_space` -- Facing open space before the verification drive, from the robot's own virtual scan.
* :mod:`~lampsam.localization.particle_filter` -- Particle filter on a grid map (paper 2, sec. 4; DESIGN.md sec. 2, step 2).
* :mod:`~lampsam.localization.pointcloud` -- Depth images to point clouds with Open3D, placed in the world with poses.
* :mod:`~lampsam.localization.raycast` -- Expected ranges in a grid map, for many poses x many beams, vectorised.
* :mod:`~lampsam.localization.replay` -- A logged run replayed in time order as a robot, and global localization of a run.
* :mod:`~lampsam.localization.result` -- What a global localization returns and writes (``OUT/result.json``).
* :mod:`~lampsam.localization.robot` -- The robot as the global localizer sees it: turn in place, drive on, frames back.
* :mod:`~lampsam.localization.spatial_map` -- The spatial feature map: SIFT keypoints with 3-D world positions (paper 2, sec. 2.3).
* :mod:`~lampsam.localization.stages` -- The turn and filter stages of global localization (paper 2, secs. 3-4.1, Fig. 11).
* :mod:`~lampsam.localization.symmetry` -- Half-turn symmetry of a ceiling map, and telling a pose from its twin by the scan.
* :mod:`~lampsam.localization.verification` -- Verification of a global-localization result with the ceiling feature map.
* :mod:`~lampsam.localization.verify_drive` -- The verification stage: drive on and test the pose on the ceiling (paper 2, sec. 4.2).
* :mod:`~lampsam.localization.virtual_scan` -- The paper's "virtual map": a 360-degree scan assembled while turning in place.
"""

from lampsam._lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, {
    "build_map": "lampsam.localization.map_build",
    "load_env_map": "lampsam.localization.map_store",
    "localize": "lampsam.localization.localizer",
    "localize_run": "lampsam.localization.replay",
    "GlobalLocalizerConfig": "lampsam.localization.filter_config",
    "localize_scans": "lampsam.localization.laser",
    "OccupancyGrid": "lampsam.localization.grid",
})
