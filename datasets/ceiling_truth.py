"""True image projections of simulated ceiling landmarks, independent of the renderer.

3-D points are projected with the camera's own lens model
(``CameraModel.project_camera_points``, pinhole or fisheye) from the camera's world
pose built from the body pose and ``body_R_camera``/``body_t_camera``
(:func:`world_T_camera`); landmarks hidden behind a low surface (:func:`occluders`) or
outside the image are flagged. Nothing from :mod:`lampsam.factors` or the renderer
(:mod:`lampsam.datasets.render_ceiling`) is used, so the simulator's labels check both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.datasets.logrun import CameraModel, LandmarkTable, ProjectionTable
from lampsam.datasets.shapes import disc_sdf, rect_sdf
from lampsam.datasets.world import World


def world_T_camera(camera: CameraModel, pose: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Camera pose in the world for a body pose.

    Args:
        camera: gives ``body_R_camera`` and ``body_t_camera``.
        pose: (3,) ``world_T_body = (x, y, theta)``.

    Returns:
        ``(world_R_camera (3, 3), world_t_camera (3,))``.
    """
    c, s = math.cos(pose[2]), math.sin(pose[2])
    world_R_body = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    world_t_body = np.array([pose[0], pose[1], 0.0])
    return world_R_body @ camera.body_R_camera, world_t_body + world_R_body @ camera.body_t_camera


@dataclass(frozen=True)
class _Occluder:
    """A horizontal shape that hides what lies above it from the camera below."""

    height: float
    shape: str  # "rect" or "disc"
    center: tuple[float, float]
    half: tuple[float, float]
    yaw: float

    def contains(self, xy: FloatArray) -> BoolArray:
        """(N,) bool: points ``xy`` (N, 2) on the shape."""
        if self.shape == "disc":
            return disc_sdf(xy[:, 0], xy[:, 1], self.center, self.half[0]) <= 0
        return rect_sdf(xy[:, 0], xy[:, 1], self.center, self.half, self.yaw) <= 0


def occluders(world: World) -> tuple[_Occluder, ...]:
    """Everything that can hide a farther point: surfaces' extents and lamps."""
    occ = []
    for s in world.surfaces:
        x0, y0, x1, y1 = s.extent
        occ.append(
            _Occluder(
                s.height,
                "rect",
                ((x0 + x1) / 2, (y0 + y1) / 2),
                ((x1 - x0) / 2, (y1 - y0) / 2),
                0.0,
            )
        )
    for lp in world.lamps:
        if lp.shape == "round":
            occ.append(_Occluder(lp.height, "disc", lp.center, (lp.length / 2, lp.length / 2), 0.0))
        else:
            occ.append(
                _Occluder(lp.height, "rect", lp.center, (lp.length / 2, lp.width / 2), lp.yaw)
            )
    return tuple(occ)


def _hidden(points: FloatArray, cam_xyz: FloatArray, occ: tuple[_Occluder, ...]) -> BoolArray:
    """(N,) True where the segment from the optical centre to a point crosses a nearer occluder."""
    hidden = np.zeros(len(points), dtype=bool)
    dz = points[:, 2] - cam_xyz[2]
    for o in occ:
        ho = o.height - cam_xyz[2]
        cand = (ho > 1e-9) & (ho < dz - 1e-6)
        if not cand.any():
            continue
        f = ho / dz[cand]
        q = cam_xyz[:2] + (points[cand, :2] - cam_xyz[:2]) * f[:, None]
        idx = np.flatnonzero(cand)
        hidden[idx[o.contains(q)]] = True
    return hidden


