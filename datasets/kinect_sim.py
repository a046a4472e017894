"""A forward-facing Kinect-like RGB-D sensor rendered from a :mod:`scene3d` world.

Paper 2, sec. 2 (DESIGN.md sec. 2): the environment map is built from a
mapping drive with a forward Kinect (narrow field of view, short range), so the
robot zig-zags to cover the room. This module renders colour and depth with
Open3D's ``RaycastingScene`` (colour from the hit triangle's base colour or its
picture texture through the barycentric hit coordinates), adds range-dependent
depth noise and drop-outs, and writes the frames in the TUM RGB-D layout.

Camera frame (OpenCV, docs/conventions.md): ``x`` right, ``y`` down, ``z`` the
optical axis. Depth is the ``z`` coordinate of the hit point in the camera frame
(like a Kinect), not the ray length.

TUM RGB-D layout written under ``RUN/kinect/``::

    rgb/<t>.png        8-bit colour
    depth/<t>.png      16-bit depth, value = depth_m * depth_scale, 0 = no depth
    rgb.txt, depth.txt "timestamp filename" per line, '#' comments
    groundtruth.txt    world_T_camera, TUM "t tx ty tz qx qy qz qw" (3-D camera pose)
    kinect.yaml        intrinsics, depth_scale, range, body_T_camera (self-describing)
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from lampsam.arrays import FloatArray, ImageU8, ImageU16
from lampsam.datasets.scene3d import Scene3D
from lampsam.datasets.scene_mesh import TriangleScene, triangle_scene
from lampsam.errors import DatasetError
from lampsam.safe_io import write_text_atomic

log = logging.getLogger(__name__)

KINECT_DIR = "kinect"
"""Sub-directory of a run holding the TUM RGB-D frames."""

FORMAT_VERSION = 1


@dataclass(frozen=True)
class KinectConfig:
    """The simulated RGB-D sensor.

    Attributes:
        width: image columns (default 320; 640 for full Kinect resolution).
        height: image rows (default 240).
        hfov_deg: horizontal field of view (default 57).
        vfov_deg: vertical field of view (default 43).
        min_depth: nearest valid depth, metres (default 0.5).
        max_depth: farthest valid depth, metres (default 4.5).
        sigma_depth_k: depth noise ``sigma = k z^2``, 1/m (default 1.5e-3: 2.4 cm at 4 m).
        max_incidence_deg: rays meeting a surface more obliquely than this give no
            depth (grazing-angle drop-out, default 75).
        depth_scale: stored 16-bit value per metre (default 5000, like TUM RGB-D).
        body_t_camera: (3,) optical centre in the body frame, metres (default
            ``(0.15, 0.0, 0.45)``: 0.15 m forward, 0.45 m above the floor).
        pitch_deg: downward tilt of the optical axis (default 0).
        rate_hz: frame rate of the mapping drive (default 3).
        pixel_noise: sigma of colour noise, grey levels (default 2).
    """

    width: int = 320
    height: int = 240
    hfov_deg: float = 57.0
    vfov_deg: float = 43.0
    min_depth: float = 0.5
    max_depth: float = 4.5
    sigma_depth_k: float = 1.5e-3
    max_incidence_deg: float = 75.0
    depth_scale: float = 5000.0
    body_t_camera: tuple[float, float, float] = (0.15, 0.0, 0.45)
    pitch_deg: float = 0.0
    rate_hz: float = 3.0
    pixel_noise: float = 2.0

    @property
    def fx(self) -> float:
        """Focal length in pixels from the horizontal field of view."""
        return (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def fy(self) -> float:
        """Focal length in pixels from the vertical field of view."""
        return (self.height / 2.0) / math.tan(math.radians(self.vfov_deg) / 2.0)

    @property
    def cx(self) -> float:
        """Principal point column (image centre, OpenCV pixel convention)."""
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        """Principal point row."""
        return (self.height - 1) / 2.0

    def K(self) -> FloatArray:  # noqa: N802 - the usual name of the intrinsic matrix
        """Intrinsic matrix (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def body_R_camera(self) -> FloatArray:  # noqa: N802
        """(3, 3) columns = camera x, y, z axes in body coordinates (forward, tilted by pitch)."""
        forward = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
        p = math.radians(self.pitch_deg)
        tilt = np.array(
            [[math.cos(p), 0.0, math.sin(p)], [0.0, 1.0, 0.0], [-math.sin(p), 0.0, math.cos(p)]]
        )
        return tilt @ forward

    def body_T_camera(self) -> FloatArray:  # noqa: N802
        """(4, 4) homogeneous transform of camera points into the body frame."""
        T = np.eye(4)
        T[:3, :3] = self.body_R_camera()
        T[:3, 3] = self.body_t_camera
        return T


def world_T_body_3d(pose: FloatArray) -> FloatArray:  # noqa: N802
    """(4, 4) transform of a planar pose ``(x, y, theta)`` (conventions.md), z = 0 on the floor."""
    x, y, th = (float(v) for v in pose)
    T = np.eye(4)
    c, s = math.cos(th), math.sin(th)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = (x, y)
    return T


def world_T_camera(pose: FloatArray, config: KinectConfig) -> FloatArray:  # noqa: N802
    """(4, 4) camera pose in the world for a planar robot pose ``(x, y, theta)``."""
    return world_T_body_3d(pose) @ config.body_T_camera()


class KinectRenderer:
    """Renders RGB-D frames of one scene (the Open3D scene is built once).

    Args:
        scene: the world's 3-D content.
        config: the sensor.
    """

    def __init__(self, scene: Scene3D, config: KinectConfig = KinectConfig()) -> None:
        import open3d as o3d

        self.config = config
        self.mesh: TriangleScene = triangle_scene(scene)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.mesh.vertices, np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.mesh.triangles, np.uint32)),
        )
        u, v = np.meshgrid(
            np.arange(config.width, dtype=np.float64), np.arange(config.height, dtype=np.float64)
        )
        self._dirs_cam = np.stack(
            [(u - config.cx) / config.fx, (v - config.cy) / config.fy, np.ones_like(u)], axis=-1
        )
        self._cos_max = math.cos(math.radians(config.max_incidence_deg))
        light = np.array([0.3, 0.5, 0.8])
        self._light = light / np.linalg.norm(light)

    def render(
        self, world_T_cam: FloatArray, rng: np.random.Generator | None = None
    ) -> tuple[ImageU8, ImageU16]:  # noqa: N803
        """Render one frame.

        Args:
            world_T_cam: (4, 4) camera pose in the world.
            rng: noise source; None gives noise-free depth and colour.

        Returns:
            ``rgb`` uint8 (H, W, 3) RGB and ``depth`` uint16 (H, W) in units of
            ``1 / depth_scale`` metres, 0 where there is no depth (out of range,
            grazing angle, no surface).
        """
        import open3d as o3d

        cfg = self.config
        rot = world_T_cam[:3, :3]
        dirs = self._dirs_cam @ rot.T
        origin = np.broadcast_to(world_T_cam[:3, 3], dirs.shape)
        rays = np.concatenate([origin, dirs], axis=-1).astype(np.float32)
        ans = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        z = ans["t_hit"].numpy().astype(np.float64)  # ray direction has unit camera-z: t = depth
        hit = np.isfinite(z)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        prim = np.where(hit, prim, 0)
        normals = ans["primitive_normals"].numpy().astype(np.float64)
        uvs = ans["primitive_uvs"].numpy().astype(np.float64)
        dir_norm = np.linalg.norm(dirs, axis=-1)
        cos_inc = np.abs(np.sum(normals * dirs, axis=-1)) / dir_norm
        # colour: base colour or texture lookup, Lambert shading
        m = self.mesh
        color = m.colors[prim].astype(np.float64)
        tex_idx = np.where(hit, m.texture_index[prim], -1)
        for k, tex in enumerate(m.textures):
            sel = tex_idx == k
            if not np.any(sel):
                continue
            tc = m.tex_coords[prim[sel]]  # (n, 3, 2)
            a, b = uvs[sel, 0:1], uvs[sel, 1:2]
            st = (1 - a - b) * tc[:, 0] + a * tc[:, 1] + b * tc[:, 2]
            col = np.clip(np.rint(st[:, 0] * (tex.shape[1] - 1)), 0, tex.shape[1] - 1).astype(int)
            row = np.clip(np.rint(st[:, 1] * (tex.shape[0] - 1)), 0, tex.shape[0] - 1).astype(int)
            color[sel] = tex[row, col] / 255.0
        shade = 0.45 + 0.55 * np.abs(normals @ self._light)
        rgb = color * shade[..., None] * 255.0
        rgb[~hit] = 0.0
        if rng is not None and cfg.pixel_noise > 0:
            rgb = rgb + rng.normal(0.0, cfg.pixel_noise, rgb.shape)
        rgb_u8 = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
        # depth: noise grows with z^2, drop-outs at grazing angles and out of range
        if rng is not None and cfg.sigma_depth_k > 0:
            z = np.where(
                hit,
                z + rng.normal(0.0, 1.0, z.shape) * cfg.sigma_depth_k * np.where(hit, z, 0.0) ** 2,
                z,
            )
        valid = hit & (z >= cfg.min_depth) & (z <= cfg.max_depth) & (cos_inc >= self._cos_max)
        depth = np.zeros(z.shape, np.uint16)
        depth[valid] = np.clip(np.rint(z[valid] * cfg.depth_scale), 1, 65535).astype(np.uint16)
        return rgb_u8, depth

    def render_pose(
        self, pose: FloatArray, rng: np.random.Generator | None = None
    ) -> tuple[ImageU8, ImageU16]:
        """Render at a planar robot pose ``(x, y, theta)`` (world, metres/rad)."""
        return self.render(world_T_camera(pose, self.config), rng)


