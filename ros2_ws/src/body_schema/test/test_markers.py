"""Marker facts: the dictionary lookup, the corner geometry, and edge-line corner refinement on
synthetic images of a dark quadrilateral whose corners are known to a sixteenth of a pixel."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from body_schema.markers import aruco_dictionary, marker_corners, refine_corners_edges

SS = 16                         # supersampling of the synthetic images


def _dark_quad(corners: np.ndarray, size: tuple[int, int] = (320, 240), dark: int = 30,
               light: int = 220) -> np.ndarray:
    """A dark quadrilateral on a light ground, area-sampled: pixel (i, j) is centred on u=i, v=j."""
    w, h = size
    fine = np.full((h * SS, w * SS), light, np.uint8)
    # Fine pixel centres of coarse pixel i average to SS*i + (SS-1)/2; fillPoly takes 4 fraction bits.
    pts = np.round((corners * SS + (SS - 1) / 2) * 16).astype(np.int32)
    cv2.fillPoly(fine, [pts.reshape(-1, 1, 2)], dark, lineType=cv2.LINE_8, shift=4)
    return cv2.resize(fine, size, interpolation=cv2.INTER_AREA)


def _quads(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Foreshortened, rotated quads of 25-60 px in OpenCV corner order (clockwise on screen)."""
    out = []
    for _ in range(n):
        side = rng.uniform(25, 60)
        sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * side / 2
        sq[:, 0] *= rng.uniform(0.6, 1.0)                       # foreshortening
        sq[:2, 0] *= rng.uniform(0.85, 1.0)                     # a little perspective
        a = rng.uniform(0, 2 * np.pi)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        out.append(sq @ rot.T + rng.uniform([100, 80], [220, 160]))
    return out


def test_edge_lines_recover_known_corners_from_biased_starts() -> None:
    rng = np.random.default_rng(7)
    worst = []
    for truth in _quads(rng, 12):
        img = _dark_quad(truth)
        # Start like ArUco's contour corners: pulled ~0.7 px into the square, plus jitter.
        inward = truth.mean(0) - truth
        start = truth + 0.7 * inward / np.linalg.norm(inward, axis=1, keepdims=True) \
            + rng.normal(0, 0.2, (4, 2))
        got = refine_corners_edges(img, start)
        assert got is not None
        worst.append(np.max(np.linalg.norm(got - truth, axis=1)))
    # The starts are >= 0.5 px off; acute, foreshortened tips amplify line errors the most, and
    # fillPoly's edge rule alone puts the synthetic edges ~0.03 px outward.
    assert max(worst) < 0.15 and np.mean(worst) < 0.1, worst


def test_edge_refinement_refuses_nonsense() -> None:
    corners = np.array([[100.0, 100.0], [130.0, 100.0], [130.0, 130.0], [100.0, 130.0]])
    assert refine_corners_edges(np.full((240, 320), 128, np.uint8), corners) is None
    assert refine_corners_edges(_dark_quad(corners), corners + [[np.nan, 0.0], [0, 0], [0, 0], [0, 0]]) is None
    # A result further than max_shift_px from the start is refused, not returned.
    shifted = corners + [1.5, 0.0]
    assert refine_corners_edges(_dark_quad(corners), shifted) is not None
    assert refine_corners_edges(_dark_quad(corners), shifted, max_shift_px=1.0) is None


def test_marker_corners_and_dictionary() -> None:
    c = marker_corners(0.04)
    np.testing.assert_allclose(c[0], [-0.02, 0.02, 0.0])
    np.testing.assert_allclose(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1), 0.04)
    assert aruco_dictionary('DICT_4X4_50').bytesList.shape[0] == 50
    with pytest.raises(ValueError, match='DICT_5X5'):
        aruco_dictionary('DICT_5X5')
