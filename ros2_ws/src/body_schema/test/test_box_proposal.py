"""The calibration-box proposer: inside the limits, in the visibility band, seeded, and its errors."""
from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest
import yaml

from body_schema import box_proposal
from body_schema.box_proposal import (BAND, BoxProposal, NoFacingConfigurationError, ProposedBoxWarning,
                                      box_yaml, geometric_visibility, propose_box)
from body_schema.occlusion import VisibilityPrior
from body_schema.robot import RobotDescriptionError, load_robot, robot_from_dict, robot_path
from body_schema.sampling import uniform_configs

FAST = {'n_samples': 256, 'n_candidates': 256}


@pytest.fixture(scope='module')
def ur5e():
    return load_robot('ur5e')


@pytest.fixture(scope='module')
def proposal(ur5e) -> BoxProposal:
    return propose_box(ur5e, seed=1, **FAST)


def test_the_box_is_inside_the_limits_with_the_last_joint_wide(ur5e, proposal):
    box, lim = proposal.box, ur5e.limits
    assert box.shape == lim.shape
    assert np.all(box[:, 0] >= lim[:, 0]) and np.all(box[:, 1] <= lim[:, 1]) and np.all(box[:, 1] > box[:, 0])
    assert np.degrees(box[-1]) == pytest.approx([-170.0, 170.0])
    assert np.all((box[:, 0] <= proposal.centre) & (proposal.centre <= box[:, 1]))


def test_the_visibility_is_in_the_band_on_an_independent_draw(ur5e, proposal):
    assert proposal.in_band and proposal.visibility >= 0.75
    # Not the proposer's own Sobol points: 4000 uniform configurations of the box.
    p, per = geometric_visibility(ur5e, uniform_configs(proposal.box, 4000, seed=7))
    assert BAND[0] <= p.mean() <= BAND[1]
    assert set(per) == {'left'}
    assert proposal.below_plane <= 0.03 and proposal.colliding <= 0.03


def test_the_same_seed_gives_the_same_box(ur5e, proposal):
    again = propose_box(ur5e, seed=1, **FAST)
    np.testing.assert_array_equal(again.box, proposal.box)
    assert again.visibility == proposal.visibility


def test_a_camera_that_cannot_see_the_marker_is_an_error_naming_it():
    doc = yaml.safe_load(robot_path('ur5e').read_text())
    doc['fixed_cameras'][0]['rpy'] = [90.0, 0.0, -90.0]          # the tripod camera looks away, up into the air
    model = robot_from_dict(doc, propose_box=False)
    with pytest.raises(NoFacingConfigurationError, match=r"camera\(s\) \['left'\]") as err:
        propose_box(model, seed=1, collision=False, **FAST)
    assert isinstance(err.value, RobotDescriptionError)
    no_camera = {k: v for k, v in doc.items() if k not in ('camera', 'calibration_box')}
    with pytest.raises(NoFacingConfigurationError, match='needs a camera section'):
        propose_box(robot_from_dict(no_camera, propose_box=False))
    with pytest.raises(ValueError, match='target'):
        propose_box(model, target=0.95)


def test_load_robot_proposes_the_missing_box_once_and_keeps_the_written_ones(monkeypatch, tmp_path):
    monkeypatch.setenv('BODY_SCHEMA_CACHE', str(tmp_path))
    monkeypatch.setattr(box_proposal, '_CACHE', {})
    doc = yaml.safe_load(robot_path('ur5e').read_text())
    written = np.radians(np.array(doc['calibration_box'], dtype=float))
    np.testing.assert_allclose(load_robot('ur5e').calibration_box, written)    # a written box is kept
    del doc['calibration_box']
    calls = []
    box = np.radians([[-40, 40], [-110, -40], [50, 130], [-230, -140], [-130, -50], [-170, 170.0]])

    def fake(model, **_):
        calls.append(model.name)
        return BoxProposal(box, box.mean(axis=1), 0.75, {'left': 0.75}, 0.0, 0.0, ('left',), 512)

    monkeypatch.setattr(box_proposal, 'propose_box', fake)
    with pytest.warns(ProposedBoxWarning, match=r'paste into the description:\ncalibration_box: \[\[-40, 40\]'):
        model = robot_from_dict(copy.deepcopy(doc), source='my_arm.yaml')
    np.testing.assert_allclose(model.calibration_box, box)
    with warnings.catch_warnings():
        warnings.simplefilter('error')                      # once per process: no second warning
        np.testing.assert_allclose(robot_from_dict(copy.deepcopy(doc)).calibration_box, box)
    monkeypatch.setattr(box_proposal, '_CACHE', {})          # another process: from the file cache
    with pytest.warns(ProposedBoxWarning, match='cached in'):
        np.testing.assert_allclose(robot_from_dict(copy.deepcopy(doc)).calibration_box, box)
    assert calls == ['ur5e']
    np.testing.assert_allclose(robot_from_dict(copy.deepcopy(doc), propose_box=False).calibration_box,
                               model.limits)


def test_the_yaml_line_rounds_inward():
    box = np.radians([[-40.4, 40.6], [-170.0, 170.0]])
    assert box_yaml(box, box, 'deg') == 'calibration_box: [[-40, 40], [-170, 170]]'
    assert box_yaml(np.array([[-0.12345, 0.5]]), np.array([[-1.0, 1.0]]), 'rad') == \
        'calibration_box: [[-0.123, 0.500]]'


def test_the_command_prints_a_box_to_paste(capsys):
    assert box_proposal.main(['--robot', 'ur5e', '--samples', '64', '--candidates', '64', '--no-collision']) == 0
    out = capsys.readouterr().out
    line = out.strip().splitlines()[-1]
    assert line.startswith('calibration_box: [[') and 'geometric estimate' in out
    assert len(yaml.safe_load(line)['calibration_box']) == 6


def test_a_large_near_marker_is_seen_more_obliquely_than_the_fixed_limit():
    cam = load_robot('ur5e').camera
    view = np.eye(4)                                     # camera at the origin looking along +z
    marker = np.eye(4)
    marker[:3, 3] = [0.0, 0.0, 1.0]
    tilt = np.radians(100.0)                              # 80 deg from facing the camera (normal -z)
    marker[:3, :3] = [[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]]
    fixed = VisibilityPrior(cam).probability(view, marker[None])
    big = VisibilityPrior(cam, max_view_angle_deg=89.0, marker_side=0.08).probability(view, marker[None])
    small = VisibilityPrior(cam, max_view_angle_deg=89.0, marker_side=0.01).probability(view, marker[None])
    assert fixed < 0.15 and big > 0.6 and small < 0.05     # floor 0.02, ceiling 0.9
    with pytest.raises(ValueError, match='marker_side'):
        VisibilityPrior(cam, marker_side=-1.0)


def test_a_robot_watched_by_its_own_eyes_has_no_mount_plane(monkeypatch, tmp_path):
    monkeypatch.setenv('BODY_SCHEMA_CACHE', str(tmp_path))
    monkeypatch.setattr(box_proposal, '_CACHE', {})
    doc = yaml.safe_load(robot_path('icub_right_arm').read_text())
    del doc['calibration_box']
    planes = []

    def fake(model, plane_z=0.0, **_):
        planes.append(plane_z)
        return BoxProposal(model.limits, model.limits.mean(axis=1), 0.75, {'left': 0.75}, float('nan'), 0.0,
                           ('left',), 512)

    monkeypatch.setattr(box_proposal, 'propose_box', fake)
    with pytest.warns(ProposedBoxWarning):
        robot_from_dict(doc)
    assert planes == [None]
