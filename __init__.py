"""lampsam: where an indoor wheeled robot is, and its map.

Ceiling-lamp SLAM (upward camera + wheel odometry), global localization on an
environment map (Kinect grid map, SIFT spatial features, ceiling features), and
stereo two-point relative pose, estimated with GTSAM factor graphs (batch and
iSAM2) and, for parity with the papers, an EKF.

Data flows one way; a later stage may import an earlier one, never the reverse::

    datasets -> frontend -> factors -> backend -> localization -> evaluation -> cli

Entry points (loaded on first use, so ``import lampsam`` stays cheap):

====================  ===========================================================
``simulate_world``    simulate a ceiling-camera run of a world into a logged run
``read_run``          read a logged run directory (images, odometry, rig, truth)
``process_image``     lamps and corners of one ceiling image (the frontend)
``iter_run``          the frontend over a logged run, frame by frame
``make_backend``      an EKF, iSAM2 or batch SLAM backend, fed step by step
``iter_steps``        merge odometry and frames into time-ordered backend steps
``run_slam``          one backend over a whole logged run, results written
``SlamConfig``        the SLAM configuration (TOML tables ``[isam2]``, ``[ekf]``, ...)
``load_config``       a config dataclass from a TOML/YAML file, strictly checked
``build_map``         an environment map (grid, spatial features, ceiling) from a run
``load_env_map``      read an environment map directory
``localize_run``      global localization of a logged or simulated run on a map
``compare``           EKF against smoothing over runs and seeds, with a report
====================  ===========================================================

Each subpackage names its own entry points the same way; see
``docs/architecture.md`` for the layout and the contracts between stages, and
``docs/conventions.md`` for frames, axes and angles.
"""

from lampsam._lazy import lazy_exports

__version__ = "0.1.0"

__getattr__, __dir__ = lazy_exports(__name__, {
    "simulate_world": "lampsam.datasets.simulator",
    "read_run": "lampsam.datasets.logrun",
    "process_image": "lampsam.frontend.pipeline",
    "iter_run": "lampsam.frontend.pipeline",
    "make_backend": "lampsam.backend.slam",
    "iter_steps": "lampsam.backend.slam",
    "run_slam": "lampsam.backend.slam",
    "SlamConfig": "lampsam.backend.config",
    "load_config": "lampsam.config_loader",
    "build_map": "lampsam.localization.map_build",
    "load_env_map": "lampsam.localization.map_store",
    "localize_run": "lampsam.localization.replay",
    "compare": "lampsam.evaluation.compare",
}, eager=("__version__",))
