"""The robot as the global localizer sees it: turn in place, drive on, frames back.

The localizer (:func:`lampsam.localization.localizer.localize`) steers the robot
through the structural :class:`Robot` protocol, so the same pipeline runs on the
simulated steerable robot (:class:`lampsam.datasets.steerable_robot.SimulatedRobot`),
on a logged run replayed in order (:class:`lampsam.localization.replay.ReplayRobot`)
and on the synthetic worlds of the tests. The frames themselves are plain data of
:mod:`lampsam.datasets.robot_frames`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from lampsam.datasets.robot_frames import DriveFrame, TurnFrame
from lampsam.errors import LocalizationError

__all__ = ["DriveFrame", "GlobalLocalizationError", "Robot", "TurnFrame"]


class GlobalLocalizationError(LocalizationError):
    """The pipeline cannot run (no usable data, bad configuration)."""


class Robot(Protocol):
    """What the localizer asks of the robot (or of a simulator, or a log replay)."""

    def turn(self, angle: float, rate: float) -> Sequence[TurnFrame]:
        """Turn in place by ``angle`` (rad, counter-clockwise positive) at ``rate`` (rad/s).

        Returns the Kinect frames recorded meanwhile (the first at the start
        heading); none when the robot (or log) cannot turn any more.
        """
        ...

    def drive(self, distance: float) -> Sequence[DriveFrame]:
        """Drive on for ``distance`` (m, along a collision-free path); the ceiling frames recorded."""
        ...
