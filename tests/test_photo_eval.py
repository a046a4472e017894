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
from lampsam.evaluation.gallery import make_gallery
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
    bad.write_bytes(bytes(range(128, 256)))  # a binary file: was UnicodeDecodeError
    with pytest.raises(LampsamError, match="bad.json: not a text file"):
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
    assert report.recall >= 0.8  # measured 0.81 (17 of 21 modules; fittings 15 of 15); docs/photo-labels.md
    assert report.recall_fitting >= 0.95
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


def test_gallery_draws_what_frontend_eval_scores(tmp_path: Path) -> None:
    """``lampsam gallery``'s working-width column is the photo evaluation's path: same
    width (from the lamps, not fixed) and same lamps, including the second look's split.

    Hand-made 1600x1200 photo: two lamps 200 x 40 px and a row of two 360 x 40 px
    modules 2 px apart. At 320 px the row is one blob (3 lamps); the rule's width
    (lamps 10 px wide: 400 px) with the look at 2x finds the 4.
    """
    img = np.full((1200, 1600), 120.0)
    img[300:340, 300:500] = 250.0
    img[300:340, 1000:1200] = 250.0
    img[780:820, 400:760] = 250.0
    img[780:820, 762:1122] = 250.0
    img = cv2.GaussianBlur(img, (0, 0), 1.0) + np.random.default_rng(5).normal(0.0, 2.0, img.shape)
    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "hand.png"), np.clip(np.rint(img), 0, 255).astype(np.uint8))
    lamps = [((400, 320), 200), ((1100, 320), 200), ((580, 800), 360), ((942, 800), 360)]
    labels = {
        "format": "lampsam-photo-labels/1",
        "photos": {"hand.png": {"width": 1600, "height": 1200, "use": "report", "regions": [
            {"kind": "lamp", "centre": list(c), "axis_deg": 0.0, "length": ln, "width": 40}
            for c, ln in lamps
        ]}},
    }
    label_file = tmp_path / "labels.json"
    label_file.write_text(json.dumps(labels))
    settings = PhotoEvalSettings(auto_width=True, second_look=True)
    score = evaluate_photos(photos, label_file, settings)[0]
    assert (score.width, score.n_detections, score.n_true, score.n_found) == (400, 4, 4, 4)

    entries = make_gallery(photos, tmp_path / "g.png")
    small, working = entries
    assert (small.width, small.n_lamps) == (320, 3)  # the 320 px column merges the row
    assert (working.width, working.height) == (400, 300)
    assert working.n_lamps == score.n_detections == 4
    assert (tmp_path / "g.png").stat().st_size > 10_000


def test_a_fitting_of_two_modules_is_scored_in_both_readings() -> None:
    """A fitting of two modules end to end, 2 px apart (``fitting`` 1), and a single lamp.

    Seen merged (one detection on the connector): true, one module found (the
    nearer), the fitting found. Seen parted (the modules drawn apart): both.
    """
    modules = (
        Region("lamp", np.array([100.0, 60.0]), 0.0, 60.0, 8.0, fitting=1),
        Region("lamp", np.array([162.0, 60.0]), 0.0, 60.0, 8.0, fitting=1),
        Region("lamp", np.array([160.0, 180.0]), 0.0, 40.0, 8.0),
    )
    labels = PhotoLabels("fit.png", 320, 240, "report", modules)
    cam = CameraModel.from_fov(320, 240, 70.0)
    merged = _render([(131.0, 60.0, 122.0, 8.0, 0.0), (160.0, 180.0, 40.0, 8.0, 0.0)], [True, True])
    sc = score_photo(detect_lamps(merged, cam), labels, (320, 240), LampDetectorConfig(),
                     PhotoEvalSettings())
    assert (sc.n_detections, sc.n_true) == (2, 2)
    assert (sc.n_lamps, sc.n_found) == (3, 2)
    assert (sc.n_fittings, sc.n_fittings_found) == (2, 2)
    assert sc.recall == pytest.approx(2 / 3) and sc.recall_fitting == pytest.approx(1.0)
    parted = _render([(100.0, 60.0, 60.0, 8.0, 0.0), (166.0, 60.0, 60.0, 8.0, 0.0),
                      (160.0, 180.0, 40.0, 8.0, 0.0)], [True] * 3)
    sc = score_photo(detect_lamps(parted, cam), labels, (320, 240), LampDetectorConfig(),
                     PhotoEvalSettings())
    assert (sc.n_true, sc.n_found, sc.n_fittings_found) == (3, 3, 2)
    assert sc.n_split == 0


def test_label_fitting_key_is_checked(tmp_path: Path) -> None:
    raw = json.loads(LABELS.read_text())
    raw["photos"]["560_db_photo.jpg"]["regions"][4]["fitting"] = "one"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(raw))
    with pytest.raises(LampsamError, match=r"560_db_photo.jpg.regions\[4\].fitting"):
        read_labels(bad)
    fits = [r.fitting for r in read_labels(LABELS)["560_db_photo.jpg"].regions if r.kind == "lamp"]
    assert fits.count(1) == 2  # the two-module fitting of 560, labelled as modules


def test_a_jpeg_cut_short_is_decoded_with_a_warning(tmp_path: Path,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    """A truncated JPEG decodes with its lower rows grey (OpenCV only writes to stderr): the
    photo loader says so; an intact JPEG gives no warning."""
    from lampsam.evaluation.gallery import jpeg_cut_short, load_photo

    rng = np.random.default_rng(7)
    img = np.clip(rng.normal(128, 40, (180, 240)), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    whole, cut = tmp_path / "whole.jpg", tmp_path / "cut.jpg"
    whole.write_bytes(buf.tobytes())
    cut.write_bytes(buf.tobytes()[: len(buf) // 2])
    assert not jpeg_cut_short(whole) and jpeg_cut_short(cut)
    with caplog.at_level("WARNING"):
        assert load_photo(whole, None).shape == (180, 240)
        assert not caplog.records
        assert load_photo(cut, None).shape == (180, 240)
    assert any("cut short" in r.getMessage() and "cut.jpg" in r.getMessage()
               for r in caplog.records)


def test_gallery_skips_an_unreadable_photo_and_keeps_a_portrait_ones_aspect(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """One corrupt file among the photos is skipped with a warning naming it (was: the
    whole gallery refused); a portrait photo's reduced column keeps its aspect (320 x 427,
    was squashed to 320 x 240); a ``.tif`` is read like the others."""
    rng = np.random.default_rng(11)
    img = np.full((800, 600), 110.0)  # portrait, 600 wide
    img[200:240, 150:450] = 250.0
    img[560:600, 150:450] = 250.0
    img = np.clip(np.rint(img + rng.normal(0.0, 2.0, img.shape)), 0, 255).astype(np.uint8)
    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "a_portrait.tif"), img)
    (photos / "b_broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    with caplog.at_level("WARNING"):
        entries = make_gallery(photos, tmp_path / "g.png", full_size=False)
    assert [(e.name, e.width, e.height) for e in entries] == [("a_portrait.tif", 320, 427)]
    assert entries[0].n_lamps == 2
    assert any("b_broken.jpg" in r.getMessage() and "skipped" in r.getMessage()
               for r in caplog.records)
    (photos / "a_portrait.tif").unlink()
    with pytest.raises(LampsamError, match=r"none of its 1 photos could be read \(b_broken\.jpg\)"):
        make_gallery(photos, tmp_path / "g2.png", full_size=False)
