"""Planner: strategies run on an estimate, outcomes teach the occlusion model, movement adds up."""
import numpy as np
import pytest

import body_schema
from active_selector.planner import Planner, PlannerSettings
from body_schema import sampling
from body_schema.acquisition import SelectorConfig
from body_schema.noise import PoseDependentNoise

ARM = body_schema.load_robot()


@pytest.mark.parametrize('strategy', ['random', 'al', 'ucsal', 'ccsal'])
def test_select_and_record(strategy):
    pl = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy=strategy, max_evals=200)))
    with pytest.raises(RuntimeError, match='start'):
        pl.select(ARM.dh, sampling.initial_covariance(7), ARM.camera_pose())
    pl.start = np.mean(ARM.calibration_box, axis=1)
    sel = pl.select(ARM.dh, sampling.initial_covariance(7), ARM.camera_pose())
    assert ARM.within_limits(sel.theta)
    a = pl.record(sel.theta, sel.theta, 'failed', False, sel.seconds)
    assert a.movement_deg == pytest.approx(np.degrees(np.abs(sel.theta - pl.start).sum()))
    assert pl.discarded == 1 and pl.occlusion.n_configs == 1
    assert pl.occlusion.mean(sel.theta) < 0.5                 # the failure was learned
    b = pl.record(sel.theta, pl.start, 'accepted', True, 0.0)
    assert b.movement_deg == pytest.approx(2 * a.movement_deg)
    assert pl.previous is not None and np.array_equal(pl.previous, pl.start)
