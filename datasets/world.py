"""Ceiling worlds: YAML files describing ceilings, lamps, the rig and the robot's path.

A world is a YAML mapping (built-in ones live in ``datasets/worlds/``)::

    name: lab
    rig:                      # as rig.yaml; the camera may give hfov_deg instead of fx..cy
      camera: {width: 320, height: 240, hfov_deg: 120, body_t_camera: [0.1, 0, 0.3],
               mount_rpy_deg: [0, 0, 0]}   # optional tilt (lampsam.datasets.mounting)
      odometry: {wheel_base: 0.4, k_r: 2.0e-5, k_l: 2.0e-5}
    render: {supersample: 2, texel: 0.005, noise_sigma: 2.0, bloom: 0.0, background: 60}
    simulation: {odometry_rate_hz: 30, image_rate_hz: 15}
    path: {speed: 0.4, start_heading_deg: 0, waypoints: [[x, y], ...]}
    ceiling:
      corner_id_start: 1000   # ids of derived corner landmarks start here
      surfaces:               # horizontal, rectangular, any number of heights
        - name: lab
          height: 2.7         # m above the floor
          extent: [xmin, ymin, xmax, ymax]
          grey: 175           # base grey level (0-255)
          corners: false      # the extent's 4 corners are corner landmarks
          tiles: {pitch: [0.6, 0.6], origin: [0, 0], line_width: 0.02, grey: 125, corners: true}
          items:              # painted on the surface, in order
            - {kind: rect, center: [x, y], size: [sx, sy], yaw_deg: 0, grey: 45, corners: true}
            - {kind: disc, center: [x, y], radius: 0.06, grey: 235}
      lamps:
        - {id: 1, shape: rect, center: [x, y], height: 2.5, length: 1.2, width: 0.3,
           yaw_deg: 0, brightness: 320}
        - {id: 2, shape: round, center: [x, y], height: 2.7, diameter: 0.35}
        - {id: 3, shape: square, center: [x, y], height: 2.7, size: 0.6, yaw_deg: 0}
      openings:               # daylight: skylights and windows (lampsam.datasets.openings)
        - {kind: skylight, center: [x, y], size: [sx, sy], height: 2.9, brightness: 240}

Unknown top-level sections (e.g. ``scene3d`` of the office world) are kept in
:attr:`World.extra`, never rejected. Unknown keys inside the sections above are
errors (they are usually typos). Angles in the YAML are degrees (``_deg``); in
the dataclasses radians.

Corner landmarks are derived (:func:`lampsam.datasets.world_landmarks.world_landmarks`): tile-grid intersections
inside a surface (except those under an item or lamp of that surface), the four
corners of ``rect`` items and, when asked, of the surface's extent.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.camera import DEFAULT_BODY_R_CAMERA
from lampsam.datasets.logrun import Rig
from lampsam.datasets.mounting import mounted
from lampsam.datasets.openings import OPENING_KEYS, Opening, parse_opening
from lampsam.datasets.textio import read_yaml as _read_yaml
from lampsam.errors import DatasetError
from lampsam.strict_keys import check_keys, finite_array, number

log = logging.getLogger(__name__)

WORLDS_DIR = Path(__file__).resolve().parent / "worlds"
"""Folder of the built-in worlds (``<name>.yaml``)."""

LAMP_TYPES = {"rect": "lamp_rect", "round": "lamp_round", "square": "lamp_square"}
"""World lamp shapes and their ``landmarks.csv`` types."""


@dataclass(frozen=True)
class TileGrid:
    """Ceiling-tile grid lines painted on a surface.

    Attributes:
        pitch: ``(px, py)`` line spacing along world x and y, m.
        origin: ``(x, y)`` of one line intersection, m.
        line_width: width of the grid lines, m.
        grey: grey level of the lines.
        corners: the line intersections are corner landmarks.
    """

    pitch: tuple[float, float] = (0.6, 0.6)
    origin: tuple[float, float] = (0.0, 0.0)
    line_width: float = 0.02
    grey: float = 125.0
    corners: bool = True


@dataclass(frozen=True)
class TextureItem:
    """A flat mark on a surface: a rectangle (vent, panel) or a disc (detector, sprinkler).

    Attributes:
        kind: ``"rect"`` or ``"disc"``.
        center: ``(x, y)`` world, m.
        size: rect: ``(sx, sy)`` side lengths along its own axes, m; disc: ``(d, d)``.
        yaw: rotation of the rect's first side from world x, rad.
        grey: grey level.
        corners: (rect) its four corners are corner landmarks.
    """

    kind: str
    center: tuple[float, float]
    size: tuple[float, float]
    yaw: float = 0.0
    grey: float = 50.0
    corners: bool = False

    def corner_points(self) -> FloatArray:
        """(4, 2) world corners of a rect (counter-clockwise)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        hx, hy = self.size[0] / 2, self.size[1] / 2
        local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
        return np.asarray(self.center) + local @ np.array([[c, s], [-s, c]])


