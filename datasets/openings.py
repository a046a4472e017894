"""Daylight openings of a simulated ceiling: skylights and windows.

Real ceilings show bright regions that are not lamps: sky through skylights
and windows, with glazing bars (mullions) across it and clouds or branches in
it. They are bright but textured and not uniformly saturated, which is what
tells them from a lamp's flat saturated face. An opening is a horizontal
rotated rectangle at a height (a skylight in the ceiling plane; a window is
modelled as the strip of daylight a clerestory or light well throws at the
ceiling's edge, seen from below like a skylight):

* daylight ``g(x, y) = brightness (1 + texture t(x, y))``, ``t`` a seeded sum
  of plane waves of wavelengths 0.08-1 m scaled to amplitude ``texture``
  (so with ``brightness`` 240 and ``texture`` 0.35 the sky spans about
  160-320 grey levels: part saturates, part does not);
* glazing bars of width ``bar_width`` every ``bar_pitch`` metres along both
  sides, at grey ``bar_grey``.

World YAML (``ceiling.openings``, schema of :mod:`lampsam.datasets.world`)::

    openings:
      - {kind: skylight, center: [x, y], size: [sx, sy], yaw_deg: 0, height: 2.9,
         brightness: 240, texture: 0.35, bar_pitch: 0.4, bar_width: 0.04,
         bar_grey: 70, seed: 1}

Sizes and positions are metres in the world frame, heights above the floor.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from lampsam.arrays import FloatArray

OpeningKind = Literal["skylight", "window"]


@dataclass(frozen=True)
class Opening:
    """A daylight opening (see the module docstring).

    Attributes:
        kind: ``skylight`` or ``window``.
        center: ``(x, y)`` world, m.
        size: ``(sx, sy)`` side lengths along its own axes, m.
        yaw: rotation of the first side from world x, rad.
        height: height above the floor, m.
        brightness: mean daylight grey level (values above 255 saturate).
        texture: relative amplitude of the daylight texture (0: flat).
        bar_pitch: glazing-bar spacing, m (0: no bars).
        bar_width: glazing-bar width, m.
        bar_grey: glazing-bar grey level.
        seed: seed of the texture's waves.
    """

    kind: OpeningKind
    center: tuple[float, float]
    size: tuple[float, float]
    yaw: float
    height: float
    brightness: float = 240.0
    texture: float = 0.35
    bar_pitch: float = 0.4
    bar_width: float = 0.04
    bar_grey: float = 70.0
    seed: int = 0

    def contains(self, xy: FloatArray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: points ``xy`` (N, 2) on the opening grown by ``margin``, m."""
        d = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - np.asarray(self.center)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        lx = c * d[:, 0] + s * d[:, 1]
        ly = -s * d[:, 0] + c * d[:, 1]
        return (np.abs(lx) <= self.size[0] / 2 + margin) & (np.abs(ly) <= self.size[1] / 2 + margin)

    def bars(self) -> list[tuple[tuple[float, float], tuple[float, float]]]:
        """Glazing bars as ``(center, size)`` rectangles in the opening's own yaw (world m)."""
        if self.bar_pitch <= 0 or self.bar_width <= 0:
            return []
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        out = []
        for axis in (0, 1):
            half = self.size[axis] / 2
            n = int(math.floor(half / self.bar_pitch))
            for k in range(-n, n + 1):
                off = k * self.bar_pitch
                if abs(off) >= half - self.bar_width:
                    continue
                lx, ly = (off, 0.0) if axis == 0 else (0.0, off)
                centre = (self.center[0] + c * lx - s * ly, self.center[1] + s * lx + c * ly)
                size = (self.bar_width, self.size[1]) if axis == 0 else (self.size[0], self.bar_width)
                out.append((centre, size))
        return out

    def daylight(self) -> Callable[[FloatArray, FloatArray], FloatArray]:
        """``g(x, y)``: the daylight grey level at world points (arrays of any shape)."""
        rng = np.random.default_rng(self.seed)
        n = 12
        wavelength = np.exp(rng.uniform(math.log(0.08), math.log(1.0), n))
        direction = rng.uniform(0.0, math.pi, n)
        phase = rng.uniform(0.0, 2 * math.pi, n)
        kx = 2 * math.pi * np.cos(direction) / wavelength
        ky = 2 * math.pi * np.sin(direction) / wavelength
        amp = wavelength / wavelength.sum()  # longer waves stronger (clouds, branches)
        scale = self.texture / math.sqrt(0.5 * float(amp @ amp))  # texture = RMS amplitude
        b = self.brightness

        def grey(x: FloatArray, y: FloatArray) -> FloatArray:
            t = np.zeros(np.shape(x))
            for i in range(n):
                t += amp[i] * np.sin(kx[i] * x + ky[i] * y + phase[i])
            return np.asarray(b * (1.0 + scale * t), dtype=np.float64)

        return grey


def parse_opening(
    d: Mapping[str, Any],
    where: str,
    number: Callable[..., float],
    vec: Callable[[Any, int, str], tuple[float, ...]],
    fail: Callable[[str, str], Exception],
) -> Opening:
    """One opening from its YAML mapping (the world parser's checked readers are passed in).

    Args:
        d: the mapping (keys already checked by the caller).
        where: key path for messages, e.g. ``ceiling.openings[0]``.
        number: ``number(d, key, where, default, positive=..., nonneg=...)`` -> float.
        vec: ``vec(value, n, where)`` -> n floats.
        fail: ``fail(where, message)`` -> the exception to raise.
    """
    kind = d["kind"]
    if kind not in ("skylight", "window"):
        raise fail(f"{where}.kind", f"must be skylight or window, got {kind!r}")
    size = vec(d["size"], 2, f"{where}.size")
    if min(size) <= 0:
        raise fail(f"{where}.size", "sides must be > 0")
    return Opening(
        kind=kind,
        center=vec(d["center"], 2, f"{where}.center"),  # type: ignore[arg-type]
        size=size,  # type: ignore[arg-type]
        yaw=math.radians(number(d, "yaw_deg", where, 0.0)),
        height=number(d, "height", where, positive=True),
        brightness=number(d, "brightness", where, 240.0, positive=True),
        texture=number(d, "texture", where, 0.35, nonneg=True),
        bar_pitch=number(d, "bar_pitch", where, 0.4, nonneg=True),
        bar_width=number(d, "bar_width", where, 0.04, nonneg=True),
        bar_grey=number(d, "bar_grey", where, 70.0, nonneg=True),
        seed=int(number(d, "seed", where, 0.0, nonneg=True)),
    )


OPENING_KEYS = {"kind", "center", "size", "yaw_deg", "height", "brightness", "texture",
                "bar_pitch", "bar_width", "bar_grey", "seed"}  # fmt: skip
"""Keys of an opening's YAML mapping."""