def _project(
    camera: CameraModel, points: FloatArray, pose: FloatArray
) -> tuple[FloatArray, BoolArray]:
    """Pixels of world points with the camera's lens model; second output: in front and unfolded."""
    if len(points) == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    w_R_c, w_t_c = world_T_camera(camera, pose)
    pc = (points - w_t_c) @ w_R_c  # camera-frame coordinates
    px, ok = camera.project_camera_points(pc)  # the camera's lens model (pinhole or fisheye)
    ok &= pc[:, 2] > 1e-6
    if camera.has_distortion and ok.any():
        # Far outside the field of view a distortion polynomial folds back: keep only
        # projections that undistort to the same ray.
        rays = camera.camera_rays(px[ok])
        ok[np.flatnonzero(ok)] = np.all(np.abs(rays - pc[ok, :2] / pc[ok, 2:3]) < 1e-3, axis=1)
    return px, ok


def lamp_outlines(
    centers: FloatArray, length: FloatArray, width: FloatArray, phi: FloatArray, round_: list[bool]
) -> FloatArray:
    """Outline points of lamps, 16 each.

    Args:
        centers: (K, 3) lamp centres, world m.
        length: (K,) long side (round: diameter), m.
        width: (K,) short side, m.
        phi: (K,) yaw of the long side, rad.
        round_: K flags: round lamps get 16 points on the circle, others the 4
            corners and 3 points on each side.

    Returns:
        (K, 16, 3) world points at the lamps' heights.
    """
    k = len(centers)
    a = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    circle = np.column_stack([np.cos(a), np.sin(a)])  # unit radius
    f = np.array([-0.5, 0.0, 0.5])
    one = np.ones(3)
    box = np.concatenate([
        [[1, 1], [-1, 1], [-1, -1], [1, -1]],
        np.column_stack([f * 2, one]), np.column_stack([f * 2, -one]),
        np.column_stack([one, f * 2]), np.column_stack([-one, f * 2]),
    ])  # fmt: skip  # (16, 2) on the [-1, 1]^2 square
    is_round = np.asarray(round_, dtype=bool).reshape(k, 1, 1)
    half = np.stack([length / 2, width / 2], axis=-1)[:, None, :]  # (K, 1, 2)
    local = np.where(is_round, circle[None] * half[..., :1], box[None] * half)
    c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
    x = centers[:, None, 0] + c * local[..., 0] - s * local[..., 1]
    y = centers[:, None, 1] + s * local[..., 0] + c * local[..., 1]
    z = np.broadcast_to(centers[:, None, 2], x.shape)
    return np.stack([x, y, z], axis=-1).reshape(k, 16, 3)


