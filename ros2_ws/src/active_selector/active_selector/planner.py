"""What the selector decides, without ROS: next target, occlusion learning, movement accounting.

:class:`Planner` holds one strategy (R, AL, UCSAL, CCSAL), the occlusion model it learns from
attempt outcomes (with two eyes also one per eye, from each eye's own verdict), the noise model
it uses to predict ``R(theta)``, and the history of visited configurations. With a collision model
it never selects a configuration inside the margins nor one whose straight joint-space path from
where the arm is leaves them (refusals are counted per selection). A list of poses (reviewed from
a plan, or taught by hand) is visited first, each checked the same way, before the strategy takes
over; :meth:`Planner.plan` plans such a list from an estimate without moving anything. The node
feeds it estimates and outcomes; everything here is testable in plain Python.
"""
from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import qmc

from body_schema import ArmModel
from body_schema.acquisition import (CRITERIA, OCCLUSION_MODES, AcquisitionCost, JointSelector, SafetyCheck,
                                     Selection, SelectorConfig, Strategy)
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
    penalty_a: float = setting(0.05, 'Weight a of the a*arctan(b*p_x) penalty on hands behind the body '
                               '(applied only where the robot description has a body: selection.body_penalty, '
                               'default on with eyes, off with fixed cameras)', (0.0, 1e6))
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
    visibility_margin: float = setting(-2.0, 'Geometric prior: how far inside the image a marker\'s centre must lie '
                                       '[fraction of the image width] (VisibilityPrior.margin); below -1: the '
                                       "description's selection.visibility_margin (default 0.06)", (-2.0, 1.0))
    visibility_marker_widths: float = setting(-1.0, 'Geometric prior: > 0 sizes the markers by the description '
                                              '(viewing-angle limit where a marker is 7.5 px wide) and adds this many '
                                              'projected marker widths to the margin (0.5: the whole marker inside '
                                              "the image); negative: the description's "
                                              'selection.visibility_marker_widths (default 0)', (-1.0, 10.0))
    eye_correlation: float = setting(0.6, 'Stereo (use_right_eye): how one eye\'s visibility follows the other\'s, '
                                     '0 independent .. 1 nested; P(both see) = c min(p_l, p_r) + (1 - c) p_l p_r '
                                     '(iCub: 0.38 over uniform configurations, tools.detector_bench; 0.59 over the attempts AL makes, '
                                     'tools.visibility_attempts)', (0.0, 1.0))
    occlusion_per_eye: bool = setting(False, 'Stereo (use_right_eye): learn where each eye sees the hand (one '
                                      "occlusion model per eye, from the detector's per-eye verdicts) and plan "
                                      'the chance that either does; false (the default: no better on held-out '
                                      'seeds, docs/selector.md): one model of whether the pair saw it')
    eye_occlusion_length_scale: float = setting(0.2, 'Kernel length scale of the per-eye occlusion models (normalised '
                                                'joints): shorter than the pair\'s, as each eye fails where the other '
                                                'sees', (1e-4, 10.0))

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
    refused: int = 0             # configurations the selection refused: inside a collision margin
    refused_paths: int = 0       # ... or behind one (the straight path to them leaves a margin)
    source: str = ''             # 'pose_list' for a pose from the list, else the strategy's search


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
    safety : SafetyCheck, optional
        A :class:`body_schema.collision.CollisionModel`: no target inside its margins, no path
        from where the arm is that leaves them.
    eyes : tuple of str
        Names of the cameras whose poses :meth:`select` receives, in order (``('left', 'right')``
        for a stereo pair). With two and ``settings.occlusion_per_eye``, :attr:`eye_occlusion`
        holds one occlusion model per eye, and :meth:`record` feeds each its eye's verdict.
    """

    model: ArmModel
    noise: NoiseModel
    settings: PlannerSettings = PlannerSettings()
    history: list[Attempt] = field(default_factory=list)
    extrinsics: Extrinsics | None = None
    safety: SafetyCheck | None = None
    eyes: tuple[str, ...] = ('left',)

    def __post_init__(self) -> None:
        box = self.model.calibration_box
        self.selector = JointSelector(box, self.settings.selector)
        self.occlusion = OcclusionModel(box, self.settings.occlusion_length_scale,
                                        self.settings.occlusion_a0, self.settings.occlusion_b0)
        if not 1 <= len(self.eyes) <= 2 or len(set(self.eyes)) != len(self.eyes):
            raise ValueError(f'eyes must name one camera or two different ones, got {self.eyes}')
        #: One occlusion model per eye (a stereo pair with ``occlusion_per_eye``), else empty.
        self.eye_occlusion: dict[str, OcclusionModel] = {}
        if len(self.eyes) == 2 and self.settings.occlusion_per_eye:
            self.eye_occlusion = {eye: OcclusionModel(box, self.settings.eye_occlusion_length_scale,
                                                      self.settings.occlusion_a0, self.settings.occlusion_b0)
                                  for eye in self.eyes}
        self.visibility = None
        if self.settings.occlusion_prior == 'geometric':
            if self.model.camera is None:
                raise ValueError("occlusion_prior 'geometric' needs the robot description's camera intrinsics")
            margin, widths = self.visibility_constants
            self.visibility = VisibilityPrior(self.model.camera, margin=margin,
                                              marker_side=self.model.marker_side_length if widths > 0 else None,
                                              margin_marker_widths=widths)
        self.start: NDArray[np.float64] | None = None
        self.movement_deg = 0.0
        #: Poses still to visit before the strategy takes over (a reviewed plan, a taught list).
        self.queue: list[NDArray[np.float64]] = []
        #: Poses of the list refused as unsafe: (index in the list, why).
        self.skipped: list[tuple[int, str]] = []
        self._queued = 0
        # Fixed (seed 0) so the criterion is the same function in every run and iteration.
        self.box_configs = box[:, 0] + (box[:, 1] - box[:, 0]) * qmc.Sobol(
            box.shape[0], rng=0).random_base2(int(np.log2(self.settings.box_samples)))

    @property
    def visibility_constants(self) -> tuple[float, float]:
        """The geometric prior's (margin, marker widths): the settings', or the description's where unset."""
        s, (margin, widths) = self.settings, self.model.visibility
        return (margin if s.visibility_margin < -1.0 else s.visibility_margin,
                widths if s.visibility_marker_widths < 0 else s.visibility_marker_widths)

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

    @property
    def penalty_a(self) -> float:
        """The penalty weight the cost uses: the setting's, or 0 where the description has no body to be
        behind (``ArmModel.body_penalty``: the sign of the root frame's x means nothing there)."""
        return self.settings.penalty_a if self.model.body_penalty else 0.0

    def cost(self, dh: ArrayLike, P: ArrayLike, camera_pose: ArrayLike) -> AcquisitionCost:  # noqa: N803
        """The acquisition cost for the current estimate (``camera_pose`` (4, 4), or (2, 4, 4) for a
        stereo pair).

        With the geometric occlusion prior, its weight is the evidence that the current estimate's
        visibility predictions explain the attempts so far (a badly wrong estimate predicts the hand
        where it is not seen, and the flat prior takes over until the estimate improves); with one
        occlusion model per eye, each eye's weight from that eye's attempts.
        """
        s = self.settings
        P = np.array(P, dtype=float)  # noqa: N806
        if s.q_length or s.q_angle:
            # The next update starts from P + Q (the estimator's predict step); the table comes first.
            q = np.tile([s.q_length, s.q_length, s.q_angle, s.q_angle], self.model.n_joints)
            P[np.arange(q.size), np.arange(q.size)] += q
        cameras = np.asarray(camera_pose, dtype=float)
        per_eye = bool(self.eye_occlusion) and cameras.reshape(-1, 4, 4).shape[0] == 2
        cost = AcquisitionCost(self.model.base, np.asarray(dh, dtype=float).reshape(self.model.dh.shape),
                               P, self.noise, cameras,
                               self.model.markers, occlusion=self.occlusion, visibility=self.visibility,
                               penalty_a=self.penalty_a, penalty_b=s.penalty_b, occlusion_mode=s.occlusion_mode,
                               criterion=s.criterion, box_configs=self.box_configs, extrinsics=self.extrinsics,
                               eye_correlation=s.eye_correlation,
                               eye_occlusion=tuple(self.eye_occlusion[e] for e in self.eyes) if per_eye else None)
        if self.visibility is not None:
            if per_eye:
                cost.eye_visibility_weights = tuple(self._evidence(cost, occ, k)
                                                    for k, occ in enumerate(cost.eye_occlusion))
            else:
                cost.visibility_weight = self._evidence(cost, self.occlusion)
        return cost

    @staticmethod
    def _evidence(cost: AcquisitionCost, occlusion: OcclusionModel, camera: int | None = None) -> float:
        """The weight of the geometric prior for ``occlusion`` (the evidence from its attempts; 0.5 without)."""
        tried, _ = occlusion.attempts
        return occlusion.geometric_evidence(cost.visibility_probability(tried, camera)) if len(tried) else 0.5

    def queue_poses(self, poses: ArrayLike) -> None:
        """Visit ``poses`` (K, L) [rad] first, in order, before the strategy selects.

        Raises
        ------
        ValueError
            If a pose has the wrong length, is not finite or lies outside the joint limits.
        """
        poses = np.atleast_2d(np.asarray(poses, dtype=float))
        if poses.shape[1] != self.model.n_joints or not np.all(np.isfinite(poses)):
            raise ValueError(f'poses must be finite, shape (K, {self.model.n_joints}), got {poses.shape}')
        outside = np.nonzero(~self.model.within_limits(poses))[0]
        if outside.size:
            raise ValueError(f'pose {int(outside[0])} lies outside the joint limits: '
                             f'{np.degrees(poses[outside[0]]).round(2).tolist()} deg')
        self.queue.extend(poses)

    def _from_queue(self) -> Selection | None:
        """The next safe pose of the list (unsafe ones are skipped and remembered), or None."""
        t0 = time.perf_counter()
        refused = refused_paths = 0
        while self.queue:
            theta = self.queue.pop(0)
            index = self._queued
            self._queued += 1
            if self.safety is not None:
                if not self.safety.clear(theta):
                    refused += 1
                    self.skipped.append((index, 'inside a collision margin'))
                    continue
                if not self.safety.path_clear(self.previous, theta).clear:
                    refused_paths += 1
                    self.skipped.append((index, 'the straight path to it leaves a collision margin'))
                    continue
            return Selection(theta, float('nan'), 0, time.perf_counter() - t0, self.model.calibration_box,
                             f'pose_list[{index}]', refused=refused, refused_paths=refused_paths)
        return None

    def select(self, dh: ArrayLike | None, P: ArrayLike | None,  # noqa: N803
               camera_pose: ArrayLike | None) -> Selection:
        """The next target configuration (clipped to the joint limits): the next safe pose of the
        list, else the strategy's choice.

        Raises
        ------
        body_schema.acquisition.UnsafeSelection
            If no configuration the search evaluated is safe to command.
        """
        if self.start is None:
            raise RuntimeError('Planner.start (the initial configuration) must be set before selecting')
        queued = self._from_queue()
        if queued is not None:
            return queued
        cost = None if self.strategy is Strategy.RANDOM else self.cost(dh, P, camera_pose)
        return self.selector.select(cost, self.previous, self.visited, safety=self.safety, start=self.previous)

    def plan(self, dh: ArrayLike, P: ArrayLike, camera_pose: ArrayLike, n: int) -> list[Selection]:  # noqa: N803
        """Plan ``n`` poses from an estimate without moving: what a run would visit if every
        attempt were seen and the estimate stayed put.

        Each pose is selected as :meth:`select` would (the strategy, the collision checks from the
        previous pose), then counted as visited and its expected information folded into ``P``
        (the update's covariance does not depend on what is measured); the occlusion model learns
        nothing. The planner's history is left as it was.

        Parameters
        ----------
        dh : array_like, shape (L, 4)
        P : array_like, shape (n_p, n_p)
            The estimate's covariance (with the extrinsics' rows when they are estimated).
        camera_pose : array_like, shape (4, 4)
        n : int

        Returns
        -------
        list of Selection, length n
        """
        if self.start is None:
            raise RuntimeError('Planner.start (the initial configuration) must be set before planning')
        history, movement = list(self.history), self.movement_deg
        P = np.array(P, dtype=float)  # noqa: N806
        out = []
        try:
            for _ in range(n):
                sel = self.select(dh, P, camera_pose)
                out.append(sel)
                if self.strategy is not Strategy.RANDOM:
                    P = self.cost(dh, P, camera_pose).posterior(sel.theta)  # noqa: N806
                self.history.append(Attempt(len(self.history) + 1, sel.theta, sel.theta, Outcome.ACCEPTED, True,
                                            0.0, sel.seconds))
        finally:
            self.history[:], self.movement_deg = history, movement
        return out

    def record(self, target: ArrayLike, reached: ArrayLike, outcome: Outcome | str, detected: bool | None,
               selection_seconds: float, refused: int = 0, refused_paths: int = 0, source: str = '',
               eyes: Mapping[str, bool] | None = None) -> Attempt:
        """Account one iteration: occlusion model(s), movement, history.

        ``detected`` None means no frame was judged at the reached configuration (no frame, or
        only bad input): the occlusion model learns nothing, as for an unreached target.
        ``eyes``: whether each eye saw the hand in that frame (an eye it does not name was not
        judged); each per-eye model learns its own. Without it a failed detection counts as failed
        for every eye (the pair's verdict is ``no_marker`` only when each eye judged says so), and a
        detection teaches the per-eye models nothing (which eye saw it is unknown).

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
            theta = self._in_box(reached)
            self.occlusion.add(theta, detected)
            self._add_eyes(theta, eyes if eyes is not None else
                           ({} if detected else dict.fromkeys(self.eye_occlusion, False)))
        attempt = Attempt(len(self.history) + 1, np.asarray(target, dtype=float), reached, outcome,
                          bool(detected), self.movement_deg, selection_seconds, refused, refused_paths, source)
        self.history.append(attempt)
        return attempt

    def learn_eyes(self, reached: ArrayLike, eyes: Mapping[str, bool]) -> None:
        """Teach each eye's occlusion model whether that eye saw the hand at ``reached`` (L,) (an
        eye not in ``eyes`` learns nothing): :meth:`record` does, or the caller once the verdicts
        arrive after an attempt recorded without them."""
        self._add_eyes(self._in_box(reached), eyes)

    def _in_box(self, q: ArrayLike) -> NDArray[np.float64]:
        """``q`` (L,) clipped to the calibration box, where the occlusion models live."""
        box = self.model.calibration_box
        return np.clip(np.asarray(q, dtype=float), box[:, 0], box[:, 1])

    def _add_eyes(self, theta: NDArray[np.float64], eyes: Mapping[str, bool]) -> None:
        for eye, model in self.eye_occlusion.items():
            if eye in eyes:
                model.add(theta, bool(eyes[eye]))
