"""Nearby views: the difference ratio and the revisit count measure what they say."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tools.nearby_views import detection_errors, difference_ratio, main, nearest_earlier, runs_table


def test_difference_ratio_separates_independent_from_repeated_errors() -> None:
    rng = np.random.default_rng(3)
    e0 = rng.normal(size=(20000, 3))
    assert difference_ratio(e0, rng.normal(size=e0.shape)) == pytest.approx(np.sqrt(2), rel=0.03)
    assert difference_ratio(e0, e0) == 0.0
    assert difference_ratio(e0, 0.5 * e0 + 0.5 * rng.normal(size=e0.shape)) < 1.0   # correlated: in between
    # Rows missing in either view are left out, not counted as errors.
    ed = e0.copy()
    ed[::2] = np.nan
    assert difference_ratio(e0, ed) == 0.0
    assert np.isnan(difference_ratio(e0[:3], np.full((3, 3), np.nan)))


def test_nearest_earlier_is_the_max_abs_distance_to_any_earlier_target() -> None:
    t = np.array([[0.0, 0.0], [10.0, 0.0], [0.1, -0.2], [10.0, 3.0]])
    np.testing.assert_allclose(nearest_earlier(t), [10.0, 0.2, 3.0])


def test_runs_table_counts_missing_runs_and_main_refuses_a_directory_without_any(tmp_path: Path,
                                                                               capsys: pytest.CaptureFixture) -> None:
    lines, read, missing = runs_table(tmp_path, ['AL', 'UCSAL'], 3)
    assert (read, missing) == (0, 6) and lines[-1] == '| UCSAL | 0 | | | | |'
    assert main(['--runs', str(tmp_path), '--methods', 'AL', '--repetitions', '2']) == 2
    assert 'no recording' in capsys.readouterr().err


def test_a_view_not_moved_repeats_its_error_exactly() -> None:
    from body_schema import load_robot
    from body_schema.sampling import uniform_configs
    from icub_sim_bridge.world import SimWorld

    model = load_robot('icub_right_arm')
    q = uniform_configs(model.calibration_box, 8, 5)
    with SimWorld(model) as world:
        first = detection_errors(model, world, q)
        again = detection_errors(model, world, q)
    left, stereo, published = first
    assert np.isfinite(published).all(axis=1).sum() >= np.isfinite(left).all(axis=1).sum() > 0
    # Where both eyes see, the published estimate is the both-image one.
    both = np.isfinite(stereo).all(axis=1)
    np.testing.assert_array_equal(stereo[both], published[both])
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
        if np.isfinite(a).any():
            assert difference_ratio(a, b) == 0.0
