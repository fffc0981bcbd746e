"""Stereo pairing of per-eye results (pure, injected times): complete pairs, timeouts, frames."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from marker_detector.detection import FrameResult, HandEstimate, MarkerPose
from marker_detector.stereo import EyeResult, StereoPairer, combine


def _pose(rotvec, t):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    m[:3, 3] = t
    return m


def _marker(cam_T_marker):
    return MarkerPose(1, np.zeros((4, 2)), cam_T_marker, None, 0.1, 1.0, 30.0, 0.3, 20.0)


def _hand(x, var):
    return HandEstimate(_pose([0, 0, 0], [x, 0, 0]), np.eye(6) * var, (1,), var, var)


def _item(eye, arrival, hand=None, markers=(), root_T_cam=None):
    return EyeResult(eye, f'{eye}-header', FrameResult(list(markers), [], hand), root_T_cam, arrival)


def test_a_pair_completes_when_both_eyes_of_the_stamp_are_in():
    pairer = StereoPairer(('left', 'right'), timeout=0.5)
    assert pairer.add((1, 0), _item('right', 10.0)) is None
    assert pairer.add((2, 0), _item('left', 10.1)) is None          # another stamp waits apart
    entry = pairer.add((1, 0), _item('left', 10.2))
    assert set(entry) == {'left', 'right'} and list(pairer.pending) == [(2, 0)]


def test_a_lone_eye_goes_out_after_the_timeout_only():
    pairer = StereoPairer(('left', 'right'), timeout=0.5)
    pairer.add((1, 0), _item('left', 10.0))
    assert pairer.stale(10.5) == []
    [entry] = pairer.stale(10.51)
    assert list(entry) == ['left'] and not pairer.pending


def test_one_eye_is_always_complete():
    assert set(StereoPairer(('left',), 0.5).add((1, 0), _item('left', 0.0))) == {'left'}


def test_combine_expresses_markers_in_the_left_frame_and_fuses_hands():
    rng = np.random.default_rng(2)
    left, right = _pose(rng.normal(size=3) * 0.2, [0.0, 0.03, 0.0]), _pose(rng.normal(size=3) * 0.2, [0.0, -0.03, 0.0])
    marker_in_root = _pose([0.3, 0.1, 0.0], [0.3, 0.0, 0.1])
    entry = {'right': _item('right', 0.0, _hand(0.2, 1e-4), [_marker(np.linalg.inv(right) @ marker_in_root)], right),
             'left': _item('left', 0.0, _hand(0.1, 1e-4), [_marker(np.linalg.inv(left) @ marker_in_root)], left)}
    header, markers, hand = combine(entry)
    assert header == 'left-header'
    for m in markers:                                       # both eyes' markers in the left camera frame
        np.testing.assert_allclose(left @ m, marker_in_root, atol=1e-12)
    assert np.isclose(hand.pose[0, 3], 0.15)                # equal weights: the mean
    assert np.isclose(hand.pos_var, 0.5e-4)


def test_combine_without_a_hand_is_a_failed_detection():
    header, markers, hand = combine({'left': _item('left', 0.0)})
    assert header == 'left-header' and markers == [] and hand is None
