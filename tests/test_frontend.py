"""Ceiling frontend: lamps (moments, axis, uncertainty, camera conversion), corners, NCC, bad input.

Synthetic images are rendered at 8x and area-averaged (``evaluation.frontend_eval``),
so edges are anti-aliased like a camera's; truth is exact.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from lampsam.angles import wrap_axis
from lampsam.datasets.logrun import CameraModel
from lampsam.errors import FrontendError, LampsamError
from lampsam.evaluation.frontend_eval import evaluate_frames
from lampsam.evaluation.frontend_synthetic import SyntheticScene, render_view, synthetic_sequence
from lampsam.frontend.blob_moments import measure_region
from lampsam.frontend.ceiling_coords import (
    ceiling_jacobians,
    ceiling_shapes,
    to_observation,
    to_observations,
)
from lampsam.frontend.corners import (
    CornerDetectorConfig,
    _near_mask,
    detect_corner_pixels,
    extract_patches,
    margin_kernel,
    match_ncc,
    spacing_nms,
    strongest_spaced,
    strongest_spaced_pixels,
)
from lampsam.frontend.dilation import dilate_disk, disk, disk_factors
from lampsam.frontend.label_stats import (
    group_by_label,
    label_levels,
    label_sums,
    levels_at,
    lower_median_rank,
)
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamps import (
    detect_lamps,
    measure_blobs,
)
from lampsam.frontend.measurements import CeilingFrame, LampObservation
from lampsam.frontend.pipeline import FrontendConfig, process_image
from lampsam.frontend.threshold import auto_threshold, otsu_level


def _scene(
    lamps: list[tuple[float, float, float, float, float]], rnd: list[bool]
) -> SyntheticScene:
    return SyntheticScene(
        lamps=np.array(lamps, dtype=float).reshape(-1, 5),
        round_lamp=np.array(rnd, dtype=bool),
        plates=np.zeros((0, 5)),
        plate_grey=np.zeros(0),
    )


def _axis_err(a: float, b: float) -> float:
    return abs(wrap_axis(a - b))


# --------------------------------------------------------------------------- lamps in pixels
def test_moments_subpixel_centroid_and_axis(rng: np.random.Generator) -> None:
    """Coverage-weighted moments: centroid < 0.1 px, axis < 0.3 deg on random lamps (N = 60)."""
    cen, ax = [], []
    for _ in range(15):
        lamps = []
        for k in range(4):
            x = 50.0 + 75.0 * k + rng.uniform(-5, 5)
            y = rng.uniform(50, 190)
            lamps.append((x, y, rng.uniform(16, 30), rng.uniform(4, 7), rng.uniform(-1.57, 1.57)))
        img, truth = render_view(_scene(lamps, [False] * 4), (0, 0, 0), noise_grey=2.0, rng=rng)
        moms, _, _, _ = measure_blobs(img, LampDetectorConfig())
        assert len(moms) == 4
        px = np.array([m.centroid for m in moms])
        for i in range(4):
            d = np.linalg.norm(px - truth.pixel[i], axis=1)
            j = int(np.argmin(d))
            cen.append(d[j])
            ax.append(_axis_err(moms[j].theta, float(truth.angle_px[i])))
    assert np.sqrt(np.mean(np.square(cen))) < 0.1
    assert np.degrees(np.sqrt(np.mean(np.square(ax)))) < 0.3


def test_axis_quadrant_kept_and_ratio(rng: np.random.Generator) -> None:
    """eq. 5 with atan2: angles in all four quadrants mod pi; R_ori = length / width."""
    for ang in (-1.2, -0.4, 0.0, 0.7, 1.4, math.pi / 2):
        img, _ = render_view(_scene([(160, 120, 40, 8, ang)], [False]), (0, 0, 0))
        (mom,), _, _, _ = measure_blobs(img, LampDetectorConfig())
        assert _axis_err(mom.theta, ang) < math.radians(0.3)
        # Uniform rectangle: sigma = side / sqrt(12), ratio = 40 / 8 (the rendered
        # rectangle is 1/8 px wider, and edge pixels' mass sits off their centres: 5 %).
        assert mom.ratio == pytest.approx(5.0, rel=0.05)
        assert mom.sigma1 == pytest.approx(40 / math.sqrt(12), rel=0.02)


def test_round_lamp_is_a_point_lamp() -> None:
    """A disc has R_ori ~ 1 <= 1.5: no axis, infinite axis variance."""
    img, _ = render_view(_scene([(100.3, 80.7, 14, 14, 0.0)], [True]), (0, 0, 0))
    det = detect_lamps(img, CameraModel())
    (lamp,) = det.lamps
    assert lamp.ratio < 1.05 and lamp.axis is None and math.isinf(lamp.var_axis)
    assert np.allclose(lamp.pixel, (100.3, 80.7), atol=0.05)


def test_uncertainty_matches_monte_carlo(rng: np.random.Generator) -> None:
    """Centroid and axis sigmas from the propagation formula agree with the spread over
    noise draws within a factor 2 (N = 60 images, sigma_n = 6 grey levels, no floors)."""
    cfg = LampDetectorConfig(sigma_centroid_floor_px=0.0, sigma_axis_floor=0.0)
    scene = _scene([(160.2, 120.4, 30, 6, 0.4)], [False])
    cs, th, pred_c, pred_t = [], [], [], []
    for _ in range(60):
        img, _ = render_view(scene, (0, 0, 0), noise_grey=6.0, rng=rng)
        (mom,), _, _, _ = measure_blobs(img, cfg)
        cs.append(mom.centroid)
        th.append(mom.theta)
        pred_c.append(np.sqrt(np.diag(mom.cov_centroid)))
        pred_t.append(math.sqrt(mom.var_theta))
    emp_c = np.std(np.array(cs), axis=0)
    emp_t = float(np.std(th))
    ratio_c = np.mean(pred_c, axis=0) / emp_c
    ratio_t = float(np.mean(pred_t)) / emp_t
    assert np.all((ratio_c > 0.5) & (ratio_c < 2.0)), ratio_c
    assert 0.5 < ratio_t < 2.0, ratio_t


def test_border_blob_flagged_and_dropped() -> None:
    img, _ = render_view(
        _scene([(5, 120, 40, 8, 0.1), (160, 120, 30, 6, 0.3)], [False] * 2), (0, 0, 0)
    )
    det = detect_lamps(img, CameraModel())
    assert sorted(lm.touches_border for lm in det.lamps) == [False, True]
    frame = process_image(img, 1.0, 3, CameraModel(), FrontendConfig(detect_corners=False))
    assert len(frame.lamps) == 1 and not frame.lamps[0].touches_border
    kept = process_image(img, 1.0, 3, CameraModel(), FrontendConfig(keep_border_lamps=True))
    assert len(kept.lamps) == 2


def test_size_limits_reject_specks_and_glare() -> None:
    img = np.full((240, 320), 60, np.uint8)
    img[100:102, 100:102] = 250  # 4 px speck
    img[0:240, 200:320] = 250  # half the image: glare / window
    img[50:56, 30:60] = 250  # a real lamp
    det = detect_lamps(img, CameraModel(), LampDetectorConfig(threshold=200))
    assert len(det.lamps) == 1 and det.n_rejected == 2
    assert np.allclose(det.lamps[0].pixel, (44.5, 52.5), atol=0.05)


def test_glare_merged_lamps_are_split() -> None:
    """Two parallel tubes joined by a dimmer saturated halo fill their moment ellipse poorly;
    re-thresholding separates them: two oriented lamps at their centres, axes kept."""
    scene = _scene([(150, 100, 36, 6, 0.0), (150, 130, 36, 6, 0.0)], [False] * 2)
    img, _ = render_view(scene, (0, 0, 0))
    img = img.copy()
    img[103:128, 140:161] = np.maximum(img[103:128, 140:161], 200)  # glare between the tubes
    det = detect_lamps(img, CameraModel(), LampDetectorConfig(threshold=150))
    assert len(det.lamps) == 2
    rows = sorted(lm.pixel[1] for lm in det.lamps)
    assert rows == pytest.approx([100.0, 130.0], abs=1.5)
    assert all(lm.axis is not None for lm in det.lamps)
    # Without the split (min_fill = 0) it is one blob with a meaningless centroid.
    merged = detect_lamps(img, CameraModel(), LampDetectorConfig(threshold=150, min_fill=0.0))
    assert len(merged.lamps) == 1


def test_fixed_and_automatic_threshold() -> None:
    """Otsu on a dark ceiling; on a bright ceiling the upper class is split again."""
    hist = np.zeros(256)
    hist[60] = 1000
    hist[240] = 50
    assert 60 <= otsu_level(hist) < 240
    bright = np.full((240, 320), 150, np.uint8)
    bright[:, :100] = 90  # shadowed half
    bright[100:110, 150:200] = 255  # lamp
    k = auto_threshold(bright, LampDetectorConfig())
    assert k is not None and 150 <= k < 255
    det = detect_lamps(bright, CameraModel())
    assert len(det.lamps) == 1 and det.lamps[0].area_px == pytest.approx(500, rel=0.02)
    assert auto_threshold(np.full((240, 320), 255, np.uint8), LampDetectorConfig()) is None


# --------------------------------------------------------------------------- camera conversion
def test_ceiling_coordinates_and_mirrored_axis() -> None:
    """Default mounting: image right = robot left, so a lamp along image columns has alpha = +-pi/2,
    one along image rows alpha = 0; m equals the camera model's map of the centroid."""
    cam = CameraModel()
    img, _ = render_view(
        _scene([(200, 60, 40, 6, 0.0), (100, 150, 40, 6, math.pi / 2)], [False] * 2), (0, 0, 0)
    )
    det = detect_lamps(img, cam)
    by_col = sorted(det.lamps, key=lambda lm: lm.pixel[0])
    along_rows, along_cols = by_col[0], by_col[1]
    assert along_cols.axis is not None and along_rows.axis is not None
    assert _axis_err(along_cols.axis, math.pi / 2) < math.radians(0.3)
    assert _axis_err(along_rows.axis, 0.0) < math.radians(0.3)
    for lm in det.lamps:
        assert np.allclose(lm.m, cam.normalized_from_pixels(lm.pixel[None])[0], atol=1e-12)
        # u forward = -y_n: a lamp above the image centre is ahead of the robot.
    assert by_col[1].m[0] > 0 and by_col[1].m[1] > 0  # (200, 60): ahead, left


