"""The calibration loop closed in one process: sim, detector, estimator and selector.

One SingleThreadedExecutor, its own context and domain id. Ten AL iterations must each end in
exactly one outcome, and the estimate's average position error (against the simulated robot's
real table) must drop at least threefold from the initial guess.
"""
from rclpy.parameter import Parameter

from active_selector.selector_node import SelectorNode
from body_schema.metrics import PoseErrorEvaluator
from dh_estimator.estimator_node import EstimatorNode
from icub_sim_bridge.sim_node import SimNode
from marker_detector.detector_node import DetectorNode

ITERATIONS = 10


def _params(**kw):
    return [Parameter('use_sim_time', value=True)] + [Parameter(k, value=v) for k, v in kw.items()]


def test_ten_al_iterations_close_the_loop(ros):
    sim = ros.add(SimNode(context=ros.context, parameter_overrides=[
        Parameter(k, value=v) for k, v in dict(real_time_factor=0.0, cameras=['left'], perturb_seed=7).items()]))
    ros.add(DetectorNode(context=ros.context, parameter_overrides=_params()))
    est = ros.add(EstimatorNode(context=ros.context, parameter_overrides=_params(
        initial_seed=3, export_on_shutdown=False)))
    sel = ros.add(SelectorNode(context=ros.context, parameter_overrides=_params(
        strategy='al', iterations=ITERATIONS, max_evals=300)))
    x0 = est.estimator.dh.copy()
    ros.spin_until(lambda: sel.done, 240.0, f'{ITERATIONS} AL iterations')

    history = sel.planner.history
    assert [a.iteration for a in history] == list(range(1, ITERATIONS + 1))
    outcomes = [a.outcome for a in history]
    assert set(outcomes) <= {'accepted', 'rejected', 'failed'}, outcomes   # none timed out or stuck
    counters = est.estimator.counters
    assert counters['updates'] == outcomes.count('accepted')
    assert counters['updates'] >= ITERATIONS // 2
    ev = PoseErrorEvaluator(sim.robot.base, sim.true_dh, sim.robot.calibration_box)
    e0, e1 = ev(x0), ev(est.estimator.dh)
    assert e1.position_m * 3 <= e0.position_m, (e0, e1)
