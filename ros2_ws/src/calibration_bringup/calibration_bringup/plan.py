"""Plan the poses of a calibration without moving anything, for review (``run_calibration.sh --plan-only``).

From the estimator's initial guess and covariance (its parameter file and the seed, exactly as the
estimator node builds them) and the selector's settings (its parameter file: strategy, criterion,
occlusion prior), the selector's :class:`~active_selector.planner.Planner` picks N poses in a row
as a run would if every attempt were seen (:meth:`~active_selector.planner.Planner.plan`), each
checked against the robot description's collision margins from the previous one (the first from
``--start-deg``, default the centre of the calibration box, where the simulator starts). Writes a
pose list (:mod:`calibration_interfaces.pose_list`) that ``run_calibration.sh --poses FILE``
(selector parameter ``poses_file``) visits first, with each pose's least clearance and closest
pair; ``--viz`` shows the poses and the obstacles in the browser (:mod:`calibration_viz.plan_view`).

Usage (from the repository root)::

    python -m calibration_bringup.plan --robot ur5e --n 20 --seed 1 --output plan.yaml \\
        --camera-prior "0.02 2" --marker-prior "0.005 5"
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from active_selector.node_settings import SelectorNodeSettings, StrategySettings
from active_selector.planner import Planner, PlannerSettings
from body_schema import load_robot
from body_schema.collision import CollisionModel
from body_schema.extrinsics import Extrinsics, parse_std
from body_schema.robot import ArmModel
from body_schema import sampling
from calibration_interfaces.dh_file import read_dh_file
from calibration_interfaces.noise import NoiseSettings, PoseDependentSettings
from calibration_interfaces.parameters import read_params_file, settings_from_parameters
from calibration_interfaces.pose_list import write_pose_list
from dh_estimator.estimator import EstimatorSettings, OnlineEstimator
from dh_estimator.node_settings import EstimatorNodeSettings

from .graph import config_dir

__all__ = ['Plan', 'make_plan', 'main']


class Plan:
    """A planned pose list and what was checked.

    Attributes
    ----------
    model : ArmModel
    start : ndarray, shape (L,)
    poses : ndarray, shape (N, L)
    selections : list of body_schema.acquisition.Selection
    collision : CollisionModel or None
    seconds : float
    """

    def __init__(self, model: ArmModel, start: np.ndarray, selections: list, collision: CollisionModel | None,
                 seconds: float) -> None:
        self.model, self.start, self.selections = model, start, selections
        self.poses = np.array([s.theta for s in selections]).reshape(-1, model.n_joints)
        self.collision, self.seconds = collision, seconds

    def clearances(self) -> list[dict[str, object]]:
        """Per pose: least distance to its margin's pair along the path to it and at it [m]."""
        if self.collision is None:
            return []
        out, prev = [], self.start
        for q in self.poses:
            at = self.collision.closest(q)
            path = self.collision.path_distance(prev, q)
            out.append({'clearance_m': round(at.distance, 4), 'closest': list(at.pair),
                        'path_clearance_m': round(path.distance, 4), 'path_closest': list(path.pair)})
            prev = q
        return out


