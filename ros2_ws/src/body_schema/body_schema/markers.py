"""ArUco marker facts the simulator and the detector share: the dictionary lookup, the black
square's corner geometry, and sub-pixel corners from the square's edges in an image (the
detector's corner refinement; the simulator's tests measure its renders with it). OpenCV is
imported only by the dictionary lookup and the corner refinement, so the rest of body_schema
never needs it."""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['aruco_dictionary', 'marker_corners', 'refine_corners_edges']


def aruco_dictionary(name: str) -> Any:
    """The cv2.aruco predefined dictionary called ``name`` (e.g. ``'DICT_4X4_50'``).

    Raises
    ------
    ValueError
        If ``name`` is not a cv2.aruco ``DICT_*`` name.
    """
    import cv2

    code = getattr(cv2.aruco, name, None)
    if not name.startswith('DICT_') or not isinstance(code, int):
        raise ValueError(f'unknown ArUco dictionary {name!r}; expected a cv2.aruco DICT_* name')
    return cv2.aruco.getPredefinedDictionary(code)


def marker_corners(side: float) -> NDArray[np.float64]:
    """The black square's corners in the marker frame (z out of the face), ArUco/OpenCV order
    (top-left, top-right, bottom-right, bottom-left), shape (4, 3) [m]."""
    h = side / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def refine_corners_edges(gray: NDArray[np.uint8], corners: ArrayLike, cells: int = 6,
                         max_shift_px: float = 3.0, iterations: int = 2) -> NDArray[np.float64] | None:
    """Re-locate a marker's corners as intersections of its four fitted edge lines.

    ArUco's corners come from the thresholded contour and sit up to ~0.6 px inside the black
    square; sub-pixel refinement on a 25-pixel marker cannot fix it because its window must stay
    inside one cell. Edges carry far more evidence than corners: along each side, the profile
    across the edge is sampled (bilinear) at many points, the crossing of the mid level between
    the dark border cell and the bright surround is found, a line is fitted by total least squares
    (one round of outlier rejection), and adjacent lines are intersected. A second pass re-centres
    the search on the fitted lines.

    Parameters
    ----------
    gray : ndarray, uint8, shape (H, W)
    corners : array_like, shape (4, 2)
        Initial corners, OpenCV order.
    cells : int
        Cells across the marker including the black border (6 for 4x4 dictionaries).
    max_shift_px : float
        Refuse the result if a corner moved further (then keep the initial corners). ArUco's
        corner at an acute, aliased tip can be 2 px short of the true one, so this is generous;
        a wrong edge fit moves corners much further.
    iterations : int
        Passes; each re-centres the edge search on the previous pass's lines.

    Returns
    -------
    ndarray, shape (4, 2), or None when an edge could not be measured.
    """
    c0 = np.asarray(corners, dtype=float).reshape(4, 2)
    if not np.all(np.isfinite(c0)):
        return None
    img = gray if gray.dtype == np.float32 else np.asarray(gray, dtype=np.float32)
    c = c0
    for _ in range(max(1, int(iterations))):
        # Later passes centre the search on the previous edges, which may have moved ~1 px.
        refined = _edge_pass(img, c, cells)
        if refined is None:
            return None
        c = refined
    if np.max(np.linalg.norm(c - c0, axis=1)) > max_shift_px:
        return None
    return c


_N_OFFSETS = 17          # samples across an edge (the profile is bilinear in between)
_NEXT = {k: (np.arange(4) + k) % 4 for k in (1, 2, 3)}      # corner i -> corner i + k


