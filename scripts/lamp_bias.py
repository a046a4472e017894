"""The lamp measurement's error against the simulator's truth, split into its causes (issue 20).

Usage::

    python scripts/lamp_bias.py --world lab --seeds 1 --every 12 --out OUT_DIR

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

Each image is measured with each detector setting of ``--configs``: ``model`` (the
default, :mod:`lampsam.frontend.saturated_edges` on) and ``read`` (the coverage weights
as read, the model off). Printed per variant and setting: the number of sightings, the
mean error (bias) and RMS in px and mm, the radial and tangential bias binned by the
lamp's distance from the image centre, the RMS per lamp type, and for rect lamps whose
long edges lie along image columns the correlation of their across-axis error with the
clipped-edge model (:func:`phase_model`: each edge off by ``min(1, phi / c_s) - phi`` at
its true sub-pixel phase ``phi``). ``--out`` writes the sightings as CSV and a figure.
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
from lampsam.evaluation.lamp_plots import PhasePoints, save_lamp_bias_figure
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


CONFIGS: dict[str, LampDetectorConfig] = {
    "model": LampDetectorConfig(),
    "read": LampDetectorConfig(saturated_edges=False),
}
"""Detector settings compared: the default (saturated-edge model on) and the weights as read."""


def measure(
    world: World, poses: FloatArray, seed: int, configs: Sequence[str], psf_px: float = 0.0
) -> dict[str, list[dict]]:
    """Render every pose once and detect with each of ``configs``; one record per paired sighting."""
    cam = world.rig.camera
    renderer = BlurredRenderer(world, psf_px) if psf_px > 0 else CeilingRenderer(world)
    lms = world_landmarks(world)
    occ = occluders(world)
    lamp_rows = {int(i): k for k, i in enumerate(lms.ids) if lms.types[k].startswith("lamp")}
    yaw = {lp.id: lp.yaw for lp in world.lamps}
    out: dict[str, list[dict]] = {c: [] for c in configs}
    for k, pose in enumerate(poses):
        img = renderer.render(pose, np.random.default_rng([seed, k]))
        truth = project_landmarks(cam, pose, lms, occ, renderer.m_max)
        full = [r for r in range(len(truth.ids))
                if truth.fully_visible[r] and int(truth.ids[r]) in lamp_rows]  # fmt: skip
        if not full:
            continue
        tpx = truth.pixel[full]
        for name in configs:
            for ob in detect_lamps(img, cam, CONFIGS[name]).lamps:
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
                out[name].append(dict(
                    frame=k, id=lid, type=lms.types[row], h=float(centre[2] - cam.z_cam),
                    x=pose[0], y=pose[1], theta=pose[2], u_true=mt[0], v_true=mt[1],
                    u=float(ob.m[0]), v=float(ob.m[1]), col=float(tpx[j, 0]), row=float(tpx[j, 1]),
                    ratio=ob.ratio, yaw=yaw[lid], width=float(lms.width[row]),
                ))  # fmt: skip
    return out


def edge_error(phi: FloatArray, cs: float) -> FloatArray:
    """Outward error (px) of a sharp saturated edge whose edge pixel the lamp covers by ``phi``,
    with the coverage weights as read (``w = min(1, phi / c_s)``)."""
    return np.minimum(1.0, phi / cs) - phi


def phase_model(recs: Sequence[dict], f_px: float, cs: float) -> tuple[FloatArray, FloatArray]:
    """Measured and predicted across-axis error (px) of rect lamps whose long edges lie along
    image columns within 2.6 deg: the prediction is half the difference of the two edges'
    :func:`edge_error` at their true sub-pixel phases (pinhole looking up: ``col = cx + f v``)."""
    meas, pred = [], []
    for r in recs:
        if r["type"] != "lamp_rect":
            continue
        a = r["yaw"] - r["theta"]  # the lamp's axis in the body frame
        if abs(math.cos(a)) < 0.999:  # across direction (-sin a, cos a): along v = image columns
            continue
        half = 0.5 * r["width"] / r["h"] * f_px
        col = CX + f_px * r["v_true"]
        phi_r = np.mod(col + half + 0.5, 1.0)  # lamp left of the right edge
        phi_l = 1.0 - np.mod(col - half + 0.5, 1.0)  # lamp right of the left edge
        pred.append(0.5 * (edge_error(phi_r, cs) - edge_error(phi_l, cs)))
        meas.append(f_px * (r["v"] - r["v_true"]))
    return np.array(meas), np.array(pred)


CX = 159.5
"""Principal point column of the lab camera, px (set from the world in :func:`main`)."""


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
    col, row = np.array([r["col"] for r in recs]), np.array([r["row"] for r in recs])
    dist = np.hypot(col - cxy[0], row - cxy[1])
    rms = float(np.sqrt((e_px**2).sum(1).mean()))
    print(f"\n== {name}: {len(recs)} sightings")
    print(f"  bias (u, v): {e_px.mean(0).round(4)} px, {e_mm.mean(0).round(3)} mm;"
          f" RMS {rms:.4f} px, {np.sqrt((e_mm**2).sum(1).mean()):.3f} mm")
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
    by_type = {}
    for t in sorted({r["type"] for r in recs}):
        sel = np.array([r["type"] == t for r in recs])
        by_type[t] = float(np.sqrt((e_px[sel] ** 2).sum(1).mean()))
        print(f"  {t:11s} n={sel.sum():5d} radial {er[sel].mean():+.4f} px, RMS err {by_type[t]:.4f} px")
    meas, pred = phase_model(recs, f_px, CS_LAB)
    if len(meas) > 2:
        print(f"  aligned rect lamps (n={len(meas)}): across error RMS {np.sqrt(np.mean(meas**2)):.4f} px;"
              f" clipped-edge model (c_s {CS_LAB:.2f}) correlation {np.corrcoef(meas, pred)[0, 1]:+.2f}")
    return dict(name=name, n=len(recs), rms=rms, by_type=by_type, rows=rows, meas=meas, pred=pred,
                e_px=e_px, col=col, row=row)


CS_LAB = (255.0 - 175.0) / (320.0 - 175.0)
"""Clip coverage of the lab's lamps (radiance 320) over its tiles (grey 175)."""