def test_axis_and_covariance_through_distortion(rng: np.random.Generator) -> None:
    """With lens distortion the axis in (u, v) is the long axis of the blob's shape on the
    ceiling (its coverage moments taken in m, within 1 deg of the pixel axis mapped through the
    camera model and of J cov_shape J^T: the drawn blob is straight in pixels, so bent on the
    ceiling); cov_m = J cov_px J^T with J checked by finite differences."""
    cam = CameraModel(dist=np.array([-0.25, 0.06, 0.0, 0.0, 0.0]))
    spec = (230.0, 70.0, 30.0, 5.0, 0.6)
    img, _ = render_view(_scene([spec], [False]), (0, 0, 0), noise_grey=1.0, rng=rng)
    det = detect_lamps(img, cam)
    (lamp,), (mom,) = det.lamps, det.moments
    assert lamp.axis is not None
    # A short segment along the pixel axis, mapped through the camera model.
    e = np.array([math.cos(mom.theta), math.sin(mom.theta)])
    mm = cam.normalized_from_pixels(lamp.pixel + np.array([[-0.5], [0.5]]) * e)
    ref = math.atan2(mm[1, 1] - mm[0, 1], mm[1, 0] - mm[0, 0])
    assert _axis_err(lamp.axis, ref) < math.radians(1.0)
    # The pixel axis itself is the rendered one (the lamp is drawn in pixels).
    assert _axis_err(mom.theta, spec[4]) < math.radians(0.3)
    # cov_m = J cov_px J^T with J = dm/dpx from fine central differences.
    eps = 1e-4
    cols = []
    for d in (np.array([eps, 0.0]), np.array([0.0, eps])):
        hi = cam.normalized_from_pixels((lamp.pixel + d)[None])[0]
        lo = cam.normalized_from_pixels((lamp.pixel - d)[None])[0]
        cols.append((hi - lo) / (2 * eps))
    jac = np.column_stack(cols)
    assert np.allclose(lamp.cov_m, jac @ mom.cov_centroid @ jac.T, rtol=1e-3, atol=0)
    cm = jac @ mom.cov_shape @ jac.T
    assert _axis_err(lamp.axis, 0.5 * math.atan2(2 * cm[0, 1], cm[0, 0] - cm[1, 1])) < math.radians(1.0)
    assert mom.ceiling is not None
    cc = mom.ceiling.cov_shape + jac @ jac.T / 12.0
    assert _axis_err(lamp.axis, 0.5 * math.atan2(2 * cc[0, 1], cc[0, 0] - cc[1, 1])) < 1e-6
    assert np.allclose(lamp.m, mom.ceiling.centroid, atol=0)
    # var_axis = (det J / |J e|^2)^2 var_theta.
    gain = np.linalg.det(jac) / float((jac @ e) @ (jac @ e))
    assert lamp.var_axis == pytest.approx(gain**2 * mom.var_theta, rel=1e-3)


