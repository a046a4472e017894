"""lampsam.factors: pure measurement/motion models with analytic Jacobians + GTSAM adapters.

Modules (import them directly; this package imports nothing so that importing one
model does not load the others):

* :mod:`~lampsam.factors.geometry` -- ``wrap_angle``, ``wrap_axis``, ``rot2``,
  ``coords_D_tangent`` / ``tangent_D_coords``, planar pose algebra, ``FactorError``.
* :mod:`~lampsam.factors.motion` -- differential drive (paper 1 eqs. 13-15):
  ``diff_drive_step``, ``wheel_noise_cov``, ``accumulate_odometry``, ``odometry_between``.
* :mod:`~lampsam.factors.range_bearing` -- ``range_bearing`` ([bearing, range], GTSAM order).
* :mod:`~lampsam.factors.ceiling` -- upward camera: ``project_point``, ``lamp_axis``,
  inverse-depth corners, ``init_point_from_observation`` (eqs. 24-25), ``HeightPrior``.
* :mod:`~lampsam.factors.gtsam_factors` -- GTSAM factors over the above (built-in where
  one exists, ``CustomFactor`` otherwise, per observation or per frame).
* :mod:`~lampsam.factors.axis_factors` -- GTSAM factors of a lamp's long axis ``A(j)``
  (paper 1 III.4: the axis angle mod pi).
* :mod:`~lampsam.factors.inverse_depth_factors` -- GTSAM factors of inverse-depth ceiling
  corners ``C(j) = (alpha_x, alpha_y, rho)`` (per observation or per frame).
* :mod:`~lampsam.factors.pose2_odometry` -- odometry as relative ``Pose2`` increments with
  their own covariance.
* :mod:`~lampsam.factors.max_mixture` -- max-mixture range-bearing factor (Olson & Agarwal):
  one sighting, several candidate landmarks, or none.
* :mod:`~lampsam.factors.stereo` -- stereo two-point model (paper 3).

Pose Jacobians are w.r.t. GTSAM's right tangent of ``Pose2`` (docs/conventions.md),
except ``diff_drive_step``, which gives the EKF's plain-coordinate Jacobians.
"""
