"""Tilted and offset ceiling cameras (issue 20): the mounting, the renderer and the frontend under tilt."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lampsam.datasets.ceiling_truth import occluders, project_landmarks
from lampsam.datasets.mounting import mounted, rotation_rpy, tilt_deg
from lampsam.datasets.render_ceiling import CeilingRenderer
from lampsam.datasets.world import load_world, world_from_dict
from lampsam.datasets.world_landmarks import world_landmarks
from lampsam.errors import DatasetError
from lampsam.frontend.lamps import detect_lamps


def test_rotation_rpy_is_a_rotation_and_tilts_the_optical_axis() -> None:
    r = rotation_rpy(0.1, -0.2, 0.3)
    assert r @ r.T == pytest.approx(np.eye(3), abs=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    up = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert tilt_deg(mounted(up, [0.0, 12.0, 0.0])) == pytest.approx(12.0)
    assert tilt_deg(mounted(up, [5.0, 12.0, 0.0])) == pytest.approx(
        math.degrees(math.acos(math.cos(math.radians(5)) * math.cos(math.radians(12))))
    )
    # pitch > 0 turns the optical axis forward (body +x)
    assert (mounted(up, [0.0, 12.0, 0.0]) @ [0, 0, 1])[0] > 0


def test_lab_tilted_world_and_bad_mount() -> None:
    w = load_world("lab_tilted")
    assert tilt_deg(w.rig.camera.body_R_camera) == pytest.approx(13.0, abs=0.1)
    assert tuple(w.rig.camera.body_t_camera) == (0.1, 0.05, 0.3)
    doc = {"rig": {"camera": {"width": 320, "height": 240, "hfov_deg": 120, "mount_rpy_deg": [1, 2]}}}
    with pytest.raises(DatasetError, match="rig.camera.mount_rpy_deg"):
        world_from_dict(doc)


def test_lamps_seen_by_a_tilted_camera_are_found_where_the_truth_projects_them() -> None:
    """Renderer (ray casting) and truth (cv2.projectPoints) agree under tilt; the detector finds the lamps."""
    w = load_world("lab_tilted")
    cam = w.rig.camera
    rend = CeilingRenderer(w)
    table = world_landmarks(w)
    n_lamps, errs = 0, []
    for pose in ([3.5, 2.6, 0.0], [6.0, 4.8, 2.0], [2.0, 1.0, -0.7]):
        p = np.array(pose)
        det = detect_lamps(rend.render(p, np.random.default_rng(0)), cam)
        proj = project_landmarks(cam, p, table, occluders(w))
        full = [i for i, t in enumerate(proj.types) if t.startswith("lamp") and proj.fully_visible[i]]
        n_lamps += len(full)
        found = [mo.centroid for lo, mo in zip(det.lamps, det.moments, strict=True) if not lo.touches_border]
        for i in full:
            d = min((float(np.hypot(*(c - proj.pixel[i]))) for c in found), default=math.inf)
            errs.append(d)
    assert n_lamps >= 8
    assert max(errs) < 3.0  # every fully visible lamp found within 3 px of its projected centre


def test_tilted_lamp_centre_taken_on_the_ceiling() -> None:
    """Tilted camera: the observation of a rendered lamp agrees with the measurement model at truth."""
    from lampsam.factors.ceiling import project_point

    w = load_world("lab_tilted")
    cam = w.rig.camera
    rend = CeilingRenderer(w)
    table = world_landmarks(w)
    errs = []
    for pose in ([3.5, 2.6, 0.0], [6.0, 4.8, 2.0], [2.0, 1.0, -0.7]):
        p = np.array(pose)
        det = detect_lamps(rend.render(p, None), cam)
        for lo in det.lamps:
            if lo.touches_border:
                continue
            preds = [
                project_point(p, table.xyz[j], cam.body_t_camera)[0]
                for j, t in enumerate(table.types)
                if t.startswith("lamp")
            ]
            errs.append(min(float(np.hypot(*(lo.m - q))) for q in preds))
    matched = [e for e in errs if e < 0.05]  # (a blob near no lamp, e.g. a cut lamp, is left out)
    assert len(matched) >= 8
    # 1 px is about 0.011 in m here; with pixel moments mapped at the centroid the RMS was ~0.01
    assert math.sqrt(np.mean(np.square(matched))) < 0.004
