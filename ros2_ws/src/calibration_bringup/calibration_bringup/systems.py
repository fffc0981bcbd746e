"""The compared systems, the paper's and ours, and the ablation from one to the other (pure; no rclpy).

A system is a set of per-node parameter overrides of the nodes' parameter files
(``calibration_bringup/config/*.yaml``): ``ours`` is the files as they are, ``paper`` (:data:`PAPER`)
the paper's system as its authors describe it (docs/paper_fidelity.md is the equation-by-equation
audit: where each piece lives, and every deviation with its reason). Where the paper is silent
(``Q``, the noise law's ``a`` and ``b``, the cost's penalty, the kernel width, ``gamma``,
``delta``, the CN constant) the values below were chosen by :mod:`calibration_bringup.paper_tuning`
on tuning seeds (seed base 1000) that no reported experiment uses; its record is
``docs/results/paper/tuning.md``.

:data:`ABLATION` walks from the paper's system to ours one change at a time: each step hands the
named parameters back to our parameter files, so step ``k``'s system is :data:`PAPER` without the
keys of steps ``1..k``, and after the last step nothing of :data:`PAPER` is left (a test checks
that the steps partition its keys). ``python -m calibration_bringup.ablation`` runs it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from body_schema.sampling import PAPER_WIDTH_ANGLE, PAPER_WIDTH_LENGTH

__all__ = ['PAPER_TUNED', 'paper_system', 'PAPER', 'SYSTEMS', 'AblationStep', 'ABLATION', 'ablation_overrides', 'without']

#: The paper's silent constants, as chosen on the tuning seeds (docs/results/paper/tuning.md;
#: ``python -m calibration_bringup.paper_tuning``); :func:`paper_system` turns them into parameters.
PAPER_TUNED: dict[str, float] = {
    # Process noise Q per update, as a fraction of the initial covariance's diagonal (the paper's
    # uniform widths, 46 mm and 54 deg: w^2 / 12 per parameter).
    'q_fraction': 1e-5,
    # The single noise law sigma^2 = a r^2 + b (phi - 45)^2, R = sigma^2 I (m, rad; r in m, phi in deg).
    'noise_a': 1e-2,
    'noise_b': 1e-4,
    # CN: one constant sigma for every component (m, rad).
    'cn_sigma': 0.09,
    # The cost's a * arctan(b * p_x) (p_x in m).
    'penalty_a': 0.1,
    'penalty_b': 10.0,
    # The smoothed Beta's squared-exponential kernel width (normalised joints).
    'length_scale': 0.2,
    # DIRECT's evaluations per selection.
    'max_evals': 1000,
    # UCSAL's weight on the normalised L1 distance, CCSAL's half-width (normalised joints).
    'gamma': 1e-5,
    'delta': 0.2,
}


def paper_system(tuned: Mapping[str, float] = PAPER_TUNED) -> dict[str, dict[str, Any]]:
    """The paper's system (docs/paper_fidelity.md) with the silent constants ``tuned`` (keys of
    :data:`PAPER_TUNED`); what each override is, in the paper's terms, is commented.

    Raises
    ------
    KeyError
        Naming a missing constant.
    """
    missing = sorted(set(PAPER_TUNED) - set(tuned))
    if missing:
        raise KeyError(f'paper_system needs {missing}')
    t = tuned
    law = {'pdn_a_pos': t['noise_a'], 'pdn_a_rot': t['noise_a'], 'pdn_b_pos': t['noise_b'],
           'pdn_b_rot': t['noise_b'], 'pdn_floor_pos': 0.0, 'pdn_floor_rot': 0.0}
    cn = {'cn_sigma_pos': float(t['cn_sigma']), 'cn_sigma_rot_deg': float(math.degrees(t['cn_sigma']))}
    q = {'q_length': float(t['q_fraction'] * PAPER_WIDTH_LENGTH ** 2 / 12.0),
         'q_angle': float(t['q_fraction'] * PAPER_WIDTH_ANGLE ** 2 / 12.0)}
    return {
        # "A random initial joint configuration ... is set and the algorithm ... executes all four
        # methods": one random start per repetition, shared by the methods.
        'sim': {'random_start': True},
        # OpenCV's ArUco module as it comes: no sub-pixel or edge refinement of the corners, no
        # polish of the pose, no gate on reprojection error, ambiguity or marker size.
        # One eye: "Redundant measurements could be used with both iCub cameras" is its future work.
        'detector': {'corner_refinement': False, 'edge_refinement': False, 'refine_lm': False,
                     'max_reprojection_error_px': 100.0, 'ambiguity_ratio': 1.0, 'ambiguity_margin_px': 0.0,
                     'min_side_px': 0.0, 'use_right_eye': False, **law},
        # The EKF (eqs. 3-6): one linearisation per update, P <- P + Q before each, no outlier gate.
        'estimator': {'estimator': 'ekf', 'iterations': 1, 'gate_probability': 0.0, **q, **cn},
        # C = C0 / eta + a arctan(b p_x) (eq. 8) with C0 the expected trace after the next update
        # of P + Q (eq. 7); the smoothed Beta from a flat prior Be(1, 1) (eqs. 12-14); NLopt's
        # DIRECT (Jones et al.); repeated configurations allowed; no collision check (the paper has none).
        'selector': {'collision_check': False, 'criterion': 'a_optimal', 'occlusion_mode': 'paper', 'occlusion_prior': 'flat',
                     'optimizer': 'direct', 'algorithm': 'DIRECT', 'max_evals': int(t['max_evals']),
                     'repeat_tolerance': 0.0,
                     'penalty_a': float(t['penalty_a']), 'penalty_b': float(t['penalty_b']),
                     'occlusion_length_scale': float(t['length_scale']), 'occlusion_a0': 1.0, 'occlusion_b0': 1.0,
                     'gamma': float(t['gamma']), 'delta': float(t['delta']), **q, **law, **cn,
                     # Planned for the one eye; the geometric prior's constants (unused with the flat
                     # prior) as fitted to uniform configurations, for the ablation's later steps.
                     'use_right_eye': False, 'visibility_margin': 0.06, 'visibility_marker_widths': 0.0},
    }


#: The paper's system with the tuned constants.
PAPER: dict[str, dict[str, Any]] = paper_system()

#: Compared systems: per-node parameter overrides of the nodes' parameter files.
SYSTEMS: dict[str, dict[str, dict[str, Any]]] = {'ours': {}, 'paper': PAPER}


@dataclass(frozen=True)
class AblationStep:
    """One change from the paper's system towards ours.

    Attributes
    ----------
    name : str
        Short, file-name safe.
    change : str
        What the step changes, in words (the ablation table's row label).
    keys : tuple of str
        ``node.parameter`` keys of :data:`PAPER` handed back to our parameter files.
    """

    name: str
    change: str
    keys: tuple[str, ...]


def _keys(node: str, *names: str) -> tuple[str, ...]:
    return tuple(f'{node}.{n}' for n in names)


_LAW = ('pdn_a_pos', 'pdn_a_rot', 'pdn_b_pos', 'pdn_b_rot', 'pdn_floor_pos', 'pdn_floor_rot')
_CN = ('cn_sigma_pos', 'cn_sigma_rot_deg')
_Q = ('q_length', 'q_angle')

#: From the paper's system to ours, one change at a time (cumulative).
ABLATION: tuple[AblationStep, ...] = (
    AblationStep('start', 'start at the box centre (not a random configuration)', _keys('sim', 'random_start')),
    AblationStep('detector', "our detector: sub-pixel and edge-fitted corners, LM polish, gates on "
                 'reprojection (1 px), flip ambiguity and size',
                 _keys('detector', 'corner_refinement', 'edge_refinement', 'refine_lm', 'max_reprojection_error_px',
                       'ambiguity_ratio', 'ambiguity_margin_px', 'min_side_px')),
    AblationStep('noise-law', 'noise law fitted per block (position, orientation) with a floor, instead of '
                 'one sigma^2 I; CN fitted to the detector',
                 _keys('detector', *_LAW) + _keys('estimator', *_CN) + _keys('selector', *_LAW, *_CN)),
    AblationStep('gate', "chi-square gate (99.9%) on the EKF's innovations, after 10 updates",
                 _keys('estimator', 'gate_probability')),
    AblationStep('no-q', 'no process noise (Q = 0)', _keys('estimator', *_Q) + _keys('selector', *_Q)),
    AblationStep('iekf', 'iterated EKF (5 linearisations per update)', _keys('estimator', 'iterations')),
    AblationStep('map', 'online MAP estimator (robust loss, re-solved after each observation) instead of the EKF',
                 _keys('estimator', 'estimator')),
    AblationStep('v-optimal', 'v-optimality (hand-pose variance over the box) instead of the trace of P',
                 _keys('selector', 'criterion')),
    AblationStep('gain', "occlusion as a discount on the gain (-eta g / tr(A P)) instead of C0 / eta, with "
                 "that form's constants (penalty, kernel, Beta prior, gamma, delta)",
                 _keys('selector', 'occlusion_mode', 'penalty_a', 'penalty_b', 'occlusion_length_scale',
                       'occlusion_a0', 'occlusion_b0', 'gamma', 'delta')),
    AblationStep('visibility', 'geometric visibility prior from the estimate (instead of the flat Beta prior)',
                 _keys('selector', 'occlusion_prior')),
    AblationStep('batch', 'batched search: 512 Sobol candidates, BOBYQA refinement and snapping (instead of '
                 "DIRECT)", _keys('selector', 'optimizer', 'algorithm', 'max_evals')),
    AblationStep('no-repeats', 'no configuration selected twice', _keys('selector', 'repeat_tolerance')),
    AblationStep('collision', 'targets and paths refused within the collision margins (the torso, the head, the '
                 'arm itself)', _keys('selector', 'collision_check')),
    AblationStep('whole-marker', "the visibility prior asks for the whole marker inside the image (margin 2% plus "
                 "half the marker's projected width, instead of a fixed 6%)",
                 _keys('selector', 'visibility_margin', 'visibility_marker_widths')),
    AblationStep('stereo', 'both eyes: one detection from both images, the selection planned for either eye',
                 _keys('detector', 'use_right_eye') + _keys('selector', 'use_right_eye')),
)


def without(system: Mapping[str, Mapping[str, Any]], keys: tuple[str, ...] | list[str]) -> dict[str, dict[str, Any]]:
    """``system`` without the ``node.parameter`` ``keys`` (nodes left with nothing are dropped).

    Raises
    ------
    KeyError
        Naming a key that ``system`` does not override.
    """
    out = {node: dict(params) for node, params in system.items()}
    for key in keys:
        node, _, name = key.partition('.')
        if name not in out.get(node, {}):
            raise KeyError(f'{key!r} is not overridden by the system')
        del out[node][name]
    return {node: params for node, params in out.items() if params}


def ablation_overrides(step: int) -> dict[str, dict[str, Any]]:
    """The system after ``step`` changes of :data:`ABLATION` (0: :data:`PAPER`; ``len(ABLATION)``: ours, empty).

    Raises
    ------
    ValueError
        If ``step`` is outside ``0 .. len(ABLATION)``.
    """
    if not 0 <= step <= len(ABLATION):
        raise ValueError(f'ablation step must be in 0..{len(ABLATION)}, got {step}')
    return without(PAPER, [k for s in ABLATION[:step] for k in s.keys])
