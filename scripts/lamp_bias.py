"""The lamp measurement's error against the simulator's truth, split into its causes (issue 20).

Usage::

    python scripts/lamp_bias.py --world lab --seeds 1 --every 6 --out OUT_DIR

For a world's path (image poses of ``simulate_trajectory``, every ``--every``-th image)
each image is rendered in-process by the simulator's renderer and the lamp detector
(:func:`lampsam.frontend.lamps.detect_lamps`) is run on it. Each detected lamp (not
touching the border) is paired with the true lamp whose projected centre is within
4 px, and its observation ``m`` (normalised ceiling coordinates, body axes: forward,
left per metre of height above the camera) is compared with the truth
``m* = R(theta)^T (c_lamp - c_cam) / (h_lamp - z_cam)`` computed from the lamp's face
centre and the camera's optical centre alone (no renderer, no projection code).

The error ``e = m - m*`` is given as

* ``px``: ``f e`` (the focal length in pixels; exact for the undistorted pinhole);
* ``mm``: ``1000 (h_lamp - z_cam) e``, the error of the lamp's position at its height;
* radial / tangential components along ``m*/|m*|`` and its left normal: a radial bias
  mimics a height error, a tangential one a turn of the camera about its axis.

Variants (each a change to the world before rendering, the same poses and noise seeds):

* ``as-is``: the world as simulated;
* ``no-noise``: sensor noise off;
* ``plain``: the ceiling surfaces without tile lines and texture marks (uniform grey);
* ``unsat``: lamp brightness 250 (no saturation of partly covered pixels);
* ``flush``: hung lamps raised to the ceiling they hang under (no parallax between the
  lamp's face and the ceiling behind it);
* ``ss8``: the renderer's supersampling 8 instead of 2;
* ``ideal``: plain + unsat + no noise (only the detector's own geometry is left);
* ``psf0.5``, ``psf0.8``: the world as simulated seen through a Gaussian lens blur of
  0.5 / 0.8 px sigma (applied in this script to the radiance before saturation; the
  simulator's renderer has no blur: each pixel is the exact area average).

Printed per variant: the number of sightings, the mean error (bias) and RMS in px and
mm, the radial and tangential bias binned by the lamp's distance from the image centre,
and the mean error per lamp type. ``--out`` writes the sightings as CSV and a figure.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.ceiling_truth import occluders, project_landmarks
from lampsam.datasets.render_ceiling import CeilingRenderer, camera_center
from lampsam.datasets.simulator import simulate_trajectory
from lampsam.datasets.world import Lamp, World, load_world
from lampsam.datasets.world_landmarks import world_landmarks
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamps import detect_lamps

GATE_PX = 4.0
BINS_PX = (0.0, 40.0, 70.0, 100.0, 130.0, 200.0)
"""Bins of the lamp centre's distance from the principal point, px."""


def _plain(world: World) -> World:
    """The world with its ceiling surfaces uniform (no tiles, no marks)."""
    surfs = tuple(dataclasses.replace(s, tiles=None, items=()) for s in world.surfaces)
    return dataclasses.replace(world, surfaces=surfs)


def _unsat(world: World) -> World:
    """The world with lamps at grey 250 (below saturation)."""
    lamps = tuple(dataclasses.replace(lp, brightness=250.0) for lp in world.lamps)
    return dataclasses.replace(world, lamps=lamps)


def _no_noise(world: World) -> World:
    """The world rendered without sensor noise."""
    return dataclasses.replace(world, render=dataclasses.replace(world.render, noise_sigma=0.0))


def _ss8(world: World) -> World:
    """The world rendered with 8 x 8 rays per pixel."""
    return dataclasses.replace(world, render=dataclasses.replace(world.render, supersample=8))


def _flush(world: World) -> World:
    """Hung lamps raised to the highest surface above their centre."""

    def ceiling_at(lp: Lamp) -> float:
        x, y = lp.center
        hs = [s.height for s in world.surfaces
              if s.extent[0] <= x <= s.extent[2] and s.extent[1] <= y <= s.extent[3]]  # fmt: skip
        return max(hs, default=lp.height) - 1e-3

    lamps = tuple(dataclasses.replace(lp, height=max(lp.height, ceiling_at(lp))) for lp in world.lamps)
    return dataclasses.replace(world, lamps=lamps)


PSF_SIGMA_PX: dict[str, float] = {"psf0.5": 0.5, "psf0.8": 0.8}
"""Variants rendered through a Gaussian lens blur of this sigma (px) before saturation."""