# --------------------------------------------------------------------------- corners and NCC
def test_corners_at_vertices_and_away_from_lamps(rng: np.random.Generator) -> None:
    frames = synthetic_sequence(rng, n_frames=1)
    img, truth = frames[0]
    det_l = detect_lamps(img, CameraModel())
    cd = detect_corner_pixels(img, det_l.mask, CornerDetectorConfig())
    assert cd.pixels.shape[0] >= 5
    corners = truth.pixel[[t == "corner" for t in truth.types]]
    d = np.min(np.linalg.norm(cd.pixels[:, None] - corners[None], axis=2), axis=1)
    assert np.sqrt(np.mean(d**2)) < 0.5  # sub-pixel refined vertices
    # Minimum spacing and no corner next to a lamp.
    dd = np.linalg.norm(cd.pixels[:, None] - cd.pixels[None], axis=2) + np.eye(len(cd.pixels)) * 99
    assert dd.min() >= CornerDetectorConfig().min_spacing_px - 1.0
    ij = np.round(cd.pixels).astype(int)
    assert not det_l.mask[ij[:, 1], ij[:, 0]].any()
    assert np.allclose(np.linalg.norm(cd.patches.reshape(len(ij), -1), axis=1), 1.0, atol=1e-5)


def test_match_ncc_gates_and_threshold(rng: np.random.Generator) -> None:
    img = rng.integers(0, 255, (60, 60)).astype(np.uint8)
    pix = np.array([[10, 10], [30, 12], [45, 40], [20, 45]], dtype=np.int64)
    patches = extract_patches(img, pix, 11)
    # Candidates: the same patches shuffled, plus a decoy next to each.
    order = np.array([2, 0, 3, 1])
    cand_pix = np.vstack([pix[order], pix + 3]).astype(float)
    cand = extract_patches(img, cand_pix.astype(np.int64), 11)
    idx, score = match_ncc(patches, pix.astype(float), cand, cand_pix, 6.0)
    assert np.array_equal(cand_pix[idx], pix.astype(float))
    assert np.allclose(score, 1.0, atol=1e-5)
    # Mahalanobis gates (S = I): the true candidates are 0 away, decoys sqrt(18) > 3.03.
    s = np.repeat(np.eye(2)[None], 4, axis=0)
    idx2, _ = match_ncc(patches, pix.astype(float), cand, cand_pix, s)
    assert np.array_equal(idx2, idx)
    # A gate that excludes the right candidates leaves only decoys: below the NCC threshold.
    idx3, score3 = match_ncc(patches, pix + 3.0, cand, cand_pix, 1.0, min_ncc=0.95)
    assert np.all(idx3 == -1) and np.all(np.isnan(score3))


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "image, fragment",
    [
        (np.zeros((0, 0), np.uint8), "empty"),
        (np.zeros((240, 320, 3), np.uint8), "shape"),
        (np.zeros((240, 320), np.float32), "dtype"),
        (np.zeros((100, 100), np.uint8), "camera model is 320x240"),
        ([[1, 2], [3, 4]], "numpy array"),
    ],
)
def test_bad_images_raise_frontend_error(image: object, fragment: str) -> None:
    with pytest.raises(FrontendError, match=fragment) as info:
        process_image(image, 0.5, 7, CameraModel())
    assert isinstance(info.value, LampsamError) and "frame 7" in str(info.value)


