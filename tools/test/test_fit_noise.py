"""The noise-law fitting command: its YAML is a description's block; its calibration figures are right."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from body_schema import load_robot
from body_schema.noise import PoseDependentNoise
from body_schema.robot import robot_from_dict, robot_path
from tools.detector_accuracy import FrameScores, draw_scores
from tools.fit_noise import calibration_of, law_yaml, main, shape, stereo_ratios, tails, views_of


def _draw(law: PoseDependentNoise, n: int, seed: int) -> FrameScores:
    return draw_scores(law, n, seed, (0.8, 1.8))


def test_the_printed_block_is_a_description_block_that_loads_back() -> None:
    law = PoseDependentNoise(2.74e-7, 1.23e-8, 1.27e-6, 1.82e-8, 1e-8, 2.74e-7)
    data = yaml.safe_load(robot_path('ur5e').read_text())
    data.update(yaml.safe_load(law_yaml(law, 'fitted')))
    assert PoseDependentNoise.for_robot(robot_from_dict(data)) == law
    data.update(yaml.safe_load(law_yaml(law, 'fitted', 'sandwich_hc3')))
    assert robot_from_dict(data).noise_covariance == 'sandwich_hc3'
    # The stereo ratios are printed for a robot with eyes only, and load back.
    assert 'stereo' not in law_yaml(law, 'fitted')
    eyed = dataclasses.replace(law, stereo_pos=0.2, stereo_rot=1.3)
    data = yaml.safe_load(robot_path('icub_right_arm').read_text())
    data.update(yaml.safe_load(law_yaml(eyed, 'fitted', stereo=True)))
    assert PoseDependentNoise.for_robot(robot_from_dict(data)) == eyed


def test_the_stereo_ratios_of_rendered_eyes_say_the_stereo_estimate_beats_the_fused_one() -> None:
    from body_schema.sampling import uniform_configs
    from icub_sim_bridge.world import SimWorld
    from tools.detector_accuracy import collect

    model = load_robot('icub_right_arm')
    with SimWorld(model) as world:
        frames = collect(model, world, uniform_configs(model.calibration_box, 60, 11), views_of(model))
    st = stereo_ratios(frames, PoseDependentNoise(stereo_pos=1.0, stereo_rot=1.0), model)
    assert st['n'] >= 10
    assert st['stereo_pos'] < 0.5 and st['pos_med_mm'] < 0.6 * st['left_pos_med_mm']
    assert 0.3 < st['stereo_rot'] < 3.0
    # One eye only: nothing to fit.
    assert stereo_ratios([f for f in frames if f.eye == 'left'], PoseDependentNoise(), model)['n'] == 0


def test_calibration_figures_are_one_for_the_true_law_and_show_a_pessimistic_one() -> None:
    truth = PoseDependentNoise(3e-7, 1e-8, 1.3e-6, 2e-8, 1e-8, 3e-7)
    out = _draw(truth, 5000, 0)
    c = calibration_of(truth, out)
    assert c['ratio_pos'] == pytest.approx(1.0, abs=0.05) and c['ratio_rot'] == pytest.approx(1.0, abs=0.05)
    assert c['cover_pos'] == pytest.approx(0.95, abs=0.01) and c['cover_rot'] == pytest.approx(0.95, abs=0.01)
    wide = dataclasses.replace(truth, a_pos=4 * truth.a_pos, b_pos=4 * truth.b_pos, floor_pos=4 * truth.floor_pos)
    assert calibration_of(wide, out)['ratio_pos'] == pytest.approx(0.25, abs=0.02)


def test_views_are_the_description_cameras_at_their_resolution() -> None:
    assert views_of(load_robot('ur5e')) == [('left', (1280, 1024))]
    assert [v[0] for v in views_of(load_robot('icub_right_arm'))] == ['left', 'right']
    with pytest.raises(ValueError, match="'bare' has no camera"):
        views_of(dataclasses.replace(load_robot('ur5e'), name='bare', fixed_cameras={}))


def test_too_few_configurations_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(['--n', '5'])
    assert e.value.code == 2
    assert '--n must be at least 20 for a fit of six coefficients, got 5' in capsys.readouterr().err


def test_tails_tell_gaussian_errors_from_heavy_tailed_ones() -> None:
    law = PoseDependentNoise(3e-7, 1e-8, 1.3e-6, 2e-8, 1e-8, 3e-7)
    gauss = tails(law, _draw(law, 4000, 0))
    assert gauss['dof'] > 30 and gauss['scale'] == pytest.approx(1.0, abs=0.1) and gauss['beyond_9999'] < 0.002
    heavy = _draw(law, 4000, 1)
    rng = np.random.default_rng(2)
    w = rng.chisquare(1.3, heavy.r.size) / 1.3               # a Student t (1.3 dof) as a Gaussian scale mixture
    heavy = dataclasses.replace(heavy, pos_err=heavy.pos_err / np.sqrt(w), rot_err=heavy.rot_err / np.sqrt(w))
    t = tails(law, heavy)
    assert t['dof'] == pytest.approx(1.3, rel=0.2) and t['beyond_9999'] > 0.05


def test_shape_sees_a_depth_error_the_isotropic_law_does_not_describe() -> None:
    law = PoseDependentNoise(3e-7, 1e-8, 1.3e-6, 2e-8, 1e-8, 3e-7)
    out = _draw(law, 4000, 3)
    turn = Rotation.from_euler('x', 90, degrees=True).as_matrix()      # camera z = root -y
    cams = np.repeat(turn[None], out.r.size, axis=0)
    iso = shape(law, out, cams)
    assert np.allclose(iso['position'] + iso['rotation'], 1.0, atol=0.1) and iso['ratio'] < 1.15
    deep = dataclasses.replace(out, pos_vec=out.pos_vec * np.array([1.0, 7.0, 1.0]))   # 7x along root y = depth
    aniso = shape(law, deep, cams)
    assert aniso['position'][2] == pytest.approx(7.0, rel=0.1) and aniso['position'][0] == pytest.approx(1.0, rel=0.1)
    assert aniso['ratio'] == pytest.approx(7.0, rel=0.15)


def test_the_depth_fit_recovers_a_line_of_sight_law_and_the_isotropic_fit_cannot() -> None:
    from tools.detector_accuracy import fit_noise
    truth = PoseDependentNoise(3e-7, 1e-8, 1.3e-6, 2e-8, 1e-8, 3e-7, depth_ratio=6.0)
    out = _draw(truth, 6000, 3)
    deep, flat = fit_noise(out, depth=True), fit_noise(out)
    assert deep.pdn.depth_ratio == pytest.approx(6.0, rel=0.05) and flat.pdn.depth_ratio == 1.0
    for r in (0.9, 1.7):
        assert deep.pdn.variances(r, 30.0)[0] == pytest.approx(truth.variances(r, 30.0)[0], rel=0.1)
    assert deep.nll_pdn < flat.nll_pdn - 0.5
    assert deep.coverage_pdn[0] == pytest.approx(0.95, abs=0.01)
    c = calibration_of(truth, out)
    assert c['ratio_pos'] == pytest.approx(1.0, abs=0.05) and c['cover_pos'] == pytest.approx(0.95, abs=0.01)
    block = yaml.safe_load(law_yaml(deep.pdn, 'fitted'))['noise_model']
    assert block['depth_ratio'] == pytest.approx(6.0, rel=0.05)
    assert 'depth_ratio' not in yaml.safe_load(law_yaml(flat.pdn, 'fitted'))['noise_model']


def test_the_typical_spread_sets_the_loss_scale_of_a_heavy_tailed_law() -> None:
    from tools.detector_accuracy import fit_noise
    from tools.fit_noise import loss_scale_for, typical_spread

    law = PoseDependentNoise(3e-7, 1e-8, 1.3e-6, 2e-8, 1e-8, 3e-7)
    right = _draw(law, 4000, 0)
    assert typical_spread(law, right) == pytest.approx(1.0, abs=0.05)
    assert loss_scale_for(typical_spread(law, right)) == 0.0                  # the estimator's default
    # 9 in 10 errors from the law, 1 in 10 ten times wider: a law fitted to their variance is
    # sqrt(0.9 + 10) = 3.3 times the typical error.
    heavy = _draw(law, 4000, 1)
    wide = np.where(np.random.default_rng(2).random(heavy.r.size) < 0.1, 10.0, 1.0)
    heavy = dataclasses.replace(heavy, pos_err=heavy.pos_err * wide, rot_err=heavy.rot_err * wide,
                                pos_vec=heavy.pos_vec * wide[:, None])
    fitted = fit_noise(heavy).pdn
    spread = typical_spread(fitted, heavy)
    assert 0.2 < spread < 0.45
    assert loss_scale_for(spread) == pytest.approx(3.0 * spread)
    block = yaml.safe_load(law_yaml(fitted, 'fitted', 'sandwich_hc3', loss_scale_for(spread)))
    data = yaml.safe_load(robot_path('ur5e').read_text())
    data.update(block)
    assert robot_from_dict(data).noise_loss_scale == pytest.approx(3.0 * spread, rel=0.01)
    assert 'loss_scale' not in yaml.safe_load(law_yaml(fitted, 'fitted'))['noise_model']
    with pytest.raises(ValueError, match='spread must be finite and > 0, got nan'):
        loss_scale_for(float('nan'))
