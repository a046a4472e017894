"""Configuration of pose-graph edges read from text logs (``[graph]``): the loop closures
of an iSAM / g2o file (:mod:`lampsam.backend.pose_graph`).

A frozen dataclass with documented defaults, checked on construction like the rest of
:mod:`lampsam.backend.config` (which composes it into ``SlamConfig``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lampsam.config_loader import FieldValueError, check_limits, limits


@dataclass(frozen=True)
class PoseGraphConfig:
    """Loop closures of a graph text log (``lampsam slam FILE``; docs/log-format.md).

    Attributes:
        batch_init: where batch LM starts on a log with loop closures: ``"chain"``
            (the odometry chained, dead reckoning, landmarks from their first
            sighting; default), ``"lago"`` (GTSAM's ``lago.initialize`` on the pose
            graph, landmarks placed from their first sighting off it) or
            ``"backend"`` (``[batch] init``: the online iSAM2 pass first). A log
            without loop closures always starts as ``[batch] init`` says. Chosen on
            GTSAM's w10000.graph (chain and LAGO reach the same minimum, chi-square
            289.735, in the same CPU time) and w20000.txt (both stop at LM's 100
            iterations, chi-square 1779 from the chain, 3356 from LAGO; iSAM2
            throws there, GTSAM's own too): docs/log-format.md.
        closure_kernel: robust loss on the loop-closure factors only: ``"none"``
            (Gaussian, default), ``"huber"`` or ``"cauchy"`` (GTSAM's
            ``mEstimator``), for files that may hold wrong closures.
        closure_kernel_k: the kernel's threshold, in sigmas of the closure's own
            covariance (default 3.0).
    """

    batch_init: str = "chain"
    closure_kernel: str = "none"
    closure_kernel_k: float = field(default=3.0, metadata=limits(gt=0.0))

    def __post_init__(self) -> None:
        """Check the declared ranges and names (:class:`FieldValueError` naming the key)."""
        check_limits(self)
        if self.batch_init not in ("lago", "chain", "backend"):
            raise FieldValueError("batch_init", "must be 'lago', 'chain' or 'backend', got "
                                  f"{self.batch_init!r}")
        if self.closure_kernel not in ("none", "huber", "cauchy"):
            raise FieldValueError("closure_kernel", "must be 'none', 'huber' or 'cauchy', got "
                                  f"{self.closure_kernel!r}")