@pytest.mark.parametrize("level", [0, 255, 128])
def test_flat_images_give_empty_frames(level: int) -> None:
    frame = process_image(np.full((240, 320), level, np.uint8), 2.0, 1, CameraModel())
    assert frame == CeilingFrame(t=2.0, index=1)


def test_noise_only_image_gives_no_lamps(rng: np.random.Generator) -> None:
    img = np.clip(rng.normal(80, 3, (240, 320)), 0, 255).astype(np.uint8)
    frame = process_image(img, 0.0, 0, CameraModel())
    assert frame.lamps == ()


# --------------------------------------------------------------------------- whole sequence
def test_targets_on_rendered_sequence(rng: np.random.Generator) -> None:
    """The issue's targets on a 12-frame rendered run (moving, turning view)."""
    res = evaluate_frames(synthetic_sequence(rng, n_frames=12), CameraModel())
    assert res.n_truth_lamps_full >= 20
    assert res.lamp_recall >= 0.99
    assert res.n_false == 0
    assert res.centroid_rms_px <= 0.3
    assert res.n_axis >= 10 and res.axis_rms_deg <= 0.5
    assert res.m_rms <= 0.3 / CameraModel().fx and res.n_axis_m >= 10 and res.axis_m_rms_deg <= 0.5
    assert res.corner_repeatability >= 0.6
    assert res.ncc_precision >= 0.95


