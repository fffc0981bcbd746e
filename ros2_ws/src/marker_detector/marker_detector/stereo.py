"""Stereo pairing of per-eye detection results (pure; no rclpy).

With both eyes, the detector publishes one ``/markers`` and at most one ``/hand_pose`` per image
stamp: :class:`StereoPairer` holds one eye's result until the other eye's result of the same stamp
arrives, or until ``timeout`` seconds pass (the other eye's frame was lost), and
:func:`combine` expresses every accepted marker in the reference eye's camera frame and makes one
hand estimate of the eyes' (from all their marker corners at once, given the estimator). Times
are passed in, so the pairing is tested without a clock.
"""
from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration_interfaces.outcome import FrameStatus

from .detection import FrameResult, HandEstimate, HandPoseEstimator, fuse_estimates

__all__ = ['EyeResult', 'StereoPairer', 'combine', 'pair_status']


@dataclass(frozen=True)
class EyeResult:
    """One eye's result for one image.

    Attributes
    ----------
    eye : str
    header : Any
        The image header (stamp, frame id), passed through to the output.
    result : FrameResult
    root_T_cam : ndarray, shape (4, 4), or None
        The eye's camera pose in the root frame when the frame was processed.
    arrival : float
        When it arrived [s, any monotonic clock].
    """

    eye: str
    header: Any
    result: FrameResult
    root_T_cam: NDArray[np.float64] | None
    arrival: float


@dataclass
class StereoPairer:
    """Pairs results of the same stamp from ``eyes``.

    Parameters
    ----------
    eyes : sequence of str
        Every eye whose result completes a pair.
    timeout : float
        Seconds a result waits for the other eyes before it goes out alone.
    """

    eyes: Sequence[str]
    timeout: float
    pending: dict[Hashable, dict[str, EyeResult]] = field(default_factory=dict)

    def add(self, stamp: Hashable, item: EyeResult) -> dict[str, EyeResult] | None:
        """Add one eye's result; returns the complete set of its stamp, or None while waiting."""
        entry = self.pending.setdefault(stamp, {})
        entry[item.eye] = item
        if len(entry) < len(self.eyes):
            return None
        return self.pending.pop(stamp)

    def stale(self, now: float) -> list[dict[str, EyeResult]]:
        """Remove and return the incomplete sets whose first result waited longer than ``timeout``."""
        keys = [k for k, v in self.pending.items() if now - min(i.arrival for i in v.values()) > self.timeout]
        return [self.pending.pop(k) for k in keys]


def combine(entry: Mapping[str, EyeResult], ref: str = 'left', estimator: HandPoseEstimator | None = None
            ) -> tuple[Any, list[NDArray[np.float64]], HandEstimate | None]:
    """What one stamp's results publish.

    Parameters
    ----------
    entry : mapping of eye name to EyeResult
    ref : str
        The eye whose camera frame ``/markers`` uses (another eye if it is missing).
    estimator : HandPoseEstimator, optional
        When several eyes found the hand: one estimate from all their corners
        (:meth:`HandPoseEstimator.stereo`); without it, their poses fused as independent.

    Returns
    -------
    header : Any
        The reference eye's image header.
    markers : list of ndarray, shape (4, 4)
        Accepted marker poses in the reference camera frame.
    hand : HandEstimate or None
        The eyes' hand estimates fused (None when no eye found the hand).
    """
    ref = ref if ref in entry else next(iter(entry))
    ref_pose = entry[ref].root_T_cam
    markers, seen = [], []
    for item in entry.values():
        to_ref = np.eye(4)
        if item.eye != ref and item.root_T_cam is not None and ref_pose is not None:
            to_ref = np.linalg.inv(ref_pose) @ item.root_T_cam
        markers.extend(to_ref @ m.cam_T_marker for m in item.result.markers)
        if item.result.hand is not None:
            seen.append(item)
    if len(seen) < 2:
        return entry[ref].header, markers, seen[0].result.hand if seen else None
    if estimator is not None and all(i.root_T_cam is not None and i.result.k is not None for i in seen):
        return entry[ref].header, markers, estimator.stereo([(i.result, i.root_T_cam) for i in seen])
    return entry[ref].header, markers, fuse_estimates([i.result.hand for i in seen])


def pair_status(entry: Mapping[str, EyeResult]) -> FrameStatus:
    """The verdict of one stamp's results: detected if any eye found the hand, no marker only if
    every eye judged a valid frame without it, bad input otherwise (an eye that could not judge
    its frame cannot vouch that the hand was hidden)."""
    statuses = {item.result.status for item in entry.values()}
    if FrameStatus.DETECTED in statuses:
        return FrameStatus.DETECTED
    return FrameStatus.NO_MARKER if statuses == {FrameStatus.NO_MARKER} else FrameStatus.BAD_INPUT