def figure(results: dict[str, dict], path: Path) -> None:
    """Lamp error RMS per variant and setting, and the across error of aligned rect lamps
    against the clipped-edge model (:func:`lampsam.evaluation.lamp_plots.save_lamp_bias_figure`)."""
    variants = list(dict.fromkeys(k.split("/")[0] for k in results))
    configs = list(dict.fromkeys(k.split("/")[1] for k in results))
    rms = np.array([[results.get(f"{v}/{c}", {}).get("rms", np.nan) for v in variants]
                    for c in configs], dtype=float).reshape(len(configs), len(variants))
    points = []
    for key, marker in ((f"{variants[0]}/read", "o"), (f"{variants[0]}/model", "x")):
        res = results.get(key)
        if res and len(res["meas"]):
            points.append(PhasePoints(key, marker, res["pred"], res["meas"]))
    save_lamp_bias_figure(path, variants, configs, rms, points)
    print(f"figure: {path}")


def main() -> None:
    """Command line."""
    global CX
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--world", default="lab")
    ap.add_argument("--seeds", default="1", help="comma-separated path/noise seeds")
    ap.add_argument("--every", type=int, default=6, help="use every n-th image pose")
    ap.add_argument("--duration", type=float, default=None, help="seconds of the path")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--configs", default="read,model", help=f"detector settings: {','.join(CONFIGS)}")
    ap.add_argument("--out", default=None, help="folder for sightings_*.csv and lamp_bias.png")
    args = ap.parse_args()
    base = load_world(args.world)
    cam = base.rig.camera
    CX = cam.cx
    f_px = math.sqrt(cam.fx * cam.fy)
    configs = args.configs.split(",")
    results: dict[str, dict] = {}
    for name in args.variants.split(","):
        world = VARIANTS[name](base)
        recs: dict[str, list[dict]] = {c: [] for c in configs}
        for seed in (int(s) for s in args.seeds.split(",")):
            _, poses, _, _ = simulate_trajectory(world, seed, args.duration)
            step = int(round(world.simulation.odometry_rate_hz / world.simulation.image_rate_hz))
            got = measure(world, poses[::step][:: args.every], seed, configs, PSF_SIGMA_PX.get(name, 0.0))
            for c in configs:
                recs[c] += got[c]
        for c in configs:
            results[f"{name}/{c}"] = summarise(f"{name}/{c}", recs[c], f_px, (cam.cx, cam.cy))
            if args.out and recs[c]:
                out = Path(args.out)
                os.makedirs(out, exist_ok=True)
                with open(out / f"sightings_{name}_{c}.csv", "w", newline="") as fh:
                    wr = csv.DictWriter(fh, fieldnames=list(recs[c][0]))
                    wr.writeheader()
                    wr.writerows(recs[c])
    if args.out:
        figure(results, Path(args.out) / "lamp_bias.png")


if __name__ == "__main__":
    main()