def test_lamp_observation_is_frozen() -> None:
    lamp = LampObservation(
        m=np.zeros(2), cov_m=np.eye(2), axis=None, var_axis=math.inf, ratio=1.0, area_px=10.0,
        pixel=np.zeros(2),
    )  # fmt: skip
    with pytest.raises(AttributeError):
        lamp.ratio = 2.0  # type: ignore[misc]
    assert not lamp.oriented


# --------------------------------------------------------------------------- fast paths
def test_margin_kernel_matches_distance_transform(rng: np.random.Generator) -> None:
    """Dilating with ``margin_kernel`` marks exactly the pixels with 3x3-L2 distance <= margin."""
    for margin in (0, 1, 2.5, 4, 7):
        kernel = margin_kernel(margin)
        for _ in range(20):
            mask = rng.random((50, 70)) < 0.005
            for _ in range(3):
                r, c = rng.integers(0, 50), rng.integers(0, 70)
                mask[r : r + rng.integers(1, 9), c : c + rng.integers(1, 9)] = True
            ref = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3) <= margin
            got = cv2.dilate(mask.view(np.uint8), kernel) > 0
            assert np.array_equal(got, ref), margin


def test_batched_lamp_observations_match_per_lamp(rng: np.random.Generator) -> None:
    """``to_observations`` equals ``to_observation`` lamp by lamp (to 1e-12 relative)."""
    cfg = LampDetectorConfig()
    image = np.full((240, 320), 40, np.uint8)
    for r, c, hh, ww in ((40, 50, 8, 40), (150, 200, 30, 9), (100, 120, 12, 12)):
        image[r : r + hh, c : c + ww] = 250
    image = cv2.GaussianBlur(image, (5, 5), 1.0)
    noisy = np.clip(image + rng.normal(0.0, 2.0, image.shape), 0, 255).astype(np.uint8)
    camera = CameraModel.from_fov(320, 240, 70.0)
    moments, _, _, _ = measure_blobs(noisy, cfg)
    assert len(moments) == 3
    px = np.array([mo.centroid for mo in moments])
    m, jac = ceiling_jacobians(camera, px, cfg.jacobian_step_px)
    shapes = ceiling_shapes(moments, m, jac)
    batch = to_observations(moments, shapes, jac, cfg)
    assert sum(ob.axis is not None for ob in batch) == 2
    for i, mo in enumerate(moments):
        one = to_observation(mo, shapes.m[i], shapes.cov[i], jac[i], cfg)
        np.testing.assert_allclose(batch[i].m, one.m, rtol=0, atol=1e-15)
        np.testing.assert_allclose(batch[i].cov_m, one.cov_m, rtol=1e-12, atol=1e-20)
        assert (batch[i].axis is None) == (one.axis is None)
        if one.axis is not None:
            assert batch[i].axis == pytest.approx(one.axis, abs=1e-12)
            assert batch[i].var_axis == pytest.approx(one.var_axis, rel=1e-12)
        else:
            assert math.isinf(batch[i].var_axis)