# ---------------------------------------------------------------------------- writer
def rotation_to_quaternion(R: FloatArray) -> FloatArray:  # noqa: N803
    """(4,) unit quaternion ``(qx, qy, qz, qw)`` of a rotation matrix (3, 3), ``qw >= 0``.

    Shepperd's method (J. Guidance and Control 1(3), 1978): the largest of
    ``4 qw^2 = 1 + tr R`` and ``4 qi^2 = 1 + 2 R_ii - tr R`` is taken from the
    diagonal, the other three components from the off-diagonal sums and
    differences, so no component is divided by a small number (the method
    SciPy's ``Rotation.from_matrix`` uses, without importing SciPy per run).
    """
    m = np.asarray(R, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    k = int(np.argmax([m[0, 0], m[1, 1], m[2, 2], tr]))
    if k == 3:
        q = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 1.0 + tr])
    else:
        i, j, n = k, (k + 1) % 3, (k + 2) % 3
        q = np.empty(4)
        q[i] = 1.0 - tr + 2.0 * m[i, i]
        q[j] = m[j, i] + m[i, j]
        q[n] = m[n, i] + m[i, n]
        q[3] = m[n, j] - m[j, n]
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def kinect_intrinsics_dict(config: KinectConfig) -> dict[str, object]:
    """The self-describing ``kinect.yaml`` content of a config."""
    return {
        "format_version": FORMAT_VERSION,
        "layout": "TUM RGB-D (rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt)",
        "width": int(config.width),
        "height": int(config.height),
        "fx": float(config.fx),
        "fy": float(config.fy),
        "cx": float(config.cx),
        "cy": float(config.cy),
        "depth_scale": float(config.depth_scale),
        "depth_units": "png value / depth_scale = metres along the optical axis; 0 = none",
        "min_depth": float(config.min_depth),
        "max_depth": float(config.max_depth),
        "body_t_camera": [float(v) for v in config.body_t_camera],
        "body_R_camera": config.body_R_camera().tolist(),
        "camera_frame": "OpenCV: x right, y down, z optical axis",
        "groundtruth": "groundtruth.txt = world_T_camera (TUM: t tx ty tz qx qy qz qw)",
        "sim_config": asdict(config),
    }


