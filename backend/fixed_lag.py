"""Fixed-lag smoothing for the online iSAM2 backend (``[isam2] fixed_lag``, keyframes).

With ``fixed_lag = N > 0`` the online backend sends each keyframe's factors to GTSAM's
``IncrementalFixedLagSmoother`` instead of a bare ``ISAM2`` (the reads, the gate's joint
marginals and the pose marginal go to the smoother's own ``ISAM2``, ``getISAM2()``, a
live reference). Every key carries a timestamp in keyframes: a new variable gets the
keyframe's index, and so does every variable a factor of the keyframe touches, so
what is still observed stays in the window; a variable not touched for ``N``
keyframes is marginalised out (its information kept as a dense prior on its
neighbours: Kaess et al. 2012, sec. 6 of the iSAM2 paper; GTSAM's
``IncrementalFixedLagSmoother``). The update cost is then bounded by the window, not
the run's length.

Lamps are re-stamped at every keyframe and so never leave: they are few (11 on the
lab path), and they carry the revisits' loop closures, which a marginalised lamp
would lose (a landmark that left the window can no longer be a variable of a new
factor). Corners and poses that left are gone from the smoother: a corner is removed
from the backend's landmarks (seen again, it is a new corner) and a pose keeps the
estimate it had when it left (the final trajectory uses it). Measured in
docs/speed.md ("Fixed lag").
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import SupportsFloat, SupportsIndex, SupportsInt

import gtsam

#: key -> timestamp (keyframes), as ``IncrementalFixedLagSmoother.update`` takes it
Stamps = dict[SupportsInt | SupportsIndex, SupportsFloat | SupportsIndex]


def keyframe_stamps(k: int, values: gtsam.Values, graph: gtsam.NonlinearFactorGraph,
                    lamp_keys: Iterable[int]) -> Stamps:
    """Timestamps to send with keyframe ``k``'s update: ``k`` for every new variable, every
    variable a new factor touches, and every lamp key already in the smoother.

    Args:
        k: the keyframe index (the smoother's clock, in keyframes).
        values: the update's new variables; graph: its new factors.
        lamp_keys: the keys of the lamps (``L(j)``, ``A(j)``) in the smoother.
    """
    stamps: Stamps = {int(key): float(k) for key in values.keys()}
    for i in range(graph.size()):
        f = graph.at(i)
        if f is not None:
            stamps.update({int(key): float(k) for key in f.keys()})
    stamps.update({int(key): float(k) for key in lamp_keys})
    return stamps


def left_window(smoother: gtsam.IncrementalFixedLagSmoother, alive: set[int]) -> set[int]:
    """The keys of ``alive`` the smoother no longer holds (marginalised by its last update)."""
    now = set(smoother.timestamps().keys())
    return {key for key in alive if key not in now}


def without_keys(graph: gtsam.NonlinearFactorGraph, gone: set[int]) -> gtsam.NonlinearFactorGraph:
    """``graph`` without the factors that touch a key in ``gone`` (the same object if none does).

    A corner's buffered sights enter the graph when it is triangulated, up to
    ``corner_pending_keyframes`` keyframes later: a sight from a keyframe that has left
    the window cannot be a factor any more (its pose is no longer a variable).
    """
    if not gone:
        return graph
    keep = gtsam.NonlinearFactorGraph()
    dropped = False
    for i in range(graph.size()):
        f = graph.at(i)
        if f is None:
            continue
        if any(int(key) in gone for key in f.keys()):
            dropped = True
            continue
        keep.add(f)
    return keep if dropped else graph
