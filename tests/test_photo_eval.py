"""Hand labels of the shared ceiling photos and the photo evaluation (issue 20).

The labels are checked for what they claim (every photo labelled, lamps inside
their photo); the evaluation's matching rules on a synthetic image whose truth
is exact; the detector on the labelled photos against the issue's targets.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from lampsam.datasets.logrun import CameraModel
from lampsam.errors import LampsamError
from lampsam.evaluation.photo_eval import PhotoEvalSettings, evaluate_photos, score_photo
from lampsam.evaluation.photo_labels import (
    PhotoLabels,
    Region,
    merge_regions,
    parse_decisions,
    read_labels,
)
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamps import detect_lamps

from .conftest import require_shared

LABELS = Path(__file__).parent / "data" / "ceiling_photo_labels.json"


def test_label_file_covers_the_five_photos_with_tune_and_report_apart() -> None:
    labels = read_labels(LABELS)
    assert sorted(labels) == [f"{n}_db_photo.jpg" for n in (430, 470, 560, 807, 808)]
    uses = {pl.use for pl in labels.values()}
    assert uses == {"tune", "report"}
    for pl in labels.values():
        lamps = [r for r in pl.regions if r.kind == "lamp"]
        assert len(lamps) >= 4
        for r in lamps:  # centres inside the photo, lamps longer than wide
            assert 0 <= r.centre[0] <= pl.width and 0 <= r.centre[1] <= pl.height
            assert r.length >= r.width
    n_not_lamp = sum(
        r.kind in ("skylight", "reflection", "window") for p in labels.values() for r in p.regions
    )
    assert n_not_lamp >= 20


def test_bad_label_file_names_the_key(tmp_path: Path) -> None:
    raw = json.loads(LABELS.read_text())
    raw["photos"]["430_db_photo.jpg"]["regions"][0]["kind"] = "lampe"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(raw))
    with pytest.raises(LampsamError, match=r"430_db_photo.jpg.regions\[0\].kind"):
        read_labels(bad)
    bad.write_text('{"format": "lampsam-photo-labels/1", "photos": {"a.jpg": {"use": "tune"}}}')
    with pytest.raises(LampsamError, match="missing key 'regions'"):
        read_labels(bad)
    bad.write_text("{not json")
    with pytest.raises(LampsamError, match="bad.json:1: not JSON"):
        read_labels(bad)


def test_decisions_and_merge() -> None:
    dec = parse_decisions("# c\n430: lamp 1 2+3; skylight 4-6\n560: lamp(occluded) 0\n")
    assert dec["430"] == [("lamp", [[1], [2, 3]]), ("skylight", [[4], [5], [6]])]
    assert dec["560"] == [("lamp(occluded)", [[0]])]
    with pytest.raises(LampsamError, match="line 1: unknown kind"):
        parse_decisions("430: lampp 1")
    # Two collinear halves merge into the whole rectangle.
    a = Region("lamp", np.array([10.0, 0.0]), 0.0, 20.0, 4.0)
    b = Region("lamp", np.array([32.0, 0.0]), 0.0, 20.0, 4.0)
    m = merge_regions([a, b], "lamp")
    assert m.centre == pytest.approx([21.0, 0.0], abs=1e-9)
    assert m.length == pytest.approx(42.0) and m.width == pytest.approx(4.0)
    assert m.axis_deg == pytest.approx(0.0, abs=1e-9)


def _render(
    rects: list[tuple[float, float, float, float, float]], bright: list[bool]
) -> np.ndarray:
    """320x240 grey image, 8x supersampled: rotated rectangles (cx, cy, l, w, deg) at 255 or 170."""
    s = 8
    big = np.full((240 * s, 320 * s), 90, np.uint8)
    for (cx, cy, ln, wd, deg), hot in zip(rects, bright, strict=True):
        # big pixel j covers small pixel (j - 3.5) / 8: draw at 8 c + 3.5 for a centre at c
        box = cv2.boxPoints(((cx * s + 3.5, cy * s + 3.5), (ln * s, wd * s), deg)).astype(np.int32)
        cv2.fillConvexPoly(big, box, 255 if hot else 170)
    return cv2.resize(big, (320, 240), interpolation=cv2.INTER_AREA)


def test_scoring_rules_on_a_synthetic_photo() -> None:
    """Two lamps labelled, one unlabelled lamp (a false 'unlabelled'), one lamp in a 'window'."""
    rects = [
        (80.0, 60.0, 40.0, 6.0, 20.0),
        (200.0, 150.0, 30.0, 8.0, -35.0),
        (260.0, 60.0, 20.0, 5.0, 0.0),
        (150.0, 200.0, 16.0, 6.0, 90.0),
    ]
    img = _render(rects, [True] * 4)
    det = detect_lamps(img, CameraModel.from_fov(320, 240, 70.0))
    assert len(det.lamps) == 4
    # Labels at 2x resolution; the first lamp's labelled centre is 1 px (working size) off.
    regions = (
        Region("lamp", np.array([162.0, 120.0]), 20.0, 80.0, 12.0),
        Region("lamp", np.array([400.0, 300.0]), -35.0, 60.0, 16.0),
        Region("lamp", np.array([600.0, 100.0]), 0.0, 4.0, 1.0),  # too small at 320 px
        Region("window", np.array([300.0, 400.0]), 0.0, 60.0, 60.0),
    )
    labels = PhotoLabels("synthetic.png", 640, 480, "report", regions)
    sc = score_photo(det, labels, (320, 240), LampDetectorConfig(), PhotoEvalSettings())
    assert sc.n_detections == 4 and sc.n_true == 2
    assert sc.false_by_kind == {"unlabelled": 1, "window": 1}
    assert sc.n_lamps == 2 and sc.n_found == 2 and sc.n_small == 1
    assert sorted(sc.centroid_err_px) == pytest.approx([0.0, 1.0], abs=0.1)
    assert max(sc.axis_err_deg) < 1.0
    assert sc.precision == pytest.approx(0.5) and sc.recall == pytest.approx(1.0)


def test_shared_photos_against_their_labels() -> None:
    """The detector at 320 px on the labelled photos (targets of issue 20: precision >= 0.95)."""
    photos = require_shared("ceiling_photos")
    scores = {s.name: s for s in evaluate_photos(photos, LABELS, PhotoEvalSettings(width=320))}
    report = scores["total (report)"]
    assert report.precision >= 0.95
    assert report.recall >= 0.8  # measured 0.85 (17 of 20); see docs/photo-labels.md
    assert math.sqrt(np.mean(np.square(report.axis_err_deg))) < 2.0
    assert scores["total"].n_detections >= 30


def test_frontend_eval_cli_on_photos(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lampsam.cli import main

    photos = require_shared("ceiling_photos")
    out = tmp_path / "photos.json"
    assert (
        main(["frontend-eval", "--photos", str(photos), "--labels", str(LABELS), "--out", str(out)])
        == 0
    )
    assert "total (report)" in capsys.readouterr().out
    rows = json.loads(out.read_text())["photos"]
    assert len(rows) == 5 + 3 and rows[-1]["photo"] == "total"
    # default: the width from each photo's lamps and the full-resolution look; the issue's
    # targets per photo (measured 1.000 / 1.000 on all five, docs/photo-labels.md; the
    # two-module fittings of 560 and 807 split into modules count in "split", not as false)
    for r in rows[:5]:
        assert 320 < r["width"] <= 1024, r
        assert r["precision"] >= 0.95 and r["recall"] >= 0.9, r
        assert r["split"] <= 2, r
    assert main(["frontend-eval", "--photos", str(photos)]) == 2  # --labels missing: usage error