class BlurredRenderer(CeilingRenderer):
    """The simulator's renderer with a Gaussian point-spread function on the radiance.

    The blur is applied to the linear radiance (lamps above 255 included) before the
    noise and the saturation, as a lens blurs light before the sensor clips it.
    """

    def __init__(self, world: World, sigma_px: float):
        """Renderer of ``world`` with a PSF of ``sigma_px``."""
        super().__init__(world)
        self.sigma_px = sigma_px

    def render_linear(self, pose: FloatArray) -> np.ndarray:
        """The radiance image, blurred."""
        img = super().render_linear(pose)
        return cv2.GaussianBlur(img, (0, 0), self.sigma_px)


VARIANTS: dict[str, Callable[[World], World]] = {
    "as-is": lambda w: w,
    "no-noise": _no_noise,
    "plain": _plain,
    "unsat": _unsat,
    "flush": _flush,
    "ss8": _ss8,
    "ideal": lambda w: _no_noise(_unsat(_plain(w))),
    "psf0.5": lambda w: w,
    "psf0.8": lambda w: w,
}


def truth_m(world: World, pose: FloatArray, centre: FloatArray) -> FloatArray:
    """True normalised ceiling coordinates of a point ``centre`` (3,) seen from body ``pose``."""
    cam = world.rig.camera
    d = centre[:2] - camera_center(cam, pose)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]]) / (centre[2] - cam.z_cam)


def measure(
    world: World, poses: FloatArray, seed: int, config: LampDetectorConfig, psf_px: float = 0.0
) -> list[dict]:
    """Render and detect every pose; one record per paired sighting."""
    cam = world.rig.camera
    renderer = BlurredRenderer(world, psf_px) if psf_px > 0 else CeilingRenderer(world)
    lms = world_landmarks(world)
    occ = occluders(world)
    lamp_rows = {int(i): k for k, i in enumerate(lms.ids) if lms.types[k].startswith("lamp")}
    out: list[dict] = []
    for k, pose in enumerate(poses):
        img = renderer.render(pose, np.random.default_rng([seed, k]))
        det = detect_lamps(img, cam, config)
        truth = project_landmarks(cam, pose, lms, occ, renderer.m_max)
        full = [r for r in range(len(truth.ids))
                if truth.fully_visible[r] and int(truth.ids[r]) in lamp_rows]  # fmt: skip
        if not full:
            continue
        tpx = truth.pixel[full]
        for ob in det.lamps:
            if ob.touches_border:
                continue
            d = np.hypot(*(tpx - ob.pixel).T)
            j = int(np.argmin(d))
            if d[j] > GATE_PX:
                continue
            lid = int(truth.ids[full[j]])
            row = lamp_rows[lid]
            centre = lms.xyz[row]
            mt = truth_m(world, pose, centre)
            out.append(dict(
                frame=k, id=lid, type=lms.types[row], h=float(centre[2] - cam.z_cam),
                x=pose[0], y=pose[1], theta=pose[2], u_true=mt[0], v_true=mt[1],
                u=float(ob.m[0]), v=float(ob.m[1]), col=float(tpx[j, 0]), row=float(tpx[j, 1]),
                ratio=ob.ratio,
            ))  # fmt: skip
    return out


def summarise(name: str, recs: Sequence[dict], f_px: float, cxy: tuple[float, float]) -> dict:
    """Print and return the bias figures of one variant."""
    if not recs:
        print(f"{name}: no sightings")
        return {}
    mt = np.array([[r["u_true"], r["v_true"]] for r in recs])
    mo = np.array([[r["u"], r["v"]] for r in recs])
    h = np.array([r["h"] for r in recs])
    e = mo - mt
    e_px, e_mm = e * f_px, e * 1000.0 * h[:, None]
    rad = mt / np.maximum(np.hypot(*mt.T), 1e-12)[:, None]
    tan = np.column_stack([-rad[:, 1], rad[:, 0]])
    er, et = np.sum(e_px * rad, axis=1), np.sum(e_px * tan, axis=1)
    dist = np.hypot(np.array([r["col"] for r in recs]) - cxy[0], np.array([r["row"] for r in recs]) - cxy[1])
    print(f"\n== {name}: {len(recs)} sightings")
    print(f"  bias (u, v): {e_px.mean(0).round(4)} px, {e_mm.mean(0).round(3)} mm;"
          f" RMS {np.sqrt((e_px**2).sum(1).mean()):.4f} px, {np.sqrt((e_mm**2).sum(1).mean()):.3f} mm")
    print(f"  radial bias {er.mean():+.4f} px (RMS {np.sqrt((er**2).mean()):.4f}),"
          f" tangential {et.mean():+.4f} px (RMS {np.sqrt((et**2).mean()):.4f})")
    print("  from centre px | n | radial px mean | tangential px mean | radial mm mean")
    rows = []
    for lo, hi in zip(BINS_PX[:-1], BINS_PX[1:], strict=True):
        sel = (dist >= lo) & (dist < hi)
        if sel.sum() == 0:
            continue
        er_mm = np.sum(e_mm[sel] * rad[sel], axis=1).mean()
        print(f"  {lo:5.0f}-{hi:<5.0f} | {sel.sum():5d} | {er[sel].mean():+.4f} | {et[sel].mean():+.4f}"
              f" | {er_mm:+.3f}")
        rows.append((lo, hi, int(sel.sum()), float(er[sel].mean()), float(et[sel].mean())))
    types = sorted({r["type"] for r in recs})
    for t in types:
        sel = np.array([r["type"] == t for r in recs])
        print(f"  {t:11s} n={sel.sum():5d} radial {er[sel].mean():+.4f} px, RMS err "
              f"{np.sqrt((e_px[sel]**2).sum(1).mean()):.4f} px")
    return dict(name=name, n=len(recs), er=er, et=et, dist=dist, e_px=e_px, mt=mt, rows=rows,
                col=np.array([r["col"] for r in recs]), row=np.array([r["row"] for r in recs]))


