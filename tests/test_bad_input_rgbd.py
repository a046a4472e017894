"""Bad input to the TUM RGB-D reader (``read_tum_rgbd``: ``kinect/`` of a run, ``build-map``).

``kinect.yaml`` used to be parsed with a bare ``yaml.safe_load``: a binary file raised
UnicodeDecodeError, an empty one "'NoneType' object is not subscriptable", a YAML error
came out on four lines, and a wrong value gave numpy's or int()'s message without the
key. Each now gives one DatasetError naming the file (and line or key).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from lampsam.datasets.rgbd import RgbdCamera, read_tum_rgbd
from lampsam.errors import DatasetError

KINECT_YAML = """\
format_version: 1
width: 64
height: 48
fx: 59.0
fy: 61.0
cx: 31.5
cy: 23.5
depth_scale: 5000.0
min_depth: 0.5
max_depth: 4.5
body_t_camera: [0.15, 0.0, 0.45]
body_R_camera:
- [0.0, 0.0, 1.0]
- [-1.0, 0.0, 0.0]
- [0.0, -1.0, 0.0]
sim_config: {rate_hz: 3.0}
"""


@pytest.fixture()
def kinect_dir(tmp_path: Path) -> Path:
    """A 3-frame TUM RGB-D folder with lampsam's kinect.yaml (images are never opened)."""
    root = tmp_path / "kinect"
    root.mkdir()
    (root / "kinect.yaml").write_text(KINECT_YAML)
    (root / "rgb.txt").write_text("# color images\n" + "".join(
        f"{0.5 * k:.6f} rgb/{k}.png\n" for k in range(3)))
    (root / "depth.txt").write_text("# depth maps\n" + "".join(
        f"{0.5 * k:.6f} depth/{k}.png\n" for k in range(3)))
    return root


def test_clean_folder_reads(kinect_dir: Path) -> None:
    seq = read_tum_rgbd(kinect_dir)
    assert isinstance(seq.camera, RgbdCamera)
    assert (seq.camera.width, seq.camera.fx, seq.camera.max_depth) == (64, 59.0, 4.5)
    np.testing.assert_allclose(seq.camera.body_T_camera[:3, 3], [0.15, 0.0, 0.45], atol=1e-12)
    assert len(seq) == 3


def _sub(pattern: str, repl: str) -> str:
    out = re.sub(pattern, repl, KINECT_YAML, count=1, flags=re.MULTILINE)
    assert out != KINECT_YAML
    return out


@pytest.mark.parametrize(("text", "match"), [
    ("", r"kinect.yaml: expected a mapping of camera keys .* got an empty file"),
    ("- 1\n- 2\n", r"kinect.yaml: expected a mapping of camera keys .* got list"),
    (_sub(r"^width: 64", "width: [64"), r"kinect.yaml:\d+: invalid YAML"),
    (_sub(r"^fx: 59.0\n", ""), r"kinect.yaml: camera key fx: missing \(required\)"),
    (_sub(r"^width: 64", "width: 64 7"), r"kinect.yaml: camera key width: must be an integer"),
    (_sub(r"^fy: 61.0", "fy: .nan"), r"kinect.yaml: camera key fy: must be a number, got nan"),
    (_sub(r"^cx: 31.5", "cx: centre"), r"kinect.yaml: camera key cx: must be a number, got a string"),
    (_sub(r"^body_t_camera: .*", "body_t_camera: [0.15, 0.0]"),
     r"kinect.yaml: camera key body_t_camera: must be 3 finite numbers"),
    (_sub(r"^- \[0.0, -1.0, 0.0\]\n", ""),
     r"kinect.yaml: camera key body_R_camera: must be 3x3 finite numbers"),
], ids=["empty", "list", "yaml_error", "missing_fx", "width_two_numbers", "nan_fy", "word_cx",
        "short_t", "two_rows_R"])
def test_bad_kinect_yaml_names_file_and_key(kinect_dir: Path, text: str, match: str) -> None:
    (kinect_dir / "kinect.yaml").write_text(text)
    with pytest.raises(DatasetError, match=match) as info:
        read_tum_rgbd(kinect_dir)
    assert "\n" not in str(info.value)
    assert info.value.path == kinect_dir / "kinect.yaml"


def test_binary_kinect_yaml(kinect_dir: Path) -> None:
    (kinect_dir / "kinect.yaml").write_bytes(np.random.default_rng(11).bytes(1500))
    with pytest.raises(DatasetError, match=r"kinect.yaml:\d+: not UTF-8 text"):
        read_tum_rgbd(kinect_dir)


def test_groundtruth_directory_is_named(kinect_dir: Path) -> None:
    """An optional file given as a directory is an error, not silently absent."""
    (kinect_dir / "groundtruth.txt").mkdir()
    with pytest.raises(DatasetError, match=r"groundtruth.txt: is a directory"):
        read_tum_rgbd(kinect_dir)


def test_missing_kinect_yaml_lists_the_keys(kinect_dir: Path) -> None:
    """A TUM RGB-D sequence from elsewhere has no kinect.yaml; the CLI cannot pass a camera,
    so the message says what to write (it said "pass the camera explicitly")."""
    (kinect_dir / "kinect.yaml").unlink()
    with pytest.raises(DatasetError, match=r"no kinect.yaml: .*width, height, fx, fy, cx, cy.*"
                       r"depth_scale.*body_t_camera.*body_R_camera"):
        read_tum_rgbd(kinect_dir)
