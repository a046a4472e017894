"""The one strict-key helper (:mod:`lampsam.strict_keys`) and its three users: the
dataclass loader, the world files and the RGB-D camera file give the same message for
the same mistake, each naming the file and the dotted key."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from lampsam.config_loader import ConfigError, from_mapping
from lampsam.datasets.rgbd import camera_from_yaml
from lampsam.datasets.scene3d import load_scene
from lampsam.datasets.world import WORLDS_DIR, load_world
from lampsam.errors import DatasetError
from lampsam.strict_keys import MISSING, array, check_keys, finite_array, number


class _Bad(Exception):
    pass


def _fail(key: str, problem: str) -> _Bad:
    return _Bad(f"{key}: {problem}")


@pytest.mark.parametrize(("value", "problem"), [
    ("2.5", "must be a number, got a string ('2.5')"),
    (True, "must be a number, got a boolean (True)"),
    (float("nan"), "must be a number, got nan"),
    (math.inf, "must be finite, got inf"),
    (-1.0, "must be >= 0, got -1.0"),
    ([1], "must be a number, got an array ([1])"),
])
def test_number_problems_name_the_key(value: object, problem: str) -> None:
    with pytest.raises(_Bad) as info:
        number({"k": value}, "k", "sec[2]", fail=_fail, nonneg=True)
    assert str(info.value) == f"sec[2].k: {problem}"


def test_number_defaults_integers_and_ranges() -> None:
    assert number({}, "k", "s", fail=_fail, default=3) == 3.0
    assert number({"k": 4}, "k", "s", fail=_fail, integer=True, positive=True) == 4.0
    with pytest.raises(_Bad, match=r"^s\.k: missing \(required\)$"):
        number({}, "k", "s", fail=_fail)
    with pytest.raises(_Bad, match=r"^s\.k: must be an integer, got a float \(2\.5\)$"):
        number({"k": 2.5}, "k", "s", fail=_fail, integer=True)
    with pytest.raises(_Bad, match=r"^s\.k: must be > 0, got 0$"):
        number({"k": 0}, "k", "s", fail=_fail, positive=True)


def test_check_keys_unknown_missing_and_not_a_table() -> None:
    allowed = {"height", "width", "brightness"}
    assert check_keys({"height": 1}, "lamp", allowed, {"height"}, fail=_fail) == {"height": 1}
    with pytest.raises(_Bad, match=r"^lamp\.brightnes: unknown key \(did you mean 'brightness'\?\)$"):
        check_keys({"brightnes": 1}, "lamp", allowed, fail=_fail)
    with pytest.raises(_Bad, match=r"^lamp\.zzz: unknown table \(known keys: brightness, height, width\)$"):
        check_keys({"zzz": {}}, "lamp", allowed, fail=_fail)
    with pytest.raises(_Bad, match=rf"^lamp\.width: {MISSING.replace('(', '.').replace(')', '.')}$"):
        check_keys({"height": 1}, "lamp", allowed, {"height", "width"}, fail=_fail)
    with pytest.raises(_Bad, match=r"^lamp: must be a table, got an array$"):
        check_keys([1], "lamp", allowed, fail=_fail)


def test_arrays_shape_type_and_finiteness() -> None:
    np.testing.assert_array_equal(array({"R": np.eye(3).tolist()}, "R", (3, 3), "", fail=_fail),
                                  np.eye(3))
    np.testing.assert_array_equal(finite_array(np.arange(3), (3,), "t", fail=_fail), [0, 1, 2])
    for bad in ([1, 2], [1, 2, math.nan], ["1", "2", "3"], [1, [2], 3], [True, 0, 0], None):
        with pytest.raises(_Bad, match=r"^c\.t: must be 3 finite numbers, got "):
            finite_array(bad, (3,), "c.t", fail=_fail)
    with pytest.raises(_Bad, match=r"^R: missing \(required\)$"):
        array({}, "R", (3, 3), "", fail=_fail)


def test_array_of_any_shape() -> None:
    """``shape=None`` (config_loader's ``np.ndarray`` fields): any shape with an axis, the
    same number rules and one message; the result is a copy of the caller's array."""
    src = np.eye(2)
    out = finite_array(src, None, "m", fail=_fail)
    np.testing.assert_array_equal(out, np.eye(2))
    src[0, 0] = 5.0
    assert out[0, 0] == 1.0
    np.testing.assert_array_equal(finite_array([np.float32(1.5), 2], None, "m", fail=_fail),
                                  [1.5, 2.0])
    for bad in (5, [[1], [2, 3]], np.array(["a"]), np.array([True]), [1, math.inf],
                np.array(5.0), "1 2"):
        with pytest.raises(_Bad, match=r"^c\.m: must be an array of finite numbers, got "):
            finite_array(bad, None, "c.m", fail=_fail)


# --------------------------------------------------------------------------- the three users
@dataclass(frozen=True)
class _Lamp:
    height: float = 2.5
    brightness: float = 320.0


def _world_file(tmp_path: Path, edit: Any) -> Path:
    """The built-in lab world with one lamp edited by ``edit(lamp_mapping)``."""
    doc = yaml.safe_load((WORLDS_DIR / "lab.yaml").read_text())
    edit(doc["ceiling"]["lamps"][0])
    path = tmp_path / "w.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _kinect_file(tmp_path: Path, key: str, value: object) -> Path:
    doc = {"width": 64, "height": 48, "fx": 59.0, "fy": 61.0, "cx": 31.5, "cy": 23.5,
           "depth_scale": 5000.0, "body_R_camera": np.eye(3).tolist(),
           "body_t_camera": [0.0, 0.0, 0.4], "provenance": "kept, not checked"}
    doc[key] = value
    path = tmp_path / "kinect.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize(("value", "problem"), [
    ("high", r"must be a number, got a string \('high'\)"),
    (True, r"must be a number, got a boolean \(True\)"),
    (math.nan, r"must be a number, got nan"),
])
def test_same_mistake_same_message_in_the_three_readers(tmp_path: Path, value: object,
                                                        problem: str) -> None:
    """A bad ``height`` in a config table, a world's lamp and a camera file (``fx``):
    one problem text, each message naming its file and key."""
    with pytest.raises(ConfigError, match=rf"^lamp\.toml: lamp\.height: {problem}$"):
        from_mapping(_Lamp, {"height": value}, source="lamp.toml", key="lamp")
    world = _world_file(tmp_path, lambda lamp: lamp.__setitem__("height", value))
    with pytest.raises(DatasetError, match=rf"w\.yaml: ceiling\.lamps\[0\]\.height: {problem}$"):
        load_world(world)
    with pytest.raises(DatasetError, match=rf"kinect\.yaml: camera key fx: {problem}$"):
        camera_from_yaml(_kinect_file(tmp_path, "fx", value))


