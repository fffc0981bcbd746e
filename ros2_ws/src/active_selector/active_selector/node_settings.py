"""Parameters of the selector node, described once on settings dataclasses (pure; no rclpy).

The node declares, in order, :class:`SelectorNodeSettings` (robot, eyes, files, reports),
:class:`StrategySettings` (the strategy and its DIRECT search: :class:`body_schema.acquisition.SelectorConfig`,
whose defaults it reuses), :class:`~active_selector.planner.PlannerSettings` (penalty, occlusion
model), :class:`~active_selector.loop.LoopSettings` (iterations, settling, timeouts) and the
noise model it predicts ``R(theta)`` with (:mod:`calibration_interfaces.noise`).
"""
from __future__ import annotations

from dataclasses import dataclass

from body_schema import ArmModel
from body_schema.acquisition import DIRECT_ALGORITHMS, LOCAL_ALGORITHMS, OPTIMIZERS, SelectorConfig, Strategy
from body_schema.extrinsics import parse_std
from calibration_interfaces.noise import NoiseSettings, PoseDependentSettings
from calibration_interfaces.parameters import setting

from .loop import LoopSettings
from .planner import PlannerSettings

__all__ = ['SelectorNodeSettings', 'StrategySettings', 'SETTINGS']

_SC = SelectorConfig()      # the strategy's defaults live in body_schema.acquisition


@dataclass(frozen=True)
class SelectorNodeSettings:
    """What the selector node reads besides the planner's and the loop's settings."""

    robot: str = setting('icub_right_arm', 'Packaged robot name or YAML path')
    eye: str = setting('left', 'Which eye the detector uses (its camera pose enters the cost)',
                       choices=('left', 'right'))
    use_right_eye: bool = setting(False, "Plan for both eyes, as the detector sees with them (set it to the "
                                  "detector's use_right_eye): an attempt counts as seen when either eye sees the "
                                  'hand, and the gain is that of the stereo or single-eye detection (a robot with '
                                  'eyes; ignored for a fixed camera)')
    progress_file: str = setting('', 'JSON-lines file, one object per iteration')
    wait_for_recorder: bool = setting(False, 'Select the first target only once /calibration/progress has a '
                                             'subscriber (the recorder, which subscribes to /arm/command in the '
                                             'same pass): a recorder that matches late loses the first commands')
    wait_for_estimator: bool = setting(False, 'Select the first target only once /body_schema/estimate has '
                                              'arrived, whatever the strategy (the estimator publishes it once it has '
                                              'a joint state and a matched /hand_pose publisher): an attempt before '
                                              "that is lost online but used by the bag's re-run")
    resume: bool = setting(False, 'Continue the run recorded in progress_file (its iterations count, its '
                                  'attempts teach the occlusion model) instead of starting it anew')
    wait_report_period: float = setting(2.0, 'Wall seconds between "waiting for" reports', (0.1, 3600.0))
    camera_prior: str = setting('', "The estimator's camera_prior: non-empty (not 0) when it estimates the "
                                'camera pose, whose covariance then comes with the estimate')
    marker_prior: str = setting('', "The estimator's marker_prior: non-empty (not 0) when it estimates the "
                                'marker offset')
    collision_check: bool = setting(True, 'Refuse targets inside the collision margins of the robot description '
                                          "(obstacles, the arm itself) and targets whose straight joint-space path "
                                          'from where the arm is leaves them (body_schema.collision)')
    collision_margin: float = setting(-1.0, 'Margin [m] to the obstacles; negative: the description\'s '
                                      'collision.margin', (-1.0, 1.0))
    poses_file: str = setting('', 'A pose list (calibration_interfaces.pose_list: a reviewed plan or taught poses) '
                                  'visited first, in order, each checked like a selection, before the strategy '
                                  'takes over')

    def planned_eyes(self, model: ArmModel) -> tuple[str, ...]:
        """The cameras the cost plans for: ``eye``, or both eyes with ``use_right_eye`` on a robot
        that has them (a fixed camera has no right eye: the parameter files' stereo default is the
        iCub's).

        Raises
        ------
        ValueError
            If both eyes are asked for together with estimated extrinsics (``camera_prior`` or
            ``marker_prior``), which are one camera's.
        """
        if not (self.use_right_eye and model.eyes is not None):
            return (self.eye,)
        if any(parse_std(v, k) is not None for k, v in (('camera_prior', self.camera_prior),
                                                          ('marker_prior', self.marker_prior))):
            raise ValueError('use_right_eye cannot be combined with camera_prior / marker_prior (extrinsics are '
                             'estimated for one camera)')
        return ('left', 'right')


@dataclass(frozen=True)
class StrategySettings:
    """The selection strategy and its search (DIRECT, or batched candidates + local refinement)."""

    strategy: str = setting(_SC.strategy.value, 'Selection strategy', choices=tuple(s.value for s in Strategy))
    seed: int = setting(_SC.seed, 'Seed of the random strategy and randomised DIRECT', (0, 2**31 - 1))
    gamma: float = setting(_SC.gamma, 'UCSAL weight of the normalised L1 movement', (0.0, 1e9))
    delta: float = setting(_SC.delta, 'CCSAL half-width of the box around the previous configuration '
                           '(normalised)', (1e-6, 1.0))
    optimizer: str = setting(_SC.optimizer, "Search: 'direct' (NLopt DIRECT, the paper's) or 'batch' (Sobol "
                             'candidates evaluated at once, then a local NLopt refinement)', choices=OPTIMIZERS)
    algorithm: str = setting(_SC.algorithm, 'NLopt DIRECT variant', choices=tuple(sorted(DIRECT_ALGORITHMS)))
    max_evals: int = setting(_SC.max_evals, 'DIRECT: cost evaluations per selection', (10, 10**7))
    n_candidates: int = setting(_SC.n_candidates, 'batch: quasi-random candidates per selection', (1, 10**6))
    refine_starts: int = setting(_SC.refine_starts, 'batch: best candidates refined locally', (0, 100))
    refine_evals: int = setting(_SC.refine_evals, 'batch: evaluations of each local refinement', (0, 10**5))
    local_algorithm: str = setting(_SC.local_algorithm, 'batch: NLopt local algorithm',
                                   choices=tuple(sorted(LOCAL_ALGORITHMS)))
    repeat_tolerance: float = setting(_SC.repeat_tolerance, 'Never select within this max-abs joint distance of '
                                      'an earlier configuration [rad] (0: allow repeats)', (0.0, 1.0))

    def config(self) -> SelectorConfig:
        """The selector configuration these parameters describe."""
        return SelectorConfig(strategy=self.strategy, gamma=self.gamma, delta=self.delta,
                              optimizer=self.optimizer, algorithm=self.algorithm, max_evals=self.max_evals,
                              n_candidates=self.n_candidates, refine_starts=self.refine_starts,
                              refine_evals=self.refine_evals, local_algorithm=self.local_algorithm,
                              repeat_tolerance=self.repeat_tolerance, seed=self.seed)


#: Every settings class the selector node declares, in order.
SETTINGS: tuple[type, ...] = (SelectorNodeSettings, StrategySettings, PlannerSettings, LoopSettings,
                              NoiseSettings, PoseDependentSettings)