def make_plan(robot: str, n: int, seed: int = 1, *, strategy: str | None = None, margin: float | None = None,
              start_deg: Sequence[float] | None = None, camera_prior: str = '', marker_prior: str = '',
              initial_guess: str | None = None, collision_check: bool = True) -> Plan:
    """Plan ``n`` poses for ``robot`` from the estimator's initial guess drawn with ``seed``.

    The estimator's and the selector's parameter files give everything not set here (as the
    launcher runs them); ``initial_guess`` ('perturbed', 'nominal') overrides the estimator's.

    Raises
    ------
    body_schema.acquisition.UnsafeSelection
        If a pose has no safe candidate.
    """
    model = load_robot(robot)
    config = config_dir()
    est_params = read_params_file(config / 'estimator.yaml', 'dh_estimator')
    sel_params = read_params_file(config / 'selector.yaml', 'active_selector')
    est_params.update(robot=robot, initial_seed=seed, camera_prior=camera_prior, marker_prior=marker_prior)
    if initial_guess:
        est_params['initial_guess'] = initial_guess
    node = settings_from_parameters(EstimatorNodeSettings, est_params)
    if node.initial_guess == 'nominal':
        x0 = model.dh.copy()
    elif node.initial_guess == 'perturbed':
        x0 = sampling.perturb_dh(model.dh, node.initial_seed, *node.widths)
    else:
        x0 = read_dh_file(node.initial_dh_file, model.n_joints).dh
    estimator = OnlineEstimator(model, x0, sampling.initial_covariance(model.n_joints, *node.widths),
                                settings_from_parameters(EstimatorSettings, est_params))
    sel_params.update(robot=robot, seed=seed, camera_prior=camera_prior, marker_prior=marker_prior)
    if strategy:
        sel_params['strategy'] = strategy
    strat = settings_from_parameters(StrategySettings, sel_params)
    planner_settings = settings_from_parameters(PlannerSettings, sel_params, selector=strat.config())
    node_settings = settings_from_parameters(SelectorNodeSettings, sel_params)
    noise = settings_from_parameters(NoiseSettings, sel_params).build(
        model, settings_from_parameters(PoseDependentSettings, sel_params))
    priors = [parse_std(v, k) for k, v in (('camera_prior', camera_prior), ('marker_prior', marker_prior))]
    extrinsics = (Extrinsics(model.camera_pose(node_settings.eye), model.markers[0].hand_T_marker, *priors)
                  if any(p is not None for p in priors) else None)
    collision = CollisionModel(model, margin) if collision_check else None
    # The camera pose, or the stereo pair's, the selector node would plan with.
    eyes = node_settings.planned_eyes(model)
    planner = Planner(model, noise, planner_settings, extrinsics=extrinsics, safety=collision, eyes=tuple(eyes))
    planner.start = (np.radians(np.asarray(start_deg, dtype=float)) if start_deg is not None
                     else model.calibration_box.mean(axis=1))
    t0 = time.perf_counter()
    cameras = np.stack([model.camera_pose(eye) for eye in eyes])
    selections = planner.plan(estimator.dh, estimator.P, cameras[0] if len(cameras) == 1 else cameras, n)
    return Plan(model, planner.start, selections, collision, time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m calibration_bringup.plan', description=__doc__.split('\n\n')[0])
    ap.add_argument('--robot', default='icub_right_arm', help='packaged robot name or YAML path')
    ap.add_argument('--n', type=int, default=50, help='poses to plan')
    ap.add_argument('--seed', type=int, default=1, help="the estimator's initial_seed and the selector's seed")
    ap.add_argument('--output', type=Path, default=Path('plan.yaml'), help='the pose list to write')
    ap.add_argument('--strategy', choices=('random', 'al', 'ucsal', 'ccsal'), help="the selector's (default: its file's)")
    ap.add_argument('--margin', type=float, help="collision margin [m] (default: the description's)")
    ap.add_argument('--no-collision-check', action='store_true',
                    help='do not check the poses against the obstacles (simulation only)')
    ap.add_argument('--start-deg', type=float, nargs='+', help='where the arm is [deg] (default: the box centre)')
    ap.add_argument('--camera-prior', default='', help="the estimator's camera_prior, e.g. '0.02 2'")
    ap.add_argument('--marker-prior', default='', help="the estimator's marker_prior, e.g. '0.005 5'")
    ap.add_argument('--initial-guess', choices=('perturbed', 'nominal'),
                    help="the estimator's initial guess (default: its file's; 'nominal' on a real robot)")
    ap.add_argument('--viz', action='store_true', help='then show the plan in the browser until Ctrl-C')
    ap.add_argument('--viz-port', type=int, default=8080)
    args = ap.parse_args(argv)
    if args.n < 1:
        ap.error('--n must be at least 1')
    if args.no_collision_check and args.margin is not None:
        ap.error('--margin and --no-collision-check exclude each other')
    plan = make_plan(args.robot, args.n, args.seed, strategy=args.strategy, margin=args.margin,
                     start_deg=args.start_deg, camera_prior=args.camera_prior, marker_prior=args.marker_prior,
                     initial_guess=args.initial_guess, collision_check=not args.no_collision_check)
    refused = sum(s.refused for s in plan.selections)
    refused_paths = sum(s.refused_paths for s in plan.selections)
    clearances = plan.clearances()
    extra = {'planned': {'seed': args.seed, 'strategy': plan.selections[0].optimizer if plan.selections else '',
                         'start_deg': [round(float(v), 6) for v in np.degrees(plan.start)],
                         'margin_m': None if plan.collision is None else plan.collision.margin,
                         'self_margin_m': None if plan.collision is None else plan.collision.self_margin,
                         'refused': refused, 'refused_paths': refused_paths},
             'clearance': clearances}
    write_pose_list(args.output, plan.model, plan.poses, extra,
                    comment=f'{len(plan.poses)} poses planned for {plan.model.name} by python -m calibration_bringup.plan '
                            f'(seed {args.seed}); review them before a run visits them (--poses)')
    least = min((c['path_clearance_m'] for c in clearances), default=float('nan'))
    checked = (f'{refused} candidates refused inside a collision margin, {refused_paths} behind one; least '
               f'clearance along the paths {least * 1e3:.0f} mm' if plan.collision is not None
               else 'NOT checked against the obstacles (--no-collision-check)')
    print(f'plan: {len(plan.poses)} poses for {plan.model.name} in {plan.seconds:.1f} s -> {args.output}; {checked}')
    if args.viz:
        from calibration_viz.plan_view import serve

        serve(plan.model, plan.poses, plan.start, port=args.viz_port)
    return 0


if __name__ == '__main__':
    sys.exit(main())
