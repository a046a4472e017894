"""Stereo two-point runs as plain data: the rig, the noise model and a run (paper 3).

Used alike by the simulator (:mod:`lampsam.datasets.stereo_sim`), the KITTI
reader (:meth:`lampsam.datasets.kitti.KittiStereoSequence.stereo_rig`) and the
estimators (:mod:`lampsam.backend.stereo`, :mod:`lampsam.backend.stereo_kitti`).
Image coordinates follow ``docs/stereo.md``: horizontal only, px from the
principal point, positive to the left.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from lampsam.arrays import BoolArray, FloatArray


@dataclass(frozen=True)
class StereoRig:
    """A parallel stereo pair (paper 3, Fig. 1).

    Defaults are a Point Grey Bumblebee2 BB2-03S2 with the 3.8 mm lens, from its
    datasheet as commonly quoted: 12 cm baseline, 7.4 um square pixels, 648 px
    wide (f/p = 513.5 px, horizontal field of view about 64 deg).

    Attributes:
        baseline: ``B``, distance between the optical centres, m.
        focal_length: ``f``, lens to image plane, m.
        pixel_pitch: ``p``, pixel width, m (square pixels).
        width_px: image width, px; the principal point is the image centre.
    """

    baseline: float = 0.12
    focal_length: float = 3.8e-3
    pixel_pitch: float = 7.4e-6
    width_px: int = 648

    @property
    def f_px(self) -> float:
        """``f / p``, px."""
        return self.focal_length / self.pixel_pitch

    @property
    def cu_px(self) -> float:
        """Principal point column, px (OpenCV pixel centres: ``(width - 1) / 2``)."""
        return 0.5 * (self.width_px - 1)

    @classmethod
    def from_pixels(cls, baseline: float, f_px: float, width_px: int) -> StereoRig:
        """A rig given in pixels (as calibrated, e.g. KITTI's projection matrices).

        Args:
            baseline: ``B``, m.
            f_px: focal length ``f / p``, px (stored as ``focal_length = f_px``,
                ``pixel_pitch = 1``).
            width_px: image width, px.
        """
        return cls(baseline=baseline, focal_length=f_px, pixel_pitch=1.0, width_px=width_px)

    def half_width_px(self) -> float:
        """Largest ``|x|`` (px from the principal point) still inside the image."""
        return self.cu_px + 0.5



@dataclass(frozen=True)
class StereoNoise:
    """Noise of the simulated sensors.

    Attributes:
        sigma_detect_px: Gaussian detection noise per coordinate, px (added before
            rounding).
        quantise: round the image column to whole pixels (uniform error,
            variance 1/12 px^2), as the paper's noise model.
        sigma_v: odometry forward-speed noise, m/s (white per step).
        sigma_omega: odometry turn-rate noise, rad/s (white per step).
        sigma_lateral: lateral-slip noise the estimators should assume, m/s
            (the simulated robot never slips; a floor that keeps the motion
            covariance full rank).
    """

    sigma_detect_px: float = 0.3
    quantise: bool = True
    sigma_v: float = 0.05
    sigma_omega: float = 0.05
    sigma_lateral: float = 0.01

    @property
    def var_measurement_px2(self) -> float:
        """Variance of one image coordinate, px^2: ``sigma_detect^2 (+ 1/12)``."""
        return self.sigma_detect_px**2 + (1.0 / 12.0 if self.quantise else 0.0)



@dataclass(frozen=True)
class StereoRun:
    """One stereo two-point run in memory.

    Attributes:
        path: run directory (or None for an in-memory run).
        rig: the stereo rig.
        noise: the noise the run was made with (the estimators use it as known).
        target_t_points: (2, 2) target points, m, target frame.
        t: (N,) frame times, s, strictly increasing.
        v, omega: (N,) measured odometry over the step ending at ``t[k]``, m/s, rad/s.
        z: (N, 4) ``[xl1, xr1, xl2, xr2]`` px (0 where not seen).
        seen: (N,) bool, both points imaged.
        truth: (N, 3) true ``target_T_camera`` ``(x, y, theta)`` or None.
        scenario: name; seed: the simulator's seed (or -1).
    """

    path: Path | None
    rig: StereoRig
    noise: StereoNoise
    target_t_points: FloatArray
    t: FloatArray
    v: FloatArray
    omega: FloatArray
    z: FloatArray
    seen: BoolArray
    truth: FloatArray | None
    scenario: str = ""
    seed: int = -1

    def __len__(self) -> int:
        """Number of frames."""
        return len(self.t)