class TumRgbdWriter:
    """Writes frames one at a time in the TUM RGB-D layout (module docstring).

    The lists are flushed after each frame, so an interrupted run leaves a valid
    sequence of the frames written so far.

    Args:
        out: the directory to create (e.g. ``RUN/kinect``).
        config: the sensor (written to ``kinect.yaml``).
    """

    def __init__(self, out: str | Path, config: KinectConfig) -> None:
        self.out = Path(out)
        self.config = config
        (self.out / "rgb").mkdir(parents=True, exist_ok=True)
        (self.out / "depth").mkdir(parents=True, exist_ok=True)
        write_text_atomic(self.out / "kinect.yaml",
                          yaml.safe_dump(kinect_intrinsics_dict(config), sort_keys=False))
        self._rgb = open(self.out / "rgb.txt", "w", encoding="utf-8")  # noqa: SIM115 (closed in close())
        self._depth = open(self.out / "depth.txt", "w", encoding="utf-8")  # noqa: SIM115
        self._gt = open(self.out / "groundtruth.txt", "w", encoding="utf-8")  # noqa: SIM115
        self._rgb.write("# color images\n# timestamp filename\n")
        self._depth.write(
            f"# depth maps\n# depth_scale {config.depth_scale:g} (value / depth_scale = metres)\n"
        )
        self._depth.write("# timestamp filename\n")
        self._gt.write("# world_T_camera\n# timestamp tx ty tz qx qy qz qw\n")
        self.count = 0

    def write(self, t: float, rgb: ImageU8, depth: ImageU16, world_T_cam: FloatArray) -> None:  # noqa: N803
        """Write one frame: RGB uint8 (H, W, 3), depth uint16 (H, W), camera pose (4, 4)."""
        name = f"{t:.6f}.png"
        if not cv2.imwrite(str(self.out / "rgb" / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise DatasetError("could not write image", self.out / "rgb" / name)
        if not cv2.imwrite(str(self.out / "depth" / name), depth):
            raise DatasetError("could not write image", self.out / "depth" / name)
        self._rgb.write(f"{t:.6f} rgb/{name}\n")
        self._depth.write(f"{t:.6f} depth/{name}\n")
        q = rotation_to_quaternion(world_T_cam[:3, :3])
        p = world_T_cam[:3, 3]
        self._gt.write(
            f"{t:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} "
            f"{q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}\n"
        )
        for fh in (self._rgb, self._depth, self._gt):
            fh.flush()
        self.count += 1

    def close(self) -> None:
        """Close the lists."""
        for fh in (self._rgb, self._depth, self._gt):
            fh.close()


# ---------------------------------------------------------------------------- mapping drive
@dataclass(frozen=True)
class MappingDrive:
    """The zig-zag mapping drive (paper 2, sec. 2: the Kinect is short ranged).

    Attributes:
        lanes: lane coordinates, metres: first lanes along x at these ``y``, then lanes
            along y at these ``x`` (default ``(1.6, 3.3, 5.0, 6.7, 8.4)``).
        span: ``(lo, hi)`` extent of every lane, metres (default ``(1.6, 8.4)``).
        speed: cruise speed, m/s (default 0.3).
        both_directions: also drive the lanes along y (default True).
    """

    lanes: tuple[float, ...] = (1.6, 3.3, 5.0, 6.7, 8.4)
    span: tuple[float, float] = (1.6, 8.4)
    speed: float = 0.3
    both_directions: bool = True


def zigzag_waypoints(drive: MappingDrive) -> FloatArray:
    """Waypoints of the zig-zag: lanes along x (boustrophedon), then along y back.

    Returns:
        (K, 2) world waypoints, metres.
    """
    lo, hi = drive.span
    pts: list[tuple[float, float]] = []
    for i, y in enumerate(drive.lanes):
        a, b = (lo, hi) if i % 2 == 0 else (hi, lo)
        pts += [(a, y), (b, y)]
    if drive.both_directions:
        x_end = pts[-1][0]
        lanes = sorted(drive.lanes, key=lambda x: abs(x - x_end))
        y_now = pts[-1][1]
        for x in lanes:
            a, b = (y_now, lo if abs(y_now - hi) < abs(y_now - lo) else hi)
            pts += [(x, a), (x, b)]
            y_now = b
    out = [pts[0]]
    for p in pts[1:]:
        if np.hypot(p[0] - out[-1][0], p[1] - out[-1][1]) > 1e-6:
            out.append(p)
    return np.array(out, dtype=float)


def simulate_kinect_run(
    world: str | Path,
    out: str | Path,
    seed: int = 0,
    config: KinectConfig = KinectConfig(),
    duration: float | None = None,
    drive: MappingDrive | None = None,
    ceiling_images: bool = False,
) -> Path:
    """Simulate the zig-zag mapping drive of a world with the Kinect.

    Writes a logged run (``docs/log-format.md`` via :func:`lampsam.datasets.logrun.write_run`:
    ``rig.yaml``, ``odometry.csv`` with wheel slip (paper 1, eq. 15), ``groundtruth.tum``,
    ``landmarks.csv`` (the ceiling's true lamps and corners), ``meta.yaml``) plus
    ``kinect/`` in the TUM RGB-D layout. The robot follows the world's ``path``
    (or ``drive``'s zig-zag when given or when the world has none) with
    :func:`lampsam.datasets.motion.follow_waypoints` at the world's odometry
    rate; Kinect frames are taken at ``config.rate_hz`` (rounded to a whole
    number of odometry samples).

    With ``ceiling_images=True`` the ceiling simulator
    (:func:`lampsam.datasets.simulator.simulate_world`) writes the run first
    (ceiling images, odometry, truth of the same drive), so that the ceiling SLAM
    can provide the mapping poses; the Kinect frames are then rendered along its
    ``groundtruth.tum``.

    Args:
        world: built-in world name (``office``) or a world YAML with ``scene3d``.
        out: the run directory.
        seed: seed of the depth/colour noise and the wheel slip.
        config: the sensor.
        duration: seconds to simulate (default: the whole drive).
        drive: override of the drive.
        ceiling_images: also render the upward camera's images.

    Returns:
        The run directory.

    Raises:
        DatasetError: unknown world, no ``scene3d`` section, bad schema.
    """
    from lampsam.datasets.logrun import OdometryLog, Trajectory, read_tum, write_run
    from lampsam.datasets.motion import follow_waypoints, noisy_wheel_travel
    from lampsam.datasets.scene3d import scene_from_dict
    from lampsam.datasets.world import load_world
    from lampsam.datasets.world_landmarks import world_landmarks

    w = load_world(world)
    if "scene3d" not in w.extra:
        raise DatasetError("world has no 'scene3d' section", w.source)
    try:
        scene = scene_from_dict(w.extra["scene3d"])
    except DatasetError as exc:
        raise DatasetError(str(exc), w.source) from exc
    out = Path(out)
    rng = np.random.default_rng(seed)
    rate = float(w.simulation.odometry_rate_hz)
    if ceiling_images:
        from lampsam.datasets.simulator import simulate_world

        simulate_world(world, out, seed=seed, duration=duration)
        gt = read_tum(out / "groundtruth.tum")
        t, poses = gt.t, gt.poses
    else:
        if drive is None and len(w.waypoints) >= 2:
            waypoints, speed = w.waypoints, w.speed
        else:
            drive = drive or MappingDrive()
            waypoints, speed = zigzag_waypoints(drive), drive.speed
        t, poses, wheel = follow_waypoints(
            waypoints, speed=speed, rate_hz=rate, wheel_base=w.rig.odometry.wheel_base,
            start_heading=w.start_heading, duration=duration,
        )  # fmt: skip
        noisy = noisy_wheel_travel(wheel, w.rig.odometry.k_r, w.rig.odometry.k_l, rng)
        meta = {
            "world": w.name,
            "seed": int(seed),
            "simulator": "lampsam.datasets.kinect_sim",
            "duration_s": float(t[-1]),
        }
        write_run(
            out, w.rig, OdometryLog(t[1:], noisy[1:, 0], noisy[1:, 1]),
            groundtruth=Trajectory(t, poses),
            landmarks=world_landmarks(w), meta=meta,
        )  # fmt: skip
    add_kinect_meta(out, w.name, config)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0 / rate
    step = max(1, int(round(1.0 / (config.rate_hz * dt))))
    idx = np.arange(0, len(t), step)
    write_kinect_frames(out, scene, config, t, poses, idx, rng)
    log.info("kinect run %s: %.1f s, %d frames", out, t[-1], len(idx))
    return out


def write_kinect_frames(out: Path, scene: Scene3D, config: KinectConfig, t: FloatArray,
                        poses: FloatArray, idx: Iterable[int], rng: np.random.Generator) -> None:
    """Render and write the Kinect frames at the rows ``idx`` of a run's truth.

    Args:
        out: the run directory (frames go to ``out / KINECT_DIR`` in the TUM RGB-D layout).
        scene: the world's 3-D content.
        config: the Kinect model.
        t: (N,) times, s; poses: (N, 3) ``world_T_body`` x, y (m), theta (rad).
        idx: rows of ``t``/``poses`` to render, increasing.
        rng: depth and colour noise.
    """
    renderer = KinectRenderer(scene, config)
    writer = TumRgbdWriter(out / KINECT_DIR, config)
    try:
        for i in idx:
            T = world_T_camera(poses[i], config)
            rgb, depth = renderer.render(T, rng)
            writer.write(float(t[i]), rgb, depth, T)
    finally:
        writer.close()


def add_kinect_meta(run: Path, world_name: str, config: KinectConfig) -> None:
    """Record the Kinect part in the run's ``meta.yaml`` (kept if present)."""
    meta_path = run / "meta.yaml"
    meta: dict[str, object] = {}
    if meta_path.is_file():
        loaded = yaml.safe_load(meta_path.read_text(encoding="utf-8"))
        meta = dict(loaded) if isinstance(loaded, dict) else {}
    meta.setdefault("world", world_name)
    meta["kinect"] = {"dir": KINECT_DIR, "rate_hz": float(config.rate_hz), "layout": "TUM RGB-D"}
    write_text_atomic(meta_path, yaml.safe_dump(meta, sort_keys=False))
