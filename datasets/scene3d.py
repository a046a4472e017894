"""Three-dimensional world content for the forward RGB-D sensor (paper 2, sec. 2).

A world YAML may carry a top-level ``scene3d`` section (the world loader keeps
unknown sections). It describes what a Kinect-like sensor sees: the floor, the
walls (with door openings), furniture as boxes, and textured pictures/posters
hung on the walls, plus named ``changes`` used by later localization trials
(furniture moved or removed, pictures taken down: paper 2, Figs. 1-2 and 14).

Schema (all lengths in metres, angles in degrees with a ``_deg`` suffix, world
frame of ``docs/conventions.md``: ``z`` up, ``z = 0`` the floor)::

    scene3d:
      height: 3.0                     # floor-to-ceiling height
      floor_color: [0.55, 0.55, 0.52] # RGB in [0, 1]
      ceiling_color: [0.92, 0.92, 0.9]
      wall_thickness: 0.1             # default for walls
      wall_height: 3.0                # default for walls (default: height)
      walls:                          # centre line segments
        - {id: north, start: [0, 10], end: [10, 10], color: [0.85, 0.83, 0.78]}
      doors:                          # openings cut into a wall
        - {id: d1, wall: north, along: 5.0, width: 0.9, height: 2.1, open: true}
      furniture:                      # boxes standing on the floor (or at base_z)
        - {id: desk1, center: [2, 3], size: [1.6, 0.8, 0.75], yaw_deg: 0, color: [...]}
      pictures:                       # textured rectangles (SIFT-rich)
        - {id: p1, center: [3, 9.94, 1.4], width: 1.0, height: 0.7, facing_deg: -90, seed: 1}
      changes:                        # named edits for localization trials
        - {name: desk_moved, move: {desk1: {center: [3, 3], yaw_deg: 30}}}
        - {name: pictures_down, remove: [p1]}

``along`` is the distance of the door centre from the wall's ``start``;
``facing_deg`` is the heading of the picture's outward normal (the direction a
viewer looks *from*). Pictures and furniture in ``changes`` are referred to by
``id``.

The module only builds geometry (boxes, textured quads, triangle meshes and a
floor-plan footprint); rendering is in :mod:`lampsam.datasets.kinect_sim`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.errors import DatasetError
from lampsam.strict_keys import finite_array, number

log = logging.getLogger(__name__)

SCENE_VERSION = 1
"""Version of the ``scene3d`` schema."""

KIND_FLOOR = "floor"
KIND_CEILING = "ceiling"
KIND_WALL = "wall"
KIND_DOOR = "door"
KIND_FURNITURE = "furniture"
KIND_PICTURE = "picture"

@dataclass(frozen=True)
class Box:
    """A rectangular box, yawed about the vertical axis.

    Attributes:
        id: unique name.
        kind: one of ``wall``, ``door``, ``furniture``.
        center: (3,) world centre, metres.
        size: (3,) extent along the box's own x, y, z, metres.
        yaw: rotation of the box's x axis from world x, rad (CCW).
        color: (3,) RGB in [0, 1].
    """

    id: str
    kind: str
    center: FloatArray
    size: FloatArray
    yaw: float
    color: FloatArray

    def corners(self) -> FloatArray:
        """The 8 corners, (8, 3) world metres; index bits (x, y, z) = (i & 1, i & 2, i & 4)."""
        signs = np.array(
            [[(i & 1) * 2 - 1, ((i >> 1) & 1) * 2 - 1, ((i >> 2) & 1) * 2 - 1] for i in range(8)],
            float,
        )
        local = signs * (self.size / 2.0)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return local @ rot.T + self.center

    def footprint(self) -> FloatArray:
        """Floor-plan outline, (4, 2) world metres, counter-clockwise."""
        return self.corners()[[0, 1, 3, 2], :2]

    def z_range(self) -> tuple[float, float]:
        """Bottom and top height, metres."""
        return float(self.center[2] - self.size[2] / 2), float(self.center[2] + self.size[2] / 2)


@dataclass(frozen=True)
class Picture:
    """A textured rectangle (picture, poster) facing into the room.

    Attributes:
        id: unique name.
        center: (3,) world centre of the picture, metres.
        width: horizontal size, metres.
        height: vertical size, metres.
        facing: heading of the outward normal, rad (CCW from world x).
        seed: seed of the procedural texture.
    """

    id: str
    center: FloatArray
    width: float
    height: float
    facing: float
    seed: int

    def corners(self) -> FloatArray:
        """(4, 3) world corners: top-left, top-right, bottom-right, bottom-left (viewer's view)."""
        right = np.array([-math.sin(self.facing), math.cos(self.facing), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        hw, hh = self.width / 2, self.height / 2
        c = self.center
        return np.array(
            [
                c - right * hw + up * hh,
                c + right * hw + up * hh,
                c + right * hw - up * hh,
                c - right * hw - up * hh,
            ]
        )


@dataclass(frozen=True)
class Change:
    """A named edit of the scene for a localization trial.

    Attributes:
        name: the change's name.
        remove: ids of furniture or pictures taken away.
        move: id -> (new centre (2,) or (3,) metres, new yaw rad or None).
    """

    name: str
    remove: tuple[str, ...] = ()
    move: Mapping[str, tuple[FloatArray, float | None]] = field(default_factory=dict)


@dataclass(frozen=True)
class Scene3D:
    """The 3-D content of a world.

    Attributes:
        height: floor-to-ceiling height, metres.
        bounds: (4,) ``x_min, y_min, x_max, y_max`` of the floor and ceiling planes, metres.
        boxes: walls, closed doors and furniture.
        pictures: textured rectangles.
        changes: name -> :class:`Change`.
        floor_color: (3,) RGB in [0, 1].
        ceiling_color: (3,) RGB in [0, 1].
    """

    height: float
    bounds: FloatArray
    boxes: tuple[Box, ...]
    pictures: tuple[Picture, ...]
    changes: Mapping[str, Change]
    floor_color: FloatArray
    ceiling_color: FloatArray

    def ids(self) -> set[str]:
        """All object ids."""
        return {b.id for b in self.boxes} | {p.id for p in self.pictures}


# ---------------------------------------------------------------------------- parsing
def _fail(key: str, problem: str) -> DatasetError:
    """``scene3d.key: problem``, the key's path in the world file (the file itself is
    added by :func:`load_scene`)."""
    return DatasetError(f"{key if key.startswith('scene3d') else 'scene3d.' + key}: {problem}")


def _vec(value: Any, n: int, where: str) -> FloatArray:
    """``value`` as ``n`` finite floats, or a DatasetError naming ``where``
    (:func:`lampsam.strict_keys.finite_array`)."""
    return finite_array(value, (n,), where, fail=_fail)


def _num(item: Mapping[str, Any], key: str, where: str, default: float | None = None) -> float:
    """``item[key]`` as a finite float (``default`` when absent and given;
    :func:`lampsam.strict_keys.number`)."""
    return number(item, key, where, fail=_fail, default=default)


def _wall_boxes(
    wall: Mapping[str, Any],
    doors: list[Mapping[str, Any]],
    thickness: float,
    height: float,
    where: str,
) -> list[Box]:
    """Split one wall into boxes around its door openings; closed doors become door boxes."""
    wid = str(wall.get("id", where))
    start = _vec(wall.get("start"), 2, f"{where}.start")
    end = _vec(wall.get("end"), 2, f"{where}.end")
    thick = _num(wall, "thickness", where, thickness)
    h = _num(wall, "height", where, height)
    color = _vec(wall.get("color", [0.85, 0.83, 0.78]), 3, f"{where}.color")
    length = float(np.linalg.norm(end - start))
    if length <= 1e-6:
        raise DatasetError(f"scene3d: {where}: wall '{wid}' has zero length")
    direction = (end - start) / length
    yaw = math.atan2(direction[1], direction[0])
    pieces: list[
        tuple[float, float, float, float, str, str, FloatArray]
    ] = []  # s0, s1, z0, z1, id, kind, colour
    cuts: list[tuple[float, float, float, Mapping[str, Any]]] = []
    for j, door in enumerate(doors):
        dwhere = f"doors[{door.get('id', j)}]"
        along = _num(door, "along", dwhere)
        width = _num(door, "width", dwhere, 0.9)
        dh = min(_num(door, "height", dwhere, 2.1), h)
        s0, s1 = along - width / 2, along + width / 2
        if s0 < 0 or s1 > length:
            raise DatasetError(
                f"scene3d: {dwhere}: door lies outside wall '{wid}' (0..{length:.2f} m)"
            )
        cuts.append((s0, s1, dh, door))
    cuts.sort(key=lambda c: c[0])
    cursor = 0.0
    for s0, s1, dh, door in cuts:
        if s0 < cursor - 1e-9:
            raise DatasetError(f"scene3d: doors of wall '{wid}' overlap")
        if s0 > cursor:
            pieces.append((cursor, s0, 0.0, h, f"{wid}#{len(pieces)}", KIND_WALL, color))
        if dh < h:
            pieces.append((s0, s1, dh, h, f"{wid}#{len(pieces)}", KIND_WALL, color))  # lintel
        if not bool(door.get("open", True)):
            dcolor = _vec(door.get("color", [0.45, 0.3, 0.18]), 3, f"doors[{door.get('id')}].color")
            pieces.append((s0, s1, 0.0, dh, str(door.get("id", f"{wid}-door")), KIND_DOOR, dcolor))
        cursor = s1
    if cursor < length:
        pieces.append((cursor, length, 0.0, h, f"{wid}#{len(pieces)}", KIND_WALL, color))
    boxes = []
    for s0, s1, z0, z1, pid, kind, col in pieces:
        mid = start + direction * (s0 + s1) / 2
        t = thick * (0.6 if kind == KIND_DOOR else 1.0)
        boxes.append(
            Box(
                pid,
                kind,
                np.array([mid[0], mid[1], (z0 + z1) / 2]),
                np.array([s1 - s0, t, z1 - z0]),
                yaw,
                col,
            )
        )
    return boxes


def scene_from_dict(section: Mapping[str, Any], bounds: Iterable[float] | None = None) -> Scene3D:
    """Build a :class:`Scene3D` from a world YAML's ``scene3d`` section.

    Args:
        section: the parsed ``scene3d`` mapping (schema in the module docstring).
        bounds: ``x_min, y_min, x_max, y_max`` of the floor (metres); default the
            bounding box of the walls.

    Returns:
        The scene.

    Raises:
        DatasetError: a missing or malformed entry (named in the message).
    """
    if not isinstance(section, Mapping):
        raise DatasetError("scene3d: section must be a mapping")
    height = _num(section, "height", "scene3d", 3.0)
    thickness = _num(section, "wall_thickness", "scene3d", 0.1)
    wall_height = _num(section, "wall_height", "scene3d", height)
    doors_by_wall: dict[str, list[Mapping[str, Any]]] = {}
    for j, door in enumerate(section.get("doors", []) or []):
        if "wall" not in door:
            raise DatasetError(f"scene3d: doors[{j}]: missing 'wall'")
        doors_by_wall.setdefault(str(door["wall"]), []).append(door)
    boxes: list[Box] = []
    wall_ids = set()
    for j, wall in enumerate(section.get("walls", []) or []):
        wid = str(wall.get("id", f"wall{j}"))
        wall_ids.add(wid)
        boxes += _wall_boxes(
            wall, doors_by_wall.get(wid, []), thickness, wall_height, f"walls[{wid}]"
        )
    unknown = set(doors_by_wall) - wall_ids
    if unknown:
        raise DatasetError(f"scene3d: doors refer to unknown walls {sorted(unknown)}")
    for j, item in enumerate(section.get("furniture", []) or []):
        where = f"furniture[{item.get('id', j)}]"
        size = _vec(item.get("size"), 3, f"{where}.size")
        center_xy = _vec(item.get("center"), 2, f"{where}.center")
        base = _num(item, "base_z", where, 0.0)
        boxes.append(
            Box(
                str(item.get("id", f"furniture{j}")),
                KIND_FURNITURE,
                np.array([center_xy[0], center_xy[1], base + size[2] / 2]),
                size,
                math.radians(_num(item, "yaw_deg", where, 0.0)),
                _vec(item.get("color", [0.5, 0.4, 0.3]), 3, f"{where}.color"),
            )
        )
    pictures = []
    for j, item in enumerate(section.get("pictures", []) or []):
        where = f"pictures[{item.get('id', j)}]"
        pictures.append(
            Picture(
                str(item.get("id", f"picture{j}")),
                _vec(item.get("center"), 3, f"{where}.center"),
                _num(item, "width", where),
                _num(item, "height", where),
                math.radians(_num(item, "facing_deg", where)),
                int(_num(item, "seed", where, float(j + 1))),
            )
        )
    ids = [b.id for b in boxes] + [p.id for p in pictures]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise DatasetError(f"scene3d: duplicate ids {sorted(dup)}")
    changes: dict[str, Change] = {}
    for j, item in enumerate(section.get("changes", []) or []):
        name = str(item.get("name", f"change{j}"))
        remove = tuple(str(r) for r in item.get("remove", []) or [])
        move: dict[str, tuple[FloatArray, float | None]] = {}
        for oid, spec in (item.get("move", {}) or {}).items():
            c = np.asarray(spec.get("center"), dtype=float).reshape(-1)
            if c.shape not in ((2,), (3,)):
                raise DatasetError(
                    f"scene3d: changes[{name}].move[{oid}].center needs 2 or 3 numbers"
                )
            yaw = math.radians(float(spec["yaw_deg"])) if "yaw_deg" in spec else None
            move[str(oid)] = (c, yaw)
        missing = (set(remove) | set(move)) - set(ids)
        if missing:
            raise DatasetError(f"scene3d: changes[{name}] refers to unknown ids {sorted(missing)}")
        changes[name] = Change(name, remove, move)
    if bounds is None:
        if not boxes:
            raise DatasetError("scene3d: no walls or furniture and no bounds given")
        xy = np.concatenate([b.footprint() for b in boxes])
        bounds_arr = np.array([xy[:, 0].min(), xy[:, 1].min(), xy[:, 0].max(), xy[:, 1].max()])
    else:
        bounds_arr = _vec(list(bounds), 4, "bounds")
    return Scene3D(
        height=height,
        bounds=bounds_arr,
        boxes=tuple(boxes),
        pictures=tuple(pictures),
        changes=changes,
        floor_color=_vec(section.get("floor_color", [0.55, 0.55, 0.52]), 3, "floor_color"),
        ceiling_color=_vec(section.get("ceiling_color", [0.92, 0.92, 0.9]), 3, "ceiling_color"),
    )


def load_scene(world: str | Path) -> Scene3D:
    """The ``scene3d`` of a built-in world name or a world YAML file.

    Args:
        world: built-in name (``office``) or a path to a world YAML.

    Returns:
        The scene.

    Raises:
        DatasetError: the world is unknown or has no ``scene3d`` section.
    """
    path = Path(world)
    if not path.suffix:
        path = Path(__file__).resolve().parent / "worlds" / f"{world}.yaml"
    if not path.is_file():
        raise DatasetError("world file not found", path)
    import yaml

    try:
        with open(path, encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        raise DatasetError(f"invalid YAML: {exc}", path) from exc
    if not isinstance(doc, Mapping) or "scene3d" not in doc:
        raise DatasetError("world has no 'scene3d' section", path)
    try:
        return scene_from_dict(doc["scene3d"])
    except DatasetError as exc:
        raise DatasetError(str(exc), path) from exc


def apply_changes(scene: Scene3D, names: Iterable[str]) -> Scene3D:
    """The scene after the named changes (remove, then move), in the order given.

    Args:
        scene: the mapping-time scene.
        names: change names from ``scene.changes``.

    Returns:
        A new scene; ``scene`` is unchanged.

    Raises:
        DatasetError: an unknown change name.
    """
    boxes = list(scene.boxes)
    pictures = list(scene.pictures)
    for name in names:
        if name not in scene.changes:
            raise DatasetError(f"scene3d: unknown change {name!r} (known: {sorted(scene.changes)})")
        ch = scene.changes[name]
        boxes = [b for b in boxes if b.id not in ch.remove]
        pictures = [p for p in pictures if p.id not in ch.remove]
        for i, b in enumerate(boxes):
            if b.id in ch.move:
                c, yaw = ch.move[b.id]
                center = np.array([c[0], c[1], c[2] if c.size == 3 else b.center[2]])
                boxes[i] = dataclasses.replace(b, center=center, yaw=b.yaw if yaw is None else yaw)
        for i, p in enumerate(pictures):
            if p.id in ch.move:
                c, yaw = ch.move[p.id]
                center = np.array([c[0], c[1], c[2] if c.size == 3 else p.center[2]])
                pictures[i] = dataclasses.replace(
                    p, center=center, facing=p.facing if yaw is None else yaw
                )
    return dataclasses.replace(scene, boxes=tuple(boxes), pictures=tuple(pictures))


def obstacle_footprints(scene: Scene3D, z_min: float, z_max: float) -> list[FloatArray]:
    """Floor-plan outlines of the boxes that reach into a height band.

    Args:
        scene: the scene.
        z_min: bottom of the band, metres.
        z_max: top of the band, metres.

    Returns:
        One (4, 2) polygon (world metres) per wall piece, closed door or
        furniture box overlapping ``[z_min, z_max]``.
    """
    out = []
    for box in scene.boxes:
        b0, b1 = box.z_range()
        if b1 > z_min and b0 < z_max:
            out.append(box.footprint())
    return out
