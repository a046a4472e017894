"""lampsam: where an indoor wheeled robot is, and its map.

Ceiling-lamp SLAM (upward camera + wheel odometry), global localization on an
environment map (Kinect grid map, SIFT spatial features, ceiling features), and
stereo two-point relative pose, estimated with GTSAM factor graphs (batch and
iSAM2) and, for parity with the papers, an EKF.

Data flows one way; a later stage may import an earlier one, never the reverse::

    datasets -> frontend -> factors -> backend -> localization -> evaluation -> cli

See ``docs/architecture.md`` for the contracts between stages and
``docs/conventions.md`` for frames, axes and angle conventions.
"""

__version__ = "0.1.0"