def test_unknown_key_gets_a_suggestion_in_world_and_config(tmp_path: Path) -> None:
    hint = r"unknown key \(did you mean 'brightness'\?\)"
    with pytest.raises(ConfigError, match=rf"lamp\.toml: lamp\.brightnes: {hint}$"):
        from_mapping(_Lamp, {"brightnes": 300.0}, source="lamp.toml", key="lamp")
    world = _world_file(tmp_path, lambda lamp: lamp.__setitem__("brightnes", 300.0))
    with pytest.raises(DatasetError, match=rf"w\.yaml: ceiling\.lamps\[0\]\.brightnes: {hint}$"):
        load_world(world)


def test_world_integers_and_missing_keys(tmp_path: Path) -> None:
    """A lamp id of 2.5 (was cut to 2) and a lamp without its height are refused."""
    world = _world_file(tmp_path, lambda lamp: lamp.__setitem__("id", 2.5))
    with pytest.raises(DatasetError, match=r"ceiling\.lamps\[0\]\.id: must be an integer, got a float"):
        load_world(world)
    world = _world_file(tmp_path, lambda lamp: lamp.pop("height"))
    with pytest.raises(DatasetError, match=r"ceiling\.lamps\[0\]\.height: missing \(required\)"):
        load_world(world)


def test_valid_files_read_as_before(tmp_path: Path) -> None:
    """The built-in lab world (its first lamp's values) and a camera file with an extra
    key read back unchanged."""
    lab = load_world("lab")
    doc = yaml.safe_load((WORLDS_DIR / "lab.yaml").read_text())["ceiling"]["lamps"][0]
    assert lab.lamps[0].id == doc["id"] and lab.lamps[0].height == doc["height"]
    cam = camera_from_yaml(_kinect_file(tmp_path, "cx", 31))
    assert (cam.width, cam.cx, cam.min_depth, cam.max_depth) == (64, 31.0, 0.3, 6.0)
    np.testing.assert_array_equal(cam.body_T_camera[:3, 3], [0.0, 0.0, 0.4])


def test_scene3d_values_name_the_world_file_and_key(tmp_path: Path) -> None:
    """The office world's 3-D scene with a bad end of its wall ``south`` and a bad
    height: the file and the key's path inside it (walls are named by their id)."""
    doc = yaml.safe_load((WORLDS_DIR / "office.yaml").read_text())
    doc["scene3d"]["walls"][0]["end"] = [10.0, "north"]
    path = tmp_path / "office.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(DatasetError, match=r"office\.yaml: scene3d\.walls\[south\]\.end: must be 2 finite "
                                           r"numbers, got \[10\.0, 'north'\]$"):
        load_scene(path)
    doc["scene3d"]["walls"][0]["end"] = [10.0, 0.0]
    doc["scene3d"]["height"] = math.inf
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(DatasetError, match=r"office\.yaml: scene3d\.height: must be finite, got inf$"):
        load_scene(path)