def project_landmarks(
    camera: CameraModel,
    pose: FloatArray,
    landmarks: LandmarkTable,
    occ: tuple[_Occluder, ...] = (),
    m_max: float | None = None,
) -> ProjectionTable:
    """True projections of the landmarks seen from a body pose (``frame``, ``t`` left 0).

    A row is produced for each landmark in front of the camera whose centre (or, for
    lamps, any outline point) projects inside the image ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.

    Args:
        camera: the camera.
        pose: (3,) body pose ``(x, y, theta)``.
        landmarks: true landmarks (``length``/``width``/``phi`` give lamp outlines).
        occ: occluders (:func:`occluders`); empty = nothing hides anything.
        m_max: skip landmarks farther than ``m_max`` per metre of height (speed only).

    Returns:
        See :class:`lampsam.datasets.logrun.ProjectionTable`; ``angle_px`` is the
        projected long axis ``atan2(d_row, d_col)`` of ``lamp_rect`` lamps, wrapped to
        (-pi/2, pi/2]; ``fully_visible`` needs every outline point inside
        ``[0.5, W - 1.5] x [0.5, H - 1.5]`` and unhidden.
    """
    w_R_c, w_t_c = world_T_camera(camera, pose)
    sel = np.flatnonzero(landmarks.xyz[:, 2] > w_t_c[2] + 1e-6)
    if m_max is not None and len(sel):
        d = np.hypot(*(landmarks.xyz[sel, :2] - w_t_c[:2]).T)
        reach = (
            (landmarks.xyz[sel, 2] - w_t_c[2]) * m_max * 1.05
            + np.maximum(landmarks.length[sel], 0)
            + 0.1
        )
        sel = sel[d <= reach]
    W, H = camera.width, camera.height  # noqa: N806

    def inside(px: FloatArray, margin: float) -> BoolArray:
        """(N,) bool: pixels inside the image shrunk by ``margin`` px."""
        return (
            (px[:, 0] >= -0.5 + margin) & (px[:, 0] <= W - 0.5 - margin)
            & (px[:, 1] >= -0.5 + margin) & (px[:, 1] <= H - 0.5 - margin)
        )  # fmt: skip

    pts = landmarks.xyz[sel]
    types = [landmarks.types[i] for i in sel]
    lamp_k = np.array([k for k, t in enumerate(types) if t.startswith("lamp")], dtype=np.int64)
    rect_k = np.array([k for k, t in enumerate(types) if t == "lamp_rect"], dtype=np.int64)
    rings = lamp_outlines(
        pts[lamp_k], landmarks.length[sel[lamp_k]], landmarks.width[sel[lamp_k]],
        landmarks.phi[sel[lamp_k]], [types[k] == "lamp_round" for k in lamp_k],
    )  # fmt: skip  # (K, R, 3)
    n_ring = rings.shape[1]
    e = (
        0.5
        * landmarks.length[sel[rect_k], None]
        * np.column_stack(
            [
                np.cos(landmarks.phi[sel[rect_k]]),
                np.sin(landmarks.phi[sel[rect_k]]),
                np.zeros(len(rect_k)),
            ]
        )
    )
    ends = np.concatenate([pts[rect_k] - e, pts[rect_k] + e])
    # One projection and one occlusion test for centres, outlines and axis ends.
    n_pts, n_rings = len(pts), len(lamp_k) * n_ring
    all_pts = np.concatenate([pts, rings.reshape(-1, 3), ends])
    all_px, all_ok = _project(camera, all_pts, pose)
    px, ok = all_px[:n_pts], all_ok[:n_pts]
    vis_pts = all_pts[: n_pts + n_rings]
    all_hidden = _hidden(vis_pts, w_t_c, occ) if occ else np.zeros(len(vis_pts), dtype=bool)
    hidden = all_hidden[:n_pts]
    centre_in = ok & inside(px, 0.0)
    keep = centre_in.copy()
    fully = centre_in & ~hidden  # corners; lamps are overwritten below
    angle = np.full(len(sel), np.nan)
    if len(lamp_k):
        rpx = all_px[n_pts : n_pts + n_rings]
        rok = all_ok[n_pts : n_pts + n_rings]
        rhid = all_hidden[n_pts:]
        any_in = (rok & inside(rpx, 0.0)).reshape(-1, n_ring).any(axis=1)
        all_in = (rok & inside(rpx, 1.0) & ~rhid).reshape(-1, n_ring).all(axis=1)
        keep[lamp_k] |= any_in
        fully[lamp_k] = all_in & ~hidden[lamp_k] & ok[lamp_k]
    if len(rect_k):
        epx = all_px[n_pts + n_rings :].reshape(2, -1, 2)
        eok = all_ok[n_pts + n_rings :].reshape(2, -1).all(axis=0)
        a = np.arctan2(epx[1, :, 1] - epx[0, :, 1], epx[1, :, 0] - epx[0, :, 0])
        a = np.mod(a + np.pi / 2, np.pi) - np.pi / 2
        a = np.where(a == -np.pi / 2, np.pi / 2, a)
        angle[rect_k] = np.where(eok, a, np.nan)
    keep &= ok
    n = int(keep.sum())
    return ProjectionTable(
        frame=np.zeros(n, dtype=np.int64),
        t=np.zeros(n),
        ids=landmarks.ids[sel][keep],
        types=tuple(t for t, k in zip(types, keep, strict=True) if k),
        pixel=px[keep],
        angle_px=angle[keep],
        visible=(centre_in & ~hidden)[keep],
        fully_visible=fully[keep],
    )
