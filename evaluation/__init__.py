"""lampsam.evaluation: Metrics, experiments and reports: the backend comparison, the frontend against
truth, Table 1 of paper 2, laser localization trials. The only stage that plots.

Entry points (loaded on first use)::

    compare         EKF against smoothing over runs and seeds, with a report (compare)
    run_demo        the demo job (demo)
    evaluate_run    the frontend against the simulator's truth (frontend_eval)
    run_table1      paper 2's Table 1 trials (table1)
    laser_trials    laser localization trials on a CARMEN log (laser_trials)

Modules:

* :mod:`~lampsam.evaluation.batch` -- Offline optimisation of many logs: one result folder per run and a summary.
* :mod:`~lampsam.evaluation.compare` -- Compare SLAM backends (EKF against smoothing) over runs and Monte Carlo seeds.
* :mod:`~lampsam.evaluation.compare_plots` -- Figures of the backend comparison (paper 1, Figs. 9, 10, 12, and more).
* :mod:`~lampsam.evaluation.compare_report` -- The comparison report: ``report.md``, ``report.html`` and ``summary.json``.
* :mod:`~lampsam.evaluation.contact_sheet` -- Contact sheet of a simulated run: frames with the true lamp and corner projections.
* :mod:`~lampsam.evaluation.demo` -- The demo job (``lampsam demo`` / ``make demo``): the main job on the built-in world.
* :mod:`~lampsam.evaluation.fleet` -- Run many independent jobs: a local process pool, or a Dask ``distributed`` cluster.
* :mod:`~lampsam.evaluation.frontend_eval` -- The ceiling frontend measured against truth.
* :mod:`~lampsam.evaluation.frontend_synthetic` -- A small independent renderer of ceiling images with truth, for the frontend's tests.
* :mod:`~lampsam.evaluation.gallery` -- Overlay gallery of the ceiling frontend on real photos (``lampsam gallery``).
* :mod:`~lampsam.evaluation.held_plots` -- Per-pose error along a drive against a reference trajectory, with where the sightings an online run left out were made (issue 15, docs/noids-offline.md "Placing the held sightings"). Plot only: the estimates come finished.
* :mod:`~lampsam.evaluation.lamp_plots` -- Figures of the lamp measurement studies: centroid error by grid tilt and by cause.
* :mod:`~lampsam.evaluation.laser_trials` -- Laser global-localization trials on a CARMEN log, scored against its corrected poses.
* :mod:`~lampsam.evaluation.live` -- Live view of a run in Rerun (``--rerun [FILE.rrd | ADDRESS]`` on ``slam``, ``localize``, ``stereo``).
* :mod:`~lampsam.evaluation.map_alignment` -- Errors in a map's own frame: the map-to-world rigid transform, fitted on landmarks.
* :mod:`~lampsam.evaluation.map_plots` -- Drawing the environment map: grid, spatial features and ceiling features in one figure.
* :mod:`~lampsam.evaluation.map_truth` -- The true floor plan of a simulated run, for the grid map's quality checks.
* :mod:`~lampsam.evaluation.metrics` -- Accuracy and consistency metrics for planar trajectories and landmark maps.
* :mod:`~lampsam.evaluation.outputs` -- Outputs of the evaluation jobs: directories created up front, figures written atomically.
* :mod:`~lampsam.evaluation.photo_augment` -- Photo robustness: the labelled photos under known transforms, scored per transform family.
* :mod:`~lampsam.evaluation.photo_eval` -- The lamp detector measured against hand labels of real photos (``lampsam frontend-eval --photos``).
* :mod:`~lampsam.evaluation.photo_labels` -- Hand labels of real ceiling photos: the file format, its reader, and the labelling tool.
* :mod:`~lampsam.evaluation.scaling_plots` -- Cost-versus-map-size scaling: a power-law fit and its log-log figure.
* :mod:`~lampsam.evaluation.slam_report` -- SLAM reports: map + path plot against ground truth, and comparison tables.
* :mod:`~lampsam.evaluation.stereo_experiment` -- The stereo two-point experiment of paper 3 (Figs. 3-5): seeds x scenarios x estimators.
* :mod:`~lampsam.evaluation.stereo_report` -- Stereo two-point relative pose: errors, tables, figures (paper 3, Figs. 3-5), run outputs.
* :mod:`~lampsam.evaluation.table1` -- Paper 2's Table 1 on the simulated ``office`` world: the trials (``lampsam table1``).
* :mod:`~lampsam.evaluation.table1_plots` -- Figures of the global-localization experiment (paper 2, Table 1).
* :mod:`~lampsam.evaluation.table1_report` -- The Table-1 report: the Markdown table, the figure and the collected trial records.
* :mod:`~lampsam.evaluation.twin_ids` -- Twin file ids: one tree under two ids in a graph log, and the reference with them merged.
"""

from lampsam._lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, {
    "compare": "lampsam.evaluation.compare",
    "run_demo": "lampsam.evaluation.demo",
    "evaluate_run": "lampsam.evaluation.frontend_eval",
    "run_table1": "lampsam.evaluation.table1",
    "laser_trials": "lampsam.evaluation.laser_trials",
})
