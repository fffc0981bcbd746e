"""What the selector decides, without ROS: next target, occlusion learning, movement accounting.

:class:`Planner` holds one strategy (R, AL, UCSAL, CCSAL), the occlusion model it learns from
attempt outcomes, the noise model it uses to predict ``R(theta)``, and the history of visited
configurations. The node feeds it estimates and outcomes; everything here is testable in plain
Python.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import qmc

from body_schema import ArmModel
from body_schema.acquisition import (CRITERIA, OCCLUSION_MODES, AcquisitionCost, JointSelector, Selection,
                                     SelectorConfig, Strategy)
from body_schema.extrinsics import Extrinsics
from body_schema.noise import NoiseModel
from body_schema.occlusion import OcclusionModel, VisibilityPrior
from calibration_interfaces.outcome import Outcome
from calibration_interfaces.parameters import setting

__all__ = ['OCCLUSION_PRIORS', 'PlannerSettings', 'Attempt', 'Planner']

#: Prior of the occlusion model: the paper's flat Be(a0, b0), or geometric visibility from the estimate.
OCCLUSION_PRIORS = ('flat', 'geometric')


@dataclass(frozen=True)
class PlannerSettings:
    """Everything a strategy needs beyond the estimate (see body_schema.acquisition).

    Defaults chosen by measurement with the MAP estimator, 20 seeds x 50 iterations
    (``python -m tools.bench_acquisition study --sweep al|ucsal|ccsal``; docs/selector.md):
    v-optimality with the occlusion-discounted gain and the geometric visibility prior
    (``--sweep visibility``); the paper's C0 / eta with a-optimality and the flat prior
    (``occlusion_mode='paper', criterion='a_optimal', occlusion_prior='flat'``) is the baseline.
    Every field but ``selector`` is a node parameter (:mod:`active_selector.node_settings`).
    """

    selector: SelectorConfig = SelectorConfig()
    penalty_a: float = setting(0.05, 'Weight a of the a*arctan(b*p_x) penalty on hands behind the body',
                               (0.0, 1e6))
    penalty_b: float = setting(10.0, 'Slope b of the arctan penalty [1/m]', (0.0, 1e6))
    occlusion_length_scale: float = setting(0.5, 'Occlusion kernel length scale (normalised joints)', (1e-4, 10.0))
    occlusion_a0: float = setting(1.0, 'Beta prior successes', (1e-6, 1e6))
    occlusion_b0: float = setting(2.0, 'Beta prior failures', (1e-6, 1e6))
    occlusion_prior: str = setting('geometric', "Occlusion model prior: 'flat' (Be(a0, b0), the paper's) or "
                                   "'geometric' (mean from the estimate: marker facing the camera inside "
                                   "the image; strength a0 + b0)", choices=OCCLUSION_PRIORS)
    occlusion_mode: str = setting('gain', "Failure handling in the cost: 'paper' (C0 / eta), 'expected' "
                                  "(tr(P) - eta g) or 'gain' (-eta g / tr(P))", choices=OCCLUSION_MODES)
    criterion: str = setting('v_optimal', "Uncertainty the selection reduces: 'a_optimal' (tr P) or "
                             "'v_optimal' (hand-pose variance over the calibration box)", choices=CRITERIA)
    box_samples: int = setting(128, 'Configurations (Sobol, fixed) v-optimality averages over; a power of two',
                               (1, 65536))
    q_length: float = setting(0.0, "The estimator's process-noise variance per update for a, d [m^2]: the cost is "
                              'computed on the covariance the next update starts from, P + Q (the paper\'s '
                              'P_{k+1|k}); set it to the estimator\'s q_length', (0.0, 1.0))
    q_angle: float = setting(0.0, "The estimator's process-noise variance per update for alpha, offset [rad^2] "
                             '(as q_length)', (0.0, 1.0))

    def __post_init__(self) -> None:
        if self.occlusion_prior not in OCCLUSION_PRIORS:
            raise ValueError(f'occlusion_prior must be one of {OCCLUSION_PRIORS}, got {self.occlusion_prior!r}')
        n = self.box_samples
        if n < 1 or n & (n - 1):
            raise ValueError(f'box_samples must be a power of two >= 1 (Sobol balance), got {n}')
        if not (self.q_length >= 0 and self.q_angle >= 0):
            raise ValueError(f'process noise must be >= 0, got q_length {self.q_length}, q_angle {self.q_angle}')


@dataclass(frozen=True)
class Attempt:
    """One finished iteration."""

    iteration: int
    target: NDArray[np.float64]
    reached: NDArray[np.float64]
    outcome: Outcome             # accepted / rejected / failed / unreachable / timeout / bad_input
    detected: bool
    movement_deg: float          # accumulated L1 joint movement after this iteration
    selection_seconds: float


@dataclass
class Planner:
    """Selection state of one calibration run.

    Parameters
    ----------
    model : ArmModel
        Robot description (base, box, limits, markers). Its DH table is *not* used: the
        estimate is passed to :meth:`select`.
    noise : NoiseModel
        Predicts ``R(theta)`` inside the A-optimality cost.
    settings : PlannerSettings
    extrinsics : Extrinsics, optional
        Camera / marker corrections the estimator estimates with the table (the covariance passed
        to :meth:`select` then includes them; see :class:`body_schema.acquisition.AcquisitionCost`).
    """

    model: ArmModel
    noise: NoiseModel
    settings: PlannerSettings = PlannerSettings()
    history: list[Attempt] = field(default_factory=list)
    extrinsics: Extrinsics | None = None

    def __post_init__(self) -> None:
        box = self.model.calibration_box
        self.selector = JointSelector(box, self.settings.selector)
        self.occlusion = OcclusionModel(box, self.settings.occlusion_length_scale,
                                        self.settings.occlusion_a0, self.settings.occlusion_b0)
        self.visibility = None
        if self.settings.occlusion_prior == 'geometric':
            if self.model.camera is None:
                raise ValueError("occlusion_prior 'geometric' needs the robot description's camera intrinsics")
            self.visibility = VisibilityPrior(self.model.camera)
        self.start: NDArray[np.float64] | None = None
        self.movement_deg = 0.0
        # Fixed (seed 0) so the criterion is the same function in every run and iteration.
        self.box_configs = box[:, 0] + (box[:, 1] - box[:, 0]) * qmc.Sobol(
            box.shape[0], rng=0).random_base2(int(np.log2(self.settings.box_samples)))

    @property
    def strategy(self) -> Strategy:
        return self.settings.selector.strategy

    @property
    def previous(self) -> NDArray[np.float64] | None:
        """The last configuration the arm reached (or the start)."""
        return self.history[-1].reached if self.history else self.start

    @property
    def visited(self) -> NDArray[np.float64]:
        """Every configuration targeted or reached so far, shape (K, L); none is selected again."""
        q = [a.target for a in self.history] + [a.reached for a in self.history]
        return np.array(q).reshape(-1, self.model.calibration_box.shape[0])

    @property
    def discarded(self) -> int:
        return sum(not a.detected for a in self.history)

    def cost(self, dh: ArrayLike, P: ArrayLike, camera_pose: ArrayLike) -> AcquisitionCost:  # noqa: N803
        """The acquisition cost for the current estimate.

        With the geometric occlusion prior, its weight is the evidence that the current estimate's
        visibility predictions explain the attempts so far (a badly wrong estimate predicts the hand
        where it is not seen, and the flat prior takes over until the estimate improves).
        """
        s = self.settings
        P = np.array(P, dtype=float)  # noqa: N806
        if s.q_length or s.q_angle:
            # The next update starts from P + Q (the estimator's predict step); the table comes first.
            q = np.tile([s.q_length, s.q_length, s.q_angle, s.q_angle], self.model.n_joints)
            P[np.arange(q.size), np.arange(q.size)] += q
        cost = AcquisitionCost(self.model.base, np.asarray(dh, dtype=float).reshape(self.model.dh.shape),
                               P, self.noise, np.asarray(camera_pose, dtype=float),
                               self.model.markers, occlusion=self.occlusion, visibility=self.visibility,
                               penalty_a=s.penalty_a, penalty_b=s.penalty_b, occlusion_mode=s.occlusion_mode,
                               criterion=s.criterion, box_configs=self.box_configs, extrinsics=self.extrinsics)
        if self.visibility is not None:
            tried, _ = self.occlusion.attempts
            cost.visibility_weight = (self.occlusion.geometric_evidence(cost.visibility_probability(tried))
                                      if len(tried) else 0.5)
        return cost

    def select(self, dh: ArrayLike | None, P: ArrayLike | None,  # noqa: N803
               camera_pose: ArrayLike | None) -> Selection:
        """The next target configuration (clipped to the joint limits)."""
        if self.start is None:
            raise RuntimeError('Planner.start (the initial configuration) must be set before selecting')
        cost = None if self.strategy is Strategy.RANDOM else self.cost(dh, P, camera_pose)
        return self.selector.select(cost, self.previous, self.visited)

    def record(self, target: ArrayLike, reached: ArrayLike, outcome: Outcome | str, detected: bool | None,
               selection_seconds: float) -> Attempt:
        """Account one iteration: occlusion model, movement, history.

        ``detected`` None means no frame was judged at the reached configuration (no frame, or
        only bad input): the occlusion model learns nothing, as for an unreached target.

        Raises
        ------
        ValueError
            If ``outcome`` is not an :class:`~calibration_interfaces.outcome.Outcome` value.
        """
        outcome = Outcome(outcome)
        reached = np.asarray(reached, dtype=float)
        prev = self.previous
        self.movement_deg += float(np.degrees(np.sum(np.abs(reached - prev))))
        # An unreached pose, or one no frame was judged at, says nothing about visibility.
        if outcome.informs_visibility and detected is not None:
            self.occlusion.add(np.clip(reached, self.model.calibration_box[:, 0], self.model.calibration_box[:, 1]),
                               detected)
        attempt = Attempt(len(self.history) + 1, np.asarray(target, dtype=float), reached, outcome,
                          bool(detected), self.movement_deg, selection_seconds)
        self.history.append(attempt)
        return attempt