def _lamp_image(rng: np.random.Generator, shift: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Blurred, noisy tubes and discs (one touching the border), shifted by (cols, rows)."""
    image = np.full((240, 320), 45, np.uint8)
    for r, c, hh, ww in ((41, 51, 7, 40), (151, 201, 30, 9), (101, 121, 12, 12), (0, 280, 9, 30)):
        image[r : r + hh, c : c + ww] = 250
    image[200:205, 20:60] = 190  # dimmer than the lamps: rejected as too dim
    image = cv2.GaussianBlur(image, (5, 5), 1.0)
    image[10:12, 10:12] = 250  # a speck: rejected by size
    image = np.roll(image, shift, axis=(1, 0))
    return np.clip(image + rng.normal(0.0, 2.0, image.shape), 0, 255).astype(np.uint8)


def test_vectorised_moments_match_per_region_path(rng: np.random.Generator) -> None:
    """``measure_blobs`` (all blobs at once, inside a box of the thresholded pixels)
    equals the one-region reference ``measure_region`` blob by blob (1e-9), in the
    label order of the whole image, whatever the box offset (odd shifts included)."""
    cfg = LampDetectorConfig()
    for shift in ((0, 0), (1, 0), (0, 1), (3, 5), (-7, 2)):
        image = _lamp_image(rng, shift)
        moments, k, mask, n_rejected = measure_blobs(image, cfg)
        assert k is not None and len(moments) == 4 and n_rejected == 2
        _, binary = cv2.threshold(image, k, 1, cv2.THRESH_BINARY)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
        big = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= cfg.min_area_px]
        big = [i for i in big if image[labels == i].max() > 200]  # the lamps, label order
        assert len(big) == 4
        pad = cfg.support_px + cfg.ring_px + 1
        for mom, i in zip(moments, big, strict=True):
            x, y, w, h = stats[i, :4]
            c0, r0 = max(x - pad, 0), max(y - pad, 0)
            roi = labels[r0 : y + h + pad, c0 : x + w + pad]
            grey = image[r0 : y + h + pad, c0 : x + w + pad].astype(np.float64)
            border = x == 0 or y == 0 or x + w == 320 or y + h == 240
            ref = measure_region(grey, roi == i, (roi != 0) & (roi != i), (c0, r0), border, cfg)
            assert ref is not None
            np.testing.assert_allclose(mom.centroid, ref.centroid, rtol=0, atol=1e-9)
            np.testing.assert_allclose(mom.cov_centroid, ref.cov_centroid, rtol=1e-9, atol=1e-15)
            np.testing.assert_allclose(mom.cov_shape, ref.cov_shape, rtol=0, atol=1e-9)
            assert mom.theta == pytest.approx(ref.theta, abs=1e-9)
            assert mom.var_theta == pytest.approx(ref.var_theta, rel=1e-9)
            assert mom.area_px == pytest.approx(ref.area_px, rel=1e-12)
            assert mom.contrast == ref.contrast and mom.touches_border == ref.touches_border
            assert mask[labels == i].all()


def test_per_label_order_statistics_and_sums(rng: np.random.Generator) -> None:
    """Per-label medians / ranks (histogram path for few labels, sort path for many)
    and grouped per-label sums against direct per-label numpy on pixels that come
    in long runs of one label."""
    for n in (7, 1500):  # 1500 > _HIST_MAX_LABELS: the sort path
        lab = np.repeat(rng.integers(0, n, 40), rng.integers(1, 200, 40))
        grey = rng.integers(0, 256, lab.size)
        values = rng.normal(0.0, 100.0, (3, lab.size))
        levels = label_levels(lab, grey, n)
        assert (levels.cum is None) == (n > 1024)
        assert np.array_equal(levels.counts, np.bincount(lab, minlength=n))
        ranks = np.array([lower_median_rank(levels.counts), levels.counts - 1])
        median, top = levels_at(levels, ranks)
        groups = group_by_label(lab, n)
        sums = label_sums(groups, values.take(groups.order, axis=1), n)
        for j in np.unique(np.append(lab, [0, n - 1])).tolist():
            g = np.sort(grey[lab == j])
            if g.size:
                assert median[j] == g[(g.size + 1) // 2 - 1] and top[j] == g[-1]
            np.testing.assert_allclose(sums[:, j], values[:, lab == j].sum(axis=1), atol=1e-9)


def test_otsu_level_matches_exhaustive_search(rng: np.random.Generator) -> None:
    """Otsu scored on the occupied range equals the exhaustive between-class maximum."""
    for trial in range(200):
        hist = np.zeros(256)
        levels = rng.integers(0, 256, rng.integers(1, 6))
        hist[levels] = rng.integers(1, 500, levels.size)
        lo = int(rng.integers(0, 200)) if trial % 2 else 0
        best, arg = 0.0, float(lo)
        h = hist[lo:]
        for t in range(h.size):
            w0, w1 = h[: t + 1].sum(), h[t + 1 :].sum()
            if w0 > 0 and w1 > 0:
                m0 = (h[: t + 1] * np.arange(lo, lo + t + 1)).sum() / w0
                m1 = (h[t + 1 :] * np.arange(lo + t + 1, 256)).sum() / w1
                score = w0 * w1 * (m0 - m1) ** 2
                if score > best * (1 + 1e-12):
                    best, arg = score, float(lo + t)
        assert otsu_level(hist, lo) == arg


def test_spacing_keeps_local_maxima_strongest_first(rng: np.random.Generator) -> None:
    """Minimum spacing (all pairs for few points, k-d tree for many) equals the rule
    checked pair by pair: a point goes when a stronger one (ties: lower index) lies
    within the spacing; the kept ones come strongest first, ties in index order."""
    for n in (2, 60, 128, 129, 700):  # 128 / 129: either side of the all-pairs limit
        pts = rng.integers(0, 120, (n, 2)).astype(np.float64)  # pixel centres: exact distances
        score = rng.integers(20, 30, n).astype(np.float64)  # many ties
        d2 = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(axis=2)
        beats = (score[None, :] > score[:, None]) | (
            (score[None, :] == score[:, None]) & (np.arange(n)[None, :] < np.arange(n)[:, None])
        )
        expected = ~((d2 <= 64.0) & beats).any(axis=1)
        assert np.array_equal(spacing_nms(pts, score, 8.0), expected)
        kept = strongest_spaced(pts, score, 8.0)
        assert np.array_equal(np.sort(kept), np.flatnonzero(expected))
        assert np.array_equal(kept, sorted(kept.tolist(), key=lambda i: (-score[i], i)))
    assert np.array_equal(strongest_spaced(pts[:3], np.array([1.0, 3.0, 2.0]), 0.0), [1, 2, 0])


def test_spacing_on_the_pixel_grid_matches_pairs(rng: np.random.Generator) -> None:
    """The rank-image dilation keeps exactly the points the pair test keeps (dense,
    many ties, points at the image border), for integer and fractional spacings;
    two points on one pixel are refused (None)."""
    h, w = 60, 90
    for spacing in (8.0, 4.5, 1.0, 0.5):
        flat = rng.choice(h * w, 900, replace=False)
        ij = np.column_stack([flat % w, flat // w])
        score = rng.integers(20, 26, ij.shape[0]).astype(np.float64)
        expected = strongest_spaced(ij.astype(np.float64), score, spacing)
        got = strongest_spaced_pixels(ij, score, spacing, (h, w))
        assert got is not None and np.array_equal(got, expected)
    twice = np.array([[3, 4], [3, 4], [10, 10]])
    assert strongest_spaced_pixels(twice, np.array([1.0, 2.0, 3.0]), 8.0, (h, w)) is None


def test_lamp_margin_filter_matches_dilation(rng: np.random.Generator) -> None:
    """The keypoint-side margin test equals reading the dilated lamp mask, borders included."""
    for margin in (1, 4, 7.5):
        mask = np.zeros((60, 80), bool)
        for _ in range(4):
            r, c = rng.integers(-3, 60), rng.integers(-3, 80)
            mask[max(r, 0) : r + rng.integers(1, 12), max(c, 0) : c + rng.integers(1, 12)] = True
        near = cv2.dilate(mask.view(np.uint8), margin_kernel(margin)) > 0
        pixels = np.column_stack([rng.integers(0, 80, 300), rng.integers(0, 60, 300)])
        assert np.array_equal(_near_mask(mask, pixels, margin), near[pixels[:, 1], pixels[:, 0]])


def test_factorised_disk_dilation_matches_direct(rng: np.random.Generator) -> None:
    """Chained dilations by the disk's small factors equal one dilation by the disk,
    labels touching the image border included (max of labels, nothing outside)."""
    for radius in range(8):
        assert sum(int(f.sum()) for f in disk_factors(radius)) <= int(disk(radius).sum())
        for _ in range(10):
            shape = (int(rng.integers(5, 50)), int(rng.integers(5, 50)))
            labels = rng.integers(0, 200, shape) * (rng.random(shape) < 0.03)
            labels[0, rng.integers(0, shape[1])] = 7  # on the border
            for dtype in (np.uint8, np.uint16):
                img = labels.astype(dtype)
                assert np.array_equal(dilate_disk(img, radius), cv2.dilate(img, disk(radius)))
    assert len(disk_factors(5)) > 1  # the ring reach of the default detector is factorised