@dataclass(frozen=True)
class Surface:
    """A horizontal rectangular ceiling surface.

    Attributes:
        name: label.
        height: height above the floor, m.
        extent: ``(xmin, ymin, xmax, ymax)`` world, m.
        grey: base grey level.
        tiles: grid lines, or None.
        items: marks painted on it, in order.
        corners: the extent's corners are corner landmarks (e.g. a soffit or duct).
    """

    name: str
    height: float
    extent: tuple[float, float, float, float]
    grey: float = 175.0
    tiles: TileGrid | None = None
    items: tuple[TextureItem, ...] = ()
    corners: bool = False

    def contains(self, xy: FloatArray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: points ``xy`` (N, 2) inside the extent shrunk by ``margin``."""
        x0, y0, x1, y1 = self.extent
        xy = np.asarray(xy).reshape(-1, 2)
        return (
            (xy[:, 0] >= x0 + margin)
            & (xy[:, 0] <= x1 - margin)
            & (xy[:, 1] >= y0 + margin)
            & (xy[:, 1] <= y1 - margin)
        )


@dataclass(frozen=True)
class Lamp:
    """A ceiling lamp (a bright flat shape, saturating the camera).

    Attributes:
        id: landmark id.
        shape: ``"rect"``, ``"round"`` or ``"square"``.
        center: ``(x, y)`` world, m.
        height: height of the lamp's face above the floor, m.
        length: rect: long side; round: diameter; square: side, m.
        width: rect: short side; otherwise equal to ``length``, m.
        yaw: direction of the long side (rect) or of one side (square) from world x, rad.
        brightness: grey level before saturation (values above 255 saturate).
    """

    id: int
    shape: str
    center: tuple[float, float]
    height: float
    length: float
    width: float
    yaw: float = 0.0
    brightness: float = 320.0

    def outline(self, n_round: int = 16) -> FloatArray:
        """(K, 2) world points on the outline (rect/square: corners and edge midpoints)."""
        cx, cy = self.center
        if self.shape == "round":
            a = np.linspace(0.0, 2 * np.pi, n_round, endpoint=False)
            r = self.length / 2
            return np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])
        hx, hy = self.length / 2, self.width / 2
        local = np.array(
            [[hx, hy], [0, hy], [-hx, hy], [-hx, 0], [-hx, -hy], [0, -hy], [hx, -hy], [hx, 0]]
        )
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([cx, cy]) + local @ np.array([[c, s], [-s, c]])

    def contains(self, xy: FloatArray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: points ``xy`` (N, 2) on the lamp grown by ``margin``, m."""
        d = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - np.asarray(self.center)
        if self.shape == "round":
            return np.hypot(d[:, 0], d[:, 1]) <= self.length / 2 + margin
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        lx = c * d[:, 0] + s * d[:, 1]
        ly = -s * d[:, 0] + c * d[:, 1]
        return (np.abs(lx) <= self.length / 2 + margin) & (np.abs(ly) <= self.width / 2 + margin)


@dataclass(frozen=True)
class RenderSettings:
    """How ceiling images are rendered.

    Attributes:
        supersample: ``S``: S x S rays per pixel, averaged (default 2).
        texel: resolution of the pre-rasterised surface textures, m (default 0.005).
        noise_sigma: std of additive Gaussian sensor noise, grey levels (default 2.0).
        bloom: strength of the glare around saturated areas, 0 = none (default 0.0).
        bloom_sigma: Gaussian radius of the glare, px (default 4.0).
        background: grey level where no surface is hit (walls, openings; default 60).
    """

    supersample: int = 2
    texel: float = 0.005
    noise_sigma: float = 2.0
    bloom: float = 0.0
    bloom_sigma: float = 4.0
    background: float = 60.0


@dataclass(frozen=True)
class SimulationSettings:
    """Sensor rates of a simulated run.

    Attributes:
        odometry_rate_hz: wheel-odometry rate (default 30).
        image_rate_hz: image rate; must divide the odometry rate (default 15).
    """

    odometry_rate_hz: float = 30.0
    image_rate_hz: float = 15.0


@dataclass(frozen=True, eq=False)
class World:
    """A ceiling world.

    Attributes:
        name: world name.
        source: the YAML file it came from, if any.
        rig: sensor rig.
        surfaces: ceiling surfaces.
        lamps: lamps.
        waypoints: (K, 2) path, world m (may be empty).
        speed: robot cruise speed, m/s.
        start_heading: initial heading, rad, or None (face the second waypoint).
        render: rendering settings.
        simulation: rates.
        corner_id_start: first id of derived corner landmarks.
        description: free text.
        openings: daylight openings (skylights, windows), not landmarks.
        extra: unknown top-level sections, kept as parsed (e.g. ``scene3d``).
    """

    name: str
    source: Path | None
    rig: Rig
    surfaces: tuple[Surface, ...]
    lamps: tuple[Lamp, ...]
    waypoints: FloatArray
    speed: float = 0.4
    start_heading: float | None = None
    render: RenderSettings = field(default_factory=RenderSettings)
    simulation: SimulationSettings = field(default_factory=SimulationSettings)
    corner_id_start: int = 1000
    description: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    openings: tuple[Opening, ...] = ()


# --------------------------------------------------------------------------- parsing
_KNOWN_TOP = {"name", "description", "rig", "render", "simulation", "path", "ceiling"}


class _Ctx:
    """Error context: the file being parsed; the strict checks of
    :mod:`lampsam.strict_keys` with its messages (``key.path: problem``, the file named)."""

    def __init__(self, path: Path | None):
        """Remember the file for error messages."""
        self.path = path

    def fail(self, where: str, msg: str) -> DatasetError:
        """A DatasetError ``where: msg`` naming the world file."""
        return DatasetError(f"{where}: {msg}", self.path)

    def keys(self, d: Any, where: str, allowed: set[str], required: set[str]) -> None:
        """DatasetError unless ``d`` is a mapping with the required and only allowed keys."""
        check_keys(d, where, allowed, required, fail=self.fail)

    def num(self, d: Mapping[str, Any], key: str, where: str, default: float | None = None,
            **checks: bool) -> float:
        """A finite number ``d[key]`` (or the default); ``checks``: ``positive``,
        ``nonneg``, ``integer`` (:func:`lampsam.strict_keys.number`)."""
        return number(d, key, where, fail=self.fail, default=default, **checks)

    def vec(self, value: Any, n: int, where: str) -> tuple[float, ...]:
        """A tuple of ``n`` finite numbers, or DatasetError naming ``where``."""
        return tuple(float(x) for x in finite_array(value, (n,), where, fail=self.fail))


def _with_mount(ctx: _Ctx, rig: Any) -> Any:
    """The rig mapping with ``camera.mount_rpy_deg`` turned into ``body_R_camera``.

    See :mod:`lampsam.datasets.mounting`; other rigs are returned unchanged.
    """
    if not isinstance(rig, Mapping) or not isinstance(rig.get("camera"), Mapping):
        return rig
    cam = dict(rig["camera"])
    if "mount_rpy_deg" not in cam:
        return rig
    rpy = ctx.vec(cam.pop("mount_rpy_deg"), 3, "rig.camera.mount_rpy_deg")
    up = cam.get("body_R_camera", DEFAULT_BODY_R_CAMERA)
    try:
        cam["body_R_camera"] = mounted(np.asarray(up, dtype=np.float64).reshape(3, 3), rpy).tolist()
    except ValueError as exc:
        raise ctx.fail("rig.camera.body_R_camera", f"expected a 3x3 matrix, got {up!r}") from exc
    return {**rig, "camera": cam}


def _parse_item(ctx: _Ctx, d: Any, where: str) -> TextureItem:
    """One texture mark of a surface."""
    ctx.keys(d, where, {"kind", "center", "size", "radius", "yaw_deg", "grey", "corners"},
                {"kind", "center"})  # fmt: skip
    kind = d["kind"]
    center = ctx.vec(d["center"], 2, f"{where}.center")
    grey = ctx.num(d, "grey", where, 50.0, nonneg=True)
    if kind == "rect":
        size = ctx.vec(d.get("size"), 2, f"{where}.size")
        if min(size) <= 0:
            raise ctx.fail(f"{where}.size", "must be > 0")
        yaw = math.radians(ctx.num(d, "yaw_deg", where, 0.0))
        return TextureItem("rect", center, size, yaw, grey, bool(d.get("corners", False)))  # type: ignore[arg-type]
    if kind == "disc":
        r = ctx.num(d, "radius", where, positive=True)
        return TextureItem("disc", center, (2 * r, 2 * r), 0.0, grey, False)  # type: ignore[arg-type]
    raise ctx.fail(f"{where}.kind", f"must be 'rect' or 'disc', got {kind!r}")


def _parse_surface(ctx: _Ctx, d: Any, where: str) -> Surface:
    """One ceiling surface (with its tile grid and marks)."""
    ctx.keys(d, where, {"name", "height", "extent", "grey", "tiles", "items", "corners"},
                {"height", "extent"})  # fmt: skip
    ext = ctx.vec(d["extent"], 4, f"{where}.extent")
    if not (ext[2] > ext[0] and ext[3] > ext[1]):
        raise ctx.fail(f"{where}.extent", "needs xmin < xmax and ymin < ymax")
    tiles = None
    if d.get("tiles") is not None:
        t = d["tiles"]
        tw = f"{where}.tiles"
        ctx.keys(t, tw, {"pitch", "origin", "line_width", "grey", "corners"}, {"pitch"})
        pitch = t["pitch"]
        pitch2 = ctx.vec([pitch, pitch] if np.isscalar(pitch) else pitch, 2, f"{tw}.pitch")
        if min(pitch2) <= 0:
            raise ctx.fail(f"{tw}.pitch", "must be > 0")
        tiles = TileGrid(
            pitch=pitch2,  # type: ignore[arg-type]
            origin=ctx.vec(t.get("origin", [ext[0], ext[1]]), 2, f"{tw}.origin"),  # type: ignore[arg-type]
            line_width=ctx.num(t, "line_width", tw, 0.02, positive=True),
            grey=ctx.num(t, "grey", tw, 125.0, nonneg=True),
            corners=bool(t.get("corners", True)),
        )
    items = d.get("items") or []
    if not isinstance(items, list):
        raise ctx.fail(f"{where}.items", "must be a list")
    return Surface(
        name=str(d.get("name", where)),
        height=ctx.num(d, "height", where, positive=True),
        extent=ext,  # type: ignore[arg-type]
        grey=ctx.num(d, "grey", where, 175.0, nonneg=True),
        tiles=tiles,
        items=tuple(_parse_item(ctx, it, f"{where}.items[{k}]") for k, it in enumerate(items)),
        corners=bool(d.get("corners", False)),
    )


def _parse_lamp(ctx: _Ctx, d: Any, where: str) -> Lamp:
    """One lamp; ``diameter`` (round) and ``size`` (square) set length = width."""
    allowed = {"id", "shape", "center", "height", "length", "width", "diameter", "size",
               "yaw_deg", "brightness"}  # fmt: skip
    ctx.keys(d, where, allowed, {"id", "shape", "center", "height"})
    shape = d["shape"]
    lamp_id = int(ctx.num(d, "id", where, integer=True))
    center = ctx.vec(d["center"], 2, f"{where}.center")
    height = ctx.num(d, "height", where, positive=True)
    yaw = math.radians(ctx.num(d, "yaw_deg", where, 0.0))
    bright = ctx.num(d, "brightness", where, 320.0, positive=True)
    if shape == "rect":
        length = ctx.num(d, "length", where, positive=True)
        width = ctx.num(d, "width", where, positive=True)
        if width > length:
            raise ctx.fail(where, "rect lamp: width must not exceed length")
    elif shape == "round":
        length = width = ctx.num(d, "diameter", where, positive=True)
    elif shape == "square":
        length = width = ctx.num(d, "size", where, positive=True)
    else:
        raise ctx.fail(f"{where}.shape", f"must be rect, round or square, got {shape!r}")
    return Lamp(lamp_id, shape, center, height, length, width, yaw, bright)  # type: ignore[arg-type]


def world_from_dict(doc: Any, source: Path | None = None) -> World:
    """Build a :class:`World` from a parsed world YAML (schema in the module docstring).

    Raises:
        DatasetError: a missing or malformed entry, named by its key path and the file.
    """
    ctx = _Ctx(source)
    if not isinstance(doc, Mapping):
        raise ctx.fail("world", "must be a mapping")
    rig = Rig.from_dict(_with_mount(ctx, doc.get("rig") or {}), source)
    rd = doc.get("render") or {}
    ctx.keys(rd, "render", {"supersample", "texel", "noise_sigma", "bloom", "bloom_sigma",
                                    "background"}, set())  # fmt: skip
    render = RenderSettings(
        supersample=int(ctx.num(rd, "supersample", "render", 2, positive=True, integer=True)),
        texel=ctx.num(rd, "texel", "render", 0.005, positive=True),
        noise_sigma=ctx.num(rd, "noise_sigma", "render", 2.0, nonneg=True),
        bloom=ctx.num(rd, "bloom", "render", 0.0, nonneg=True),
        bloom_sigma=ctx.num(rd, "bloom_sigma", "render", 4.0, positive=True),
        background=ctx.num(rd, "background", "render", 60.0, nonneg=True),
    )
    sd = doc.get("simulation") or {}
    ctx.keys(sd, "simulation", {"odometry_rate_hz", "image_rate_hz"}, set())
    sim = SimulationSettings(
        odometry_rate_hz=ctx.num(sd, "odometry_rate_hz", "simulation", 30.0, positive=True),
        image_rate_hz=ctx.num(sd, "image_rate_hz", "simulation", 15.0, positive=True),
    )
    ratio = sim.odometry_rate_hz / sim.image_rate_hz
    if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise ctx.fail("simulation", "odometry_rate_hz must be a multiple of image_rate_hz")
    pd = doc.get("path") or {}
    ctx.keys(pd, "path", {"speed", "start_heading_deg", "waypoints"}, set())
    wps = pd.get("waypoints") or []
    try:
        waypoints = np.asarray(wps, dtype=np.float64).reshape(-1, 2)
    except (TypeError, ValueError) as exc:
        raise ctx.fail("path.waypoints", "must be a list of [x, y]") from exc
    if not np.all(np.isfinite(waypoints)):
        raise ctx.fail("path.waypoints", "must be finite")
    start = None if pd.get("start_heading_deg") is None else ctx.num(pd, "start_heading_deg", "path")
    cd = doc.get("ceiling") or {}
    ctx.keys(cd, "ceiling", {"surfaces", "lamps", "corner_id_start", "openings"}, set())
    surfaces = tuple(
        _parse_surface(ctx, s, f"ceiling.surfaces[{k}]")
        for k, s in enumerate(cd.get("surfaces") or [])
    )
    lamps = tuple(
        _parse_lamp(ctx, s, f"ceiling.lamps[{k}]") for k, s in enumerate(cd.get("lamps") or [])
    )
    openings = []
    for k, od in enumerate(cd.get("openings") or []):
        where = f"ceiling.openings[{k}]"
        ctx.keys(od, where, OPENING_KEYS, {"kind", "center", "size", "height"})
        openings.append(
            parse_opening(
                od,
                where,
                ctx.num,
                ctx.vec,
                ctx.fail,
            )
        )
    ids = [lp.id for lp in lamps]
    if len(set(ids)) != len(ids):
        raise ctx.fail("ceiling.lamps", "duplicate lamp ids")
    corner_start = int(ctx.num(cd, "corner_id_start", "ceiling", 1000, integer=True))
    if ids and max(ids) >= corner_start:
        raise ctx.fail("ceiling.lamps", f"lamp ids must be below corner_id_start={corner_start}")
    z_cam = rig.camera.z_cam
    for s in surfaces:
        if s.height <= z_cam + 0.1:
            raise ctx.fail(f"surface {s.name!r}", "must be more than 0.1 m above the camera")
    for lp in lamps:
        if lp.height <= z_cam + 0.1:
            raise ctx.fail(f"lamp {lp.id}", "must be more than 0.1 m above the camera")
    return World(
        name=str(doc.get("name", source.stem if source else "world")),
        source=source,
        rig=rig,
        surfaces=surfaces,
        lamps=lamps,
        waypoints=waypoints,
        speed=ctx.num(pd, "speed", "path", 0.4, positive=True),
        start_heading=None if start is None else math.radians(float(start)),
        render=render,
        simulation=sim,
        corner_id_start=corner_start,
        description=str(doc.get("description", "")),
        extra={k: v for k, v in doc.items() if k not in _KNOWN_TOP},
        openings=tuple(openings),
    )


def world_path(world: str | Path) -> Path:
    """The YAML file of a built-in world name, or ``world`` itself when it is a path."""
    p = Path(world)
    if p.suffix in (".yaml", ".yml") or p.parent != Path("."):
        return p
    return WORLDS_DIR / f"{world}.yaml"


def builtin_worlds() -> list[str]:
    """Names of the built-in worlds."""
    return sorted(p.stem for p in WORLDS_DIR.glob("*.yaml"))


def load_world(world: str | Path) -> World:
    """Load a built-in world by name (``lab``, ``corridor``, ...) or a world YAML file.

    Raises:
        DatasetError: unknown name, missing file, invalid YAML or schema errors.
    """
    path = world_path(world)
    if not path.is_file():
        raise DatasetError(
            f"world not found (built-in: {', '.join(builtin_worlds())}; or give a YAML path)",
            path,
        )
    return world_from_dict(_read_yaml(path), path)
