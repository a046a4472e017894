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
        batch_init: where batch LM starts on a log with loop closures: ``"backend"``
            (``[batch] init``: by default the online iSAM2 pass, default), ``"chain"``
            (the odometry chained, dead reckoning, landmarks from their first
            sighting) or ``"lago"`` (GTSAM's ``lago.initialize`` on the pose graph,
            each edge's covariance cut to its diagonal, landmarks placed from their
            first sighting off it). A log without loop closures always starts as
            ``[batch] init`` says. Chosen on GTSAM's w20000.txt, where LM from the
            chain or LAGO stops in local minima (chi-square 1779 and 3356-4032 after
            LM's 100 iterations) while iSAM2 (QR) ends at 37.5; on w10000.graph all
            reach the same minimum, the iSAM2 pass at 66 times the CPU of LM from the
            chain (160 s against 2.4 s): ``"chain"`` is the fast choice for a graph
            that converges from dead reckoning (docs/log-format.md).
        isam2_factorization: GTSAM's ISAM2 factorization on a log with loop closures,
            ``"QR"`` (default) or ``"CHOLESKY"`` (GTSAM's default, and lampsam's on
            logs without closures): with Cholesky, GTSAM's own iSAM2 throws
            "indeterminate linear system" at pose 1191 of w20000.txt (16,601 of 20,061
            updates fail), QR runs through.
        closure_kernel: robust loss on the loop-closure factors only: ``"none"``
            (Gaussian, default), ``"huber"`` or ``"cauchy"`` (GTSAM's
            ``mEstimator``), for files that may hold wrong closures.
        closure_kernel_k: the kernel's threshold, in sigmas of the closure's own
            covariance (default 3.0).
    """

    batch_init: str = "backend"
    isam2_factorization: str = "QR"
    closure_kernel: str = "none"
    closure_kernel_k: float = field(default=3.0, metadata=limits(gt=0.0))

    def __post_init__(self) -> None:
        """Check the declared ranges and names (:class:`FieldValueError` naming the key)."""
        check_limits(self)
        if self.batch_init not in ("lago", "chain", "backend"):
            raise FieldValueError("batch_init", "must be 'lago', 'chain' or 'backend', got "
                                  f"{self.batch_init!r}")
        if self.isam2_factorization not in ("QR", "CHOLESKY"):
            raise FieldValueError("isam2_factorization", "must be 'QR' or 'CHOLESKY', got "
                                  f"{self.isam2_factorization!r}")
        if self.closure_kernel not in ("none", "huber", "cauchy"):
            raise FieldValueError("closure_kernel", "must be 'none', 'huber' or 'cauchy', got "
                                  f"{self.closure_kernel!r}")
