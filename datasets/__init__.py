"""lampsam.datasets: Logged runs and where they come from: the run format, its readers and writers, the
simulators (ceiling camera, Kinect, stereo) and the public-dataset adapters. The
simulators import no estimator code, so the truth they give is independent.

Entry points (loaded on first use)::

    read_run               read a logged run directory (logrun)
    write_run              write a logged run directory (logrun)
    LoggedRun              a logged run in memory (logrun)
    simulate_world         simulate a ceiling-camera run of a world (simulator)
    simulate_kinect_run    simulate a Kinect mapping drive (TUM RGB-D layout) (kinect_sim)
    simulate_stereo_run    simulate a stereo two-point run (stereo_sim)
    read_stereo_run        read a stereo run directory (stereo_sim)
    read_carmen            read a CARMEN laser log (carmen)
    read_mrclam            read the MRCLAM dataset (mrclam)
    read_tum               read a planar TUM trajectory (tum)
    write_tum              write a TUM trajectory (tum)

Modules:

* :mod:`~lampsam.datasets.calibration` -- Camera calibration files: ROS ``camera_info`` YAML and OpenCV ``FileStorage`` YAML.
* :mod:`~lampsam.datasets.camera` -- The ceiling camera: intrinsics, lens model and mounting on the robot body.
* :mod:`~lampsam.datasets.carmen` -- Reader for CARMEN laser logs (the Intel Research Lab log and logs of other buildings).
* :mod:`~lampsam.datasets.ceiling_truth` -- True image projections of simulated ceiling landmarks, independent of the renderer.
* :mod:`~lampsam.datasets.g2o_writer` -- Write a planar pose graph as a g2o text file (readable by g2o, GTSAM's ``readG2o``, ...).
* :mod:`~lampsam.datasets.graph_text` -- Readers for the planar SLAM text formats that ``gtsam.load2D`` reads (iSAM and g2o).
* :mod:`~lampsam.datasets.kinect_sim` -- A forward-facing Kinect-like RGB-D sensor rendered from a :mod:`scene3d` world.
* :mod:`~lampsam.datasets.kitti` -- KITTI odometry stereo sequence reader (rectified grey pairs, calib.txt, poses.txt).
* :mod:`~lampsam.datasets.landmark_log_heldout` -- Held-out synthetic landmark logs: layouts and noise unlike the tuning logs, with truth.
* :mod:`~lampsam.datasets.landmark_log_sim` -- Synthetic planar landmark-SLAM logs in the iSAM text format, with ground truth.
* :mod:`~lampsam.datasets.localization_run` -- A simulated run for global localization: start at an unknown pose, turn, drive on, repeat.
* :mod:`~lampsam.datasets.logrun` -- The logged-run directory: what it holds, and reading or writing it whole (``docs/log-format.md``).
* :mod:`~lampsam.datasets.motion` -- True motion of a differential-drive robot along waypoints, and wheel-slip noise.
* :mod:`~lampsam.datasets.mounting` -- Camera mounting: a tilted or offset ceiling camera from roll, pitch and yaw.
* :mod:`~lampsam.datasets.mrclam` -- Adapter for the UTIAS MRCLAM dataset (one robot, ``ds0_RS_*`` resampled at 50 Hz, or the dataset as distributed: ``MRCLAM_DatasetN/Robot1_Odometry.dat`` ..., robot 1; :func:`mrclam_files`).
* :mod:`~lampsam.datasets.odometry` -- Odometry as relative ``Pose2`` increments in the logged-run format (beside wheel travel).
* :mod:`~lampsam.datasets.openings` -- Daylight openings of a simulated ceiling: skylights and windows.
* :mod:`~lampsam.datasets.paths` -- Where the shared real-data folder is.
* :mod:`~lampsam.datasets.render_ceiling` -- Ceiling images by ray casting, and the true projections of landmarks, from geometry only.
* :mod:`~lampsam.datasets.rgbd` -- Readers of RGB-D sequences: the TUM RGB-D layout and the slambook2 sample.
* :mod:`~lampsam.datasets.rig` -- The sensor rig of a logged run (``rig.yaml``): ceiling camera and wheel odometry.
* :mod:`~lampsam.datasets.robot_frames` -- What a robot records while it turns in place and while it drives on (paper 2, sec. 4).
* :mod:`~lampsam.datasets.ros_messages` -- Conversions between ROS messages (as ``rosbags`` builds them) and lampsam arrays.
* :mod:`~lampsam.datasets.rosbag_build` -- What a bag's streams become (:mod:`lampsam.datasets.rosbag_import`): the rig and the odometry.
* :mod:`~lampsam.datasets.rosbag_export` -- Write a logged run as a ROS1 ``.bag`` or a ROS2 bag (``rosbags``, no ROS install).
* :mod:`~lampsam.datasets.rosbag_import` -- Read a ROS1 ``.bag`` or ROS2 bag (``.db3`` / ``.mcap``) into a logged run (``rosbags``).
* :mod:`~lampsam.datasets.rosbag_streams` -- One pass over a bag's chosen topics (:mod:`lampsam.datasets.rosbag_import`).
* :mod:`~lampsam.datasets.scan_times` -- Strictly increasing scan times from the time stamps a laser log gives (CARMEN reader).
* :mod:`~lampsam.datasets.scene3d` -- Three-dimensional world content for the forward RGB-D sensor (paper 2, sec. 2).
* :mod:`~lampsam.datasets.scene_mesh` -- Meshes and picture textures of a :class:`~lampsam.datasets.scene3d.Scene3D` for the RGB-D renderer.
* :mod:`~lampsam.datasets.shapes` -- Signed distance functions of the simulated ceiling's planar shapes (rectangles, discs).
* :mod:`~lampsam.datasets.simulator` -- Simulated ceiling-camera runs: ``lampsam simulate WORLD --out RUN``.
* :mod:`~lampsam.datasets.steerable_robot` -- A simulated robot the global localizer can steer: turn in place, drive on, frames back.
* :mod:`~lampsam.datasets.stereo_sim` -- Stereo two-point runs: the simulator of paper 3 and the run-directory format.
* :mod:`~lampsam.datasets.stereo_types` -- Stereo two-point runs as plain data: the rig, the noise model and a run (paper 3).
* :mod:`~lampsam.datasets.tables` -- The tables of a logged run: in-memory types, readers and writers (``docs/log-format.md``).
* :mod:`~lampsam.datasets.textio` -- Reading text files with errors that name the file and the 1-based line.
* :mod:`~lampsam.datasets.tum` -- TUM trajectory files: one parser with a planar and a 3-D view, and the writer.
* :mod:`~lampsam.datasets.world` -- Ceiling worlds: YAML files describing ceilings, lamps, the rig and the robot's path.
* :mod:`~lampsam.datasets.world_landmarks` -- True landmarks of a ceiling world: its lamps and the corners derived from its surfaces.
"""

from lampsam._lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, {
    "read_run": "lampsam.datasets.logrun",
    "write_run": "lampsam.datasets.logrun",
    "LoggedRun": "lampsam.datasets.logrun",
    "simulate_world": "lampsam.datasets.simulator",
    "simulate_kinect_run": "lampsam.datasets.kinect_sim",
    "simulate_stereo_run": "lampsam.datasets.stereo_sim",
    "read_stereo_run": "lampsam.datasets.stereo_sim",
    "read_carmen": "lampsam.datasets.carmen",
    "read_mrclam": "lampsam.datasets.mrclam",
    "read_tum": "lampsam.datasets.tum",
    "write_tum": "lampsam.datasets.tum",
})