def figure(results: list[dict], path: Path) -> None:
    """Radial bias against distance from the image centre per variant, and the as-is error field."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.8))
    for res in results:
        if not res:
            continue
        mids = [(lo + hi) / 2 for lo, hi, *_ in res["rows"]]
        ax1.plot(mids, [r[3] for r in res["rows"]], "o-", label=f"{res['name']} radial")
    base = results[0]
    if base:
        mids = [(lo + hi) / 2 for lo, hi, *_ in base["rows"]]
        ax1.plot(mids, [r[4] for r in base["rows"]], "k--", label=f"{base['name']} tangential")
    ax1.axhline(0.0, color="grey", lw=0.5)
    ax1.set_xlabel("lamp centre's distance from the image centre, px")
    ax1.set_ylabel("mean error, px (+ = outward / counter-clockwise)")
    ax1.set_title("lamp centroid bias by variant")
    ax1.legend(fontsize=7)
    if base:
        # Mean error (pixel axes) on a 8 x 6 grid of the image.
        gc, gr = np.floor(base["col"] / 40).astype(int), np.floor(base["row"] / 40).astype(int)
        # e in body (u forward, v left) -> pixel axes: the lab camera's image top is forward.
        for i in range(8):
            for j in range(6):
                sel = (gc == i) & (gr == j)
                if sel.sum() < 5:
                    continue
                eu, ev = base["e_px"][sel].mean(0)
                ax2.quiver(40 * i + 20, 40 * j + 20, -ev, -eu, angles="xy", scale_units="xy",
                           scale=0.002, color="C3")  # fmt: skip
        ax2.set_xlim(0, 320)
        ax2.set_ylim(240, 0)
        ax2.set_aspect("equal")
        ax2.set_title(f"{base['name']}: mean error per 40 px cell (arrow x500)")
        ax2.set_xlabel("col px")
        ax2.set_ylabel("row px")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"figure: {path}")


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--world", default="lab")
    ap.add_argument("--seeds", default="1", help="comma-separated path/noise seeds")
    ap.add_argument("--every", type=int, default=6, help="use every n-th image pose")
    ap.add_argument("--duration", type=float, default=None, help="seconds of the path")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--out", default=None, help="folder for sightings.csv and lamp_bias.png")
    args = ap.parse_args()
    base = load_world(args.world)
    cam = base.rig.camera
    f_px = math.sqrt(cam.fx * cam.fy)
    config = LampDetectorConfig()
    results = []
    for name in args.variants.split(","):
        world = VARIANTS[name](base)
        recs: list[dict] = []
        for seed in (int(s) for s in args.seeds.split(",")):
            _, poses, _, _ = simulate_trajectory(world, seed, args.duration)
            step = int(round(world.simulation.odometry_rate_hz / world.simulation.image_rate_hz))
            sel = poses[::step][:: args.every]
            recs += measure(world, sel, seed, config, PSF_SIGMA_PX.get(name, 0.0))
        results.append(summarise(name, recs, f_px, (cam.cx, cam.cy)))
        if args.out:
            out = Path(args.out)
            os.makedirs(out, exist_ok=True)
            if recs:
                with open(out / f"sightings_{name}.csv", "w", newline="") as fh:
                    wr = csv.DictWriter(fh, fieldnames=list(recs[0]))
                    wr.writeheader()
                    wr.writerows(recs)
    if args.out:
        figure(results, Path(args.out) / "lamp_bias.png")


if __name__ == "__main__":
    main()
