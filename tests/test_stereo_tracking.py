"""Frontend stereo tracking on a synthetic rectified sequence with known motion.

A smoothed random texture is cropped so that every feature moves ``SHIFT_PX`` to the
right per frame in the left image and appears ``DISP_PX`` further left in the right
image (a fronto-parallel plane translating sideways): tracked columns must move by
exactly that, stereo matches must have that disparity and keep their row.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from lampsam.frontend.stereo_tracking import TrackConfig, paper_coords, track_sequence

SHIFT_PX = 2
DISP_PX = 9
H, W, N = 160, 320, 6


@dataclass
class _Sequence:
    """Just what ``track_sequence`` reads from a ``KittiStereoSequence``."""

    base: np.ndarray
    cx: float = 160.0

    width: int = W
    height: int = H

    def __len__(self) -> int:
        return N

    def load_pair(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        off = 40 - SHIFT_PX * k
        left = self.base[20:20 + H, off:off + W]
        right = self.base[20:20 + H, off + DISP_PX:off + DISP_PX + W]
        return np.ascontiguousarray(left), np.ascontiguousarray(right)


@pytest.fixture(scope="module")
def seq() -> _Sequence:
    rng = np.random.default_rng(31)
    noise = rng.uniform(0, 255, (H + 40, W + 80)).astype(np.float32)
    tex = cv2.GaussianBlur(noise, (0, 0), 2.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    return _Sequence(tex.astype(np.uint8))


def test_tracks_follow_the_known_motion(seq: _Sequence) -> None:
    """Columns move +2 px/frame within 0.05 px, rows stay within 0.05 px, stereo
    disparity 9 px within 0.05 px, on at least 50 tracks seen in all 6 frames.

    The disparity check leaves out right matches within ``border_px`` of the image
    edge: new corners are not border-filtered and a right match is not required to
    lie inside the image, so a corner at u ~ 9 px gets u_right ~ -0.3 px (about
    0.4 px off; 17 of 1571 matches here). That is current behaviour, not asserted."""
    cfg = TrackConfig(max_corners=200, min_distance_px=8.0)
    tracks = track_sequence(seq, cfg)  # type: ignore[arg-type]
    full = tracks.seen.all(axis=0)
    assert full.sum() >= 50
    du = np.diff(tracks.u_left[:, full], axis=0)
    np.testing.assert_allclose(du, SHIFT_PX, atol=0.05)
    np.testing.assert_allclose(np.diff(tracks.v[:, full], axis=0), 0.0, atol=0.05)
    st = tracks.stereo & tracks.seen
    assert st.sum() >= 0.9 * tracks.seen.sum()
    interior = st & (tracks.u_right >= cfg.border_px)
    assert interior.sum() >= 0.95 * st.sum()
    np.testing.assert_allclose((tracks.u_left - tracks.u_right)[interior], DISP_PX, atol=0.05)
    np.testing.assert_allclose((tracks.u_left - tracks.u_right)[st], DISP_PX, atol=0.5)
    # absent entries are zero and never flagged stereo
    assert not (tracks.stereo & ~tracks.seen).any()
    assert np.all(tracks.u_left[~tracks.seen] == 0.0)


def test_paper_coords_positive_left(seq: _Sequence) -> None:
    """x = cx - u: the principal point maps to 0, columns left of it are positive."""
    np.testing.assert_allclose(paper_coords(np.array([160.0, 100.0, 250.5]), seq),  # type: ignore[arg-type]
                               [0.0, 60.0, -90.5], atol=1e-12)
