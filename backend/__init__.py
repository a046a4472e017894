"""lampsam.backend: SLAM backends behind one interface: the papers' EKF, iSAM2 (online) and batch
Levenberg-Marquardt (offline) on GTSAM factor graphs; data association; the stereo
two-point estimators.

Entry points (loaded on first use)::

    make_backend    an EKF, iSAM2 or batch backend, fed step by step (slam)
    iter_steps      merge odometry and frames into steps (slam)
    run_slam        one backend over a whole logged run (slam)
    SlamConfig      the SLAM configuration (config)
    SlamBackend     the backends' common interface (interface)
    SlamResult      what a backend returns (interface)
    estimate        a stereo two-point estimator over a stereo run (stereo)

Modules:

* :mod:`~lampsam.backend.alias_gate` -- The alias test: a range-bearing match must beat "a landmark not yet mapped" (no ids).
* :mod:`~lampsam.backend.association` -- Data association shared by the EKF, iSAM2 and batch backends (paper 1, eqs. 19-20).
* :mod:`~lampsam.backend.ceiling` -- The upward-camera observation model as the backends use it (wraps :mod:`lampsam.factors.ceiling`).
* :mod:`~lampsam.backend.ceiling_graph` -- Ceiling landmarks in the factor graphs (lamps and corners), via :mod:`lampsam.factors.gtsam_factors`.
* :mod:`~lampsam.backend.ceiling_map_io` -- The saved ceiling map: write it once after mapping, read it back every day.
* :mod:`~lampsam.backend.config` -- Configuration of the SLAM backends: frozen dataclasses with documented defaults.
* :mod:`~lampsam.backend.config_association` -- Configuration of data association (``[association]``): the gate, landmark initialisation and pruning, and the no-ids options, shared by every backend.
* :mod:`~lampsam.backend.config_graph` -- Configuration of pose-graph edges read from text logs (``[graph]``): the loop closures of an iSAM / g2o file (:mod:`lampsam.backend.pose_graph`).
* :mod:`~lampsam.backend.config_offline` -- Configuration of the offline passes: batch Levenberg-Marquardt (``[batch]``) and the batch re-association without ids (``[reassociation]``).
* :mod:`~lampsam.backend.constellation` -- Revisit detection by constellation: a 2-D rigid alignment of recent landmarks to the map.
* :mod:`~lampsam.backend.covariance` -- A growable symmetric covariance kept as its lower triangle, updated in place by BLAS.
* :mod:`~lampsam.backend.cpu_budget` -- CPU budgets of the no-ids final solves: stop cleanly, keep what is finished (issue 15).
* :mod:`~lampsam.backend.dense_log` -- Known-id fast path of the smoothers over a planar landmark log, one step per pose.
* :mod:`~lampsam.backend.ekf` -- The paper's EKF-SLAM (paper 1, eqs. 13-25), exploiting the sparsity of its Jacobians.
* :mod:`~lampsam.backend.ekf_gate` -- The EKF's vectorised gate (paper 1, eqs. 19-20): a frame's candidates and distances.
* :mod:`~lampsam.backend.ekf_joint` -- Joint compatibility (JCBB) for the EKF's planar observations without ids (eqs. 19-20).
* :mod:`~lampsam.backend.ekf_landmarks` -- Landmark book-keeping of the EKF state.
* :mod:`~lampsam.backend.ekf_map` -- The EKF's map: landmarks added (paper 1, eqs. 24-25), merged and pruned.
* :mod:`~lampsam.backend.ekf_state` -- The EKF's state, prediction (paper 1, eqs. 13-15) and innovations (eq. 19).
* :mod:`~lampsam.backend.ekf_update` -- The EKF's stacked measurement update and gathered innovation covariances (eqs. 19-23).
* :mod:`~lampsam.backend.final_moves` -- The last pass of offline association without ids: single sightings, and merges with the poses free, by description length.
* :mod:`~lampsam.backend.fixed_lag` -- Fixed-lag smoothing for the online iSAM2 backend (``[isam2] fixed_lag``, keyframes).
* :mod:`~lampsam.backend.g2o_export` -- A SLAM result as a g2o graph file (``lampsam slam ... --g2o OUT.g2o``).
* :mod:`~lampsam.backend.gate_bracket` -- A bracket of the exact gate distance from the pose and landmark marginals alone (issue 19).
* :mod:`~lampsam.backend.gate_exact` -- The exact gate of a factor-graph backend: eq.-19 innovations with the pose-landmark cross-covariance.
* :mod:`~lampsam.backend.gate_shortcuts` -- Lamp-gate shortcuts: settle a lamp pair without iSAM2's joint marginal when the decision is known.
* :mod:`~lampsam.backend.gating` -- Gating of a factor-graph backend: the screen of a keyframe's observations (paper eqs. 19-20).
* :mod:`~lampsam.backend.graph` -- Factor-graph backends: iSAM2 (online) and batch Levenberg-Marquardt (offline).
* :mod:`~lampsam.backend.graph_log` -- SLAM on a graph text log (iSAM ``ODOMETRY``/``LANDMARK``, g2o; e.g. GTSAM's ``victoria_park.txt``): one step per pose, each sighting with its own covariance.
* :mod:`~lampsam.backend.graph_state` -- The state a factor-graph backend keeps, and the primitives every part of it uses.
* :mod:`~lampsam.backend.handlers` -- How a landmark kind lives in the factor graph: the handler protocol and its record.
* :mod:`~lampsam.backend.held_placement` -- Placing the sightings an online run held, in the final solve, by max-mixture factors.
* :mod:`~lampsam.backend.held_sightings` -- Held range-bearing sightings without ids: held while ambiguous, given back once not.
* :mod:`~lampsam.backend.innovation_scale` -- Online robust scale of the association gate's normalised innovations (``[association] odometry_noise_adapt``; shared by the EKF and the smoothers).
* :mod:`~lampsam.backend.interface` -- One interface for the three SLAM backends (``ekf``, ``isam2``, ``batch``).
* :mod:`~lampsam.backend.isam2_update` -- iSAM2 updates of a factor-graph backend, and recovery from a failed one.
* :mod:`~lampsam.backend.joint_gating` -- Joint compatibility for the smoothers' range-bearing observations without ids.
* :mod:`~lampsam.backend.keyframes` -- Keyframe policy of the factor-graph backends.
* :mod:`~lampsam.backend.label_entropy` -- The label entropy of an association: what the online picker's ``C`` adds so that a landmark split in overlapping copies does not win (no ids).
* :mod:`~lampsam.backend.landmark_merge` -- Merging duplicate planar landmarks after the fact (association without ids).
* :mod:`~lampsam.backend.landmark_moves` -- Merge and split landmarks by description length (offline association without ids).
* :mod:`~lampsam.backend.landmarks` -- Landmark lifecycle in a factor-graph backend: start, observe, triangulate, insert, prune.
* :mod:`~lampsam.backend.localize_config` -- Configuration of localize-only tracking on a saved ceiling map (:class:`LocalizeConfig`).
* :mod:`~lampsam.backend.localize_only` -- Localize-only tracking against a saved ceiling map: the map is used, never grown.
* :mod:`~lampsam.backend.localize_run` -- Run localize-only tracking over a logged run, and save the map of a SLAM run.
* :mod:`~lampsam.backend.map_calibration` -- How honest a batch map's landmark covariances are, measured on the mapping run itself.
* :mod:`~lampsam.backend.map_frame` -- The map's frame uncertainty: the common part of a batch map's landmark errors.
* :mod:`~lampsam.backend.map_merge` -- Merge ceiling maps of the same floor made on separate mapping drives.
* :mod:`~lampsam.backend.map_release` -- Releasing map landmarks that today's sightings contradict (lifelong localize-only).
* :mod:`~lampsam.backend.map_smoother` -- Localize-only smoothing: the run's poses and the used map landmarks in one factor graph.
* :mod:`~lampsam.backend.mapping_worker` -- The mapping worker of :mod:`lampsam.backend.tracking`: the backend stepped in its own process.
* :mod:`~lampsam.backend.models` -- Observation models as the backends see them: one record type, one predict/init API.
* :mod:`~lampsam.backend.noids_offline` -- Offline SLAM without ids on a graph log: online EKF pass, batch re-association, scale choice.
* :mod:`~lampsam.backend.odometry` -- Odometry as the backends see it: a motion model over a step's odometry samples.
* :mod:`~lampsam.backend.odometry_scale` -- Online odometry noise scale by covariance matching on landmark innovations.
* :mod:`~lampsam.backend.online_final` -- The final solve of an online run without ids on a graph log: its association re-solved in batch at the log's stated noise (issue 15).
* :mod:`~lampsam.backend.online_run` -- ``lampsam slam RUN --online decoupled``: a whole SLAM run with tracking decoupled from mapping.
* :mod:`~lampsam.backend.pipelined` -- Frontend and estimator overlapped: ceiling frames made ahead in a worker.
* :mod:`~lampsam.backend.planar_gate` -- Vectorised range-bearing prediction and gate against every planar landmark (eqs. 19-20).
* :mod:`~lampsam.backend.pose_cov` -- Pose-covariance algebra on SE(2) in GTSAM's right tangent (docs/conventions.md).
* :mod:`~lampsam.backend.pose_graph` -- Loop closures of a graph text log as factors, and the batch start on a graph with them.
* :mod:`~lampsam.backend.reassociate` -- Batch association without ids: re-associate every sighting against the optimised map.
* :mod:`~lampsam.backend.revisit_merge` -- Revisit check without ids: the local scan matched to the older map by constellation.
* :mod:`~lampsam.backend.slam` -- Run a SLAM backend over a logged run, and write its results.
* :mod:`~lampsam.backend.stereo` -- Stereo two-point relative pose estimators (paper 3): raw, EKF, iSAM2, batch.
* :mod:`~lampsam.backend.stereo_kitti` -- Stereo two-point relative pose on real KITTI images: pair selection and check.
* :mod:`~lampsam.backend.tracking` -- Tracking decoupled from mapping: per-frame poses from odometry, keyframe work in a worker.
"""

from lampsam._lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, {
    "make_backend": "lampsam.backend.slam",
    "iter_steps": "lampsam.backend.slam",
    "run_slam": "lampsam.backend.slam",
    "SlamConfig": "lampsam.backend.config",
    "SlamBackend": "lampsam.backend.interface",
    "SlamResult": "lampsam.backend.interface",
    "estimate": "lampsam.backend.stereo",
})