def _edge_pass(img: NDArray[np.float32], c: NDArray[np.float64], cells: int) -> NDArray[np.float64] | None:
    """One pass of :func:`refine_corners_edges`, vectorised over the four edges."""
    a = c
    b = c[_NEXT[1]]
    length = np.linalg.norm(b - a, axis=1)                      # (4,)
    if np.any(length < 4):
        return None
    u = (b - a) / length[:, None]
    n = np.stack([-u[:, 1], u[:, 0]], axis=1)
    centre = c.mean(axis=0)
    n *= np.where(np.sum(n * ((a + b) / 2 - centre), axis=1) < 0, -1.0, 1.0)[:, None]   # outward
    # The border cell's depth across an edge is set by the marker's extent perpendicular to it
    # (foreshortened on oblique views), not by the edge's own length.
    opp = np.stack([c[_NEXT[2]], c[_NEXT[3]]], axis=1)                            # (4, 2, 2)
    depth = np.abs(np.einsum('kij,kj->ki', opp - a[:, None], n).mean(axis=1))
    w = np.clip(0.7 * depth / cells, 1.0, 4.0)                  # stay within the border cell
    t0 = np.minimum(0.45, (w + 1.0) / length)                   # keep clear of the other edges
    n_s = int(np.clip(0.8 * length.max(), 5, 400))
    frac = np.linspace(0.0, 1.0, n_s)
    ts = t0[:, None] + frac[None] * (1 - 2 * t0)[:, None]       # (4, S)
    offs = np.linspace(-1.0, 1.0, _N_OFFSETS)[None] * w[:, None]                   # (4, O)
    pts = a[:, None] + (ts * length[:, None])[..., None] * u[:, None]              # (4, S, 2)
    grid = pts[:, :, None] + offs[:, None, :, None] * n[:, None, None]             # (4, S, O, 2)
    g = grid.reshape(4 * n_s, _N_OFFSETS, 2).astype(np.float32)
    import cv2                  # only the corner refinement needs OpenCV here

    prof = cv2.remap(img, g[..., 0], g[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(4, n_s, _N_OFFSETS)
    k = _N_OFFSETS // 5
    dark, bright = prof[..., :k].mean(-1), prof[..., -k:].mean(-1)
    mid = (dark + bright) / 2
    above = prof >= mid[..., None]
    # Dark-to-bright crossing nearest the current edge estimate, per sample line.
    cost = np.where(~above[..., :-1] & above[..., 1:], np.abs(offs[:, None, :-1]), np.inf)
    j = np.argmin(cost, axis=-1)                                                    # (4, S)
    valid = (bright - dark > 20.0) & np.isfinite(np.take_along_axis(cost, j[..., None], -1)[..., 0])
    v0 = np.take_along_axis(prof, j[..., None], -1)[..., 0]
    v1 = np.take_along_axis(prof, j[..., None] + 1, -1)[..., 0]
    o0 = np.take_along_axis(np.broadcast_to(offs[:, None], prof.shape), j[..., None], -1)[..., 0]
    step = offs[:, 1:2] - offs[:, 0:1]
    with np.errstate(divide='ignore', invalid='ignore'):
        o = o0 + (mid - v0) / (v1 - v0) * step
    e = pts + o[..., None] * n[:, None]                                            # (4, S, 2)
    valid &= np.isfinite(o)
    if np.any(valid.sum(1) < 4):
        return None
    mask = valid.astype(float)
    for _ in range(2):                                          # fit, drop outliers, refit
        m, d = _fit_lines(e, mask)
        res = np.abs(np.einsum('ksj,kj->ks', e - m[:, None], np.stack([-d[:, 1], d[:, 0]], 1)))
        srt = np.sort(np.where(mask > 0, res, np.inf), axis=1)   # masked samples sort last
        mad = srt[np.arange(4), (mask.sum(1).astype(int) - 1) // 2]   # (lower) median
        keep = (mask > 0) & (res <= np.maximum(3.0 * 1.4826 * mad, 0.05)[:, None])
        if np.any(keep.sum(1) < 4):
            break
        mask = keep.astype(float)
    m, d = _fit_lines(e, mask)
    # Corner i is where the line of edge i-1 meets the line of edge i (2x2 solve by Cramer).
    p1, d1 = m[_NEXT[3]], d[_NEXT[3]]
    diff = m - p1
    det = d1[:, 1] * d[:, 0] - d1[:, 0] * d[:, 1]
    if np.any(np.abs(det) < 1e-6):
        return None
    s1 = (diff[:, 1] * d[:, 0] - diff[:, 0] * d[:, 1]) / det
    out = p1 + s1[:, None] * d1
    return out if np.all(np.isfinite(out)) else None


def _fit_lines(e: NDArray[np.float64], mask: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Total-least-squares lines through masked point sets: centroids (K, 2), directions (K, 2)."""
    wsum = mask.sum(1)
    m = (e * mask[..., None]).sum(1) / wsum[:, None]
    dx, dy = (e - m[:, None]).transpose(2, 0, 1)
    cxx = (mask * dx * dx).sum(1)
    cyy = (mask * dy * dy).sum(1)
    cxy = (mask * dx * dy).sum(1)
    theta = 0.5 * np.arctan2(2 * cxy, cxx - cyy)               # principal axis of the scatter
    return m, np.stack([np.cos(theta), np.sin(theta)], axis=1)
