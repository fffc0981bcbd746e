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
from body_schema.acquisition import AcquisitionCost, JointSelector, Selection, SelectorConfig, Strategy
from body_schema.noise import NoiseModel
from body_schema.occlusion import OcclusionModel

__all__ = ['PlannerSettings', 'Attempt', 'Planner']


@dataclass(frozen=True)
class PlannerSettings:
    """Everything a strategy needs beyond the estimate (see body_schema.acquisition).

    Defaults chosen by measurement with :mod:`active_selector.study` (README, active_selector).
    """

    selector: SelectorConfig = SelectorConfig()
    penalty_a: float = 0.05
    penalty_b: float = 10.0
    occlusion_length_scale: float = 0.5
    occlusion_a0: float = 1.0
    occlusion_b0: float = 2.0
    occlusion_mode: str = 'paper'
    criterion: str = 'a_optimal'
    box_samples: int = 128          # configurations v-optimality averages over (Sobol, fixed)

    def __post_init__(self) -> None:
        n = self.box_samples
        if n < 1 or n & (n - 1):
            raise ValueError(f'box_samples must be a power of two >= 1 (Sobol balance), got {n}')


@dataclass(frozen=True)
class Attempt:
    """One finished iteration."""

    iteration: int
    target: NDArray[np.float64]
    reached: NDArray[np.float64]
    outcome: str                 # accepted / rejected / failed / unreachable / timeout
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
    """

    model: ArmModel
    noise: NoiseModel
    settings: PlannerSettings = PlannerSettings()
    history: list[Attempt] = field(default_factory=list)

    def __post_init__(self) -> None:
        box = self.model.calibration_box
        self.selector = JointSelector(box, self.settings.selector)
        self.occlusion = OcclusionModel(box, self.settings.occlusion_length_scale,
                                        self.settings.occlusion_a0, self.settings.occlusion_b0)
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
        """The acquisition cost for the current estimate."""
        s = self.settings
        return AcquisitionCost(self.model.base, np.asarray(dh, dtype=float).reshape(self.model.dh.shape),
                               np.asarray(P, dtype=float), self.noise, np.asarray(camera_pose, dtype=float),
                               self.model.markers, occlusion=self.occlusion, penalty_a=s.penalty_a,
                               penalty_b=s.penalty_b, occlusion_mode=s.occlusion_mode, criterion=s.criterion,
                               box_configs=self.box_configs)

    def select(self, dh: ArrayLike | None, P: ArrayLike | None,  # noqa: N803
               camera_pose: ArrayLike | None) -> Selection:
        """The next target configuration (clipped to the joint limits)."""
        if self.start is None:
            raise RuntimeError('Planner.start (the initial configuration) must be set before selecting')
        cost = None if self.strategy is Strategy.RANDOM else self.cost(dh, P, camera_pose)
        return self.selector.select(cost, self.previous, self.visited)

    def record(self, target: ArrayLike, reached: ArrayLike, outcome: str, detected: bool,
               selection_seconds: float) -> Attempt:
        """Account one iteration: occlusion model, movement, history."""
        reached = np.asarray(reached, dtype=float)
        prev = self.previous
        self.movement_deg += float(np.degrees(np.sum(np.abs(reached - prev))))
        if outcome != 'unreachable':
            self.occlusion.add(np.clip(reached, self.model.calibration_box[:, 0], self.model.calibration_box[:, 1]),
                               detected)
        attempt = Attempt(len(self.history) + 1, np.asarray(target, dtype=float), reached, outcome,
                          detected, self.movement_deg, selection_seconds)
        self.history.append(attempt)
        return attempt
