"""The calibration loop closed in one process: the in-process graph of calibration_bringup.graph.

One SingleThreadedExecutor, its own context and domain id. Ten AL iterations must each end in
exactly one outcome, and the estimate's average position error (against the simulated robot's
real table) must drop at least threefold from the initial guess.
"""
from body_schema.metrics import PoseErrorEvaluator
from calibration_bringup.graph import InProcessGraph

ITERATIONS = 10


def test_ten_al_iterations_close_the_loop(ros):
    with InProcessGraph(ros.context, ros.executor, {
            'sim': {'perturb_seed': 7}, 'estimator': {'initial_seed': 3},
            'selector': {'strategy': 'al', 'iterations': ITERATIONS, 'max_evals': 300}}) as graph:
        sim, est, sel = graph.sim, graph.estimator, graph.selector
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
