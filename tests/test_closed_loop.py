"""The calibration loop closed in one process: the in-process graph of calibration_bringup.graph.

One SingleThreadedExecutor, its own context and domain id. Ten AL iterations must each end in
exactly one outcome, and the estimate's average position error (against the simulated robot's
real table) must drop at least threefold from the initial guess, and each eye's own verdicts
must reach the selector's per-eye occlusion models. The same loop on what real
cameras send: image_transport's compressed topic (JPEG) and a Bayer camera.
"""
import numpy as np
import pytest

from body_schema.metrics import PoseErrorEvaluator
from calibration_bringup.graph import InProcessGraph
from calibration_interfaces.outcome import FrameStatus

ITERATIONS = 10


def test_ten_al_iterations_close_the_loop(ros):
    with InProcessGraph(ros.context, ros.executor, {
            'sim': {'perturb_seed': 7}, 'estimator': {'initial_seed': 3},
            'selector': {'strategy': 'al', 'iterations': ITERATIONS, 'max_evals': 300,
                         'occlusion_per_eye': True}}) as graph:
        sim, est, sel = graph.sim, graph.estimator, graph.selector
        x0 = est.estimator.dh.copy()
        ros.spin_until(lambda: sel.done, 240.0, f'{ITERATIONS} AL iterations')

        history = sel.planner.history
        assert [a.iteration for a in history] == list(range(1, ITERATIONS + 1))
        outcomes = [a.outcome for a in history]
        assert set(outcomes) <= {'accepted', 'outlier', 'rejected', 'failed'}, outcomes   # none timed out or stuck
        # Both eyes (the default) and an occlusion model per eye: each eye's verdict on an attempt's
        # frame reached its own model (an eye whose image missed the pairing is not judged), and
        # the pair saw the hand exactly when one of the eyes did.
        tried, pair = sel.planner.occlusion.attempts
        assert len(pair) == len(history)
        seen_by = [[] for _ in pair]
        for eye in ('left', 'right'):
            q, seen = sel.planner.eye_occlusion[eye].attempts
            assert len(seen) >= len(pair) - 2, (eye, seen, pair)
            for qk, sk in zip(q, seen):
                seen_by[int(np.flatnonzero((tried == qk).all(axis=1))[0])].append(bool(sk))
        assert [any(s) for s in seen_by] == pair.tolist(), (seen_by, pair)
        counters = est.estimator.counters
        assert counters['updates'] == outcomes.count('accepted') + outcomes.count('outlier')   # both update
        assert counters['updates'] >= ITERATIONS // 2
        ev = PoseErrorEvaluator(sim.robot.base, sim.true_dh, sim.robot.calibration_box)
        e0, e1 = ev(x0), ev(est.estimator.dh)
        assert e1.position_m * 3 <= e0.position_m, (e0, e1)


@pytest.mark.parametrize('sim, detector', [
    ({'compressed_format': 'jpeg', 'jpeg_quality': 90}, {'transport': 'compressed'}),
    ({'image_encoding': 'bayer_rggb8'}, {}),
], ids=['compressed-jpeg', 'bayer_rggb8'])
def test_the_loop_on_compressed_images_and_a_bayer_camera(ros, sim, detector):
    iterations = 6
    with InProcessGraph(ros.context, ros.executor, {
            'sim': {'perturb_seed': 7, **sim}, 'detector': detector, 'estimator': {'initial_seed': 3},
            'selector': {'strategy': 'al', 'iterations': iterations, 'max_evals': 300}}) as graph:
        est, sel = graph.estimator, graph.selector
        x0 = est.estimator.dh.copy()
        ros.spin_until(lambda: sel.done, 240.0, f'{iterations} AL iterations')
        outcomes = [a.outcome for a in sel.planner.history]
        assert len(outcomes) == iterations, outcomes
        assert set(outcomes) <= {'accepted', 'outlier', 'rejected', 'failed'}, outcomes
        assert est.estimator.counters['updates'] == outcomes.count('accepted') + outcomes.count('outlier') \
            >= iterations // 2
        ev = PoseErrorEvaluator(graph.sim.robot.base, graph.sim.true_dh, graph.sim.robot.calibration_box)
        assert ev(est.estimator.dh).position_m * 2 <= ev(x0).position_m
        # Every frame decoded and judged (the first may come before its camera_info: bad input).
        counts = graph.nodes['detector'].frame_counts
        assert counts[FrameStatus.BAD_INPUT] <= 1 and counts[FrameStatus.DETECTED] > 0, counts
