"""The parameterisation study: its chains equal the descriptions, its Jacobians their models'
derivatives, its ranks the geometry's, Hayati's table follows a tilt DH jumps on, and the command
runs small."""
from __future__ import annotations

import numpy as np
import pytest

from body_schema.robot import load_robot
from tools import parameterisation_study as ps


@pytest.fixture(scope='module')
def ur5e():
    return load_robot('ur5e')


@pytest.fixture(scope='module')
def panda():
    return load_robot('panda')


@pytest.mark.parametrize('name', ['ur5e', 'panda'])
def test_origin_chain_moves_the_hand_as_the_description(name: str) -> None:
    model = load_robot(name)
    qs = np.random.default_rng(1).uniform(-2, 2, (20, model.n_joints))
    np.testing.assert_allclose(ps.origin_chain(model).frames(qs)[1], model.forward_kinematics(qs), atol=1e-12)


@pytest.mark.parametrize('name', ['ur5e', 'panda'])
def test_analytic_jacobians_are_the_models_derivatives(name: str) -> None:
    model = load_robot(name)
    qs = np.random.default_rng(2).uniform(-2, 2, (4, model.n_joints))
    for key, p in ps.parameterisations(model).items():
        h, n = 1e-6, len(p.names)
        fd = np.zeros((len(qs), 6, n))
        base = p.poses(np.zeros(n), qs)
        for i in range(n):
            step = np.zeros(n)
            step[i] = h
            plus, minus = p.poses(step, qs), p.poses(-step, qs)
            fd[:, :3, i] = (plus[:, :3, 3] - minus[:, :3, 3]) / (2 * h)
            fd[:, 3:, i] = ps.kinematics.rotation_vector_error(plus[:, :3, :3], minus[:, :3, :3]) / (2 * h)
        np.testing.assert_allclose(p.jacobian(qs), fd, atol=1e-7, err_msg=key)
        np.testing.assert_allclose(base, model.forward_kinematics(qs), atol=1e-12, err_msg=key)


def test_ranks_are_the_geometrys(ur5e, panda) -> None:
    # 4 per joint + 6 for a complete set; the UR5e's three parallel axes cost DH two d's, not Hayati.
    expected = {'ur5e': {'dh': 22, 'hayati': 24, 'dh+bt': 28, 'hayati+bt': 30, 'origins': 30},
                'panda': {'dh': 28, 'hayati': 28, 'dh+bt': 34, 'hayati+bt': 34, 'origins': 34}}
    for model in (ur5e, panda):
        qs = ps.uniform_configs(model.calibration_box, 30, 0)
        got = {k: ps.conditioning(p.jacobian(qs), p.names).rank for k, p in ps.parameterisations(model).items()}
        assert got == expected[model.name]
    assert ps.hayati_links(ur5e.dh) == (1, 2) and ps.hayati_links(panda.dh) == ()
    with pytest.raises(ValueError, match='zero columns'):
        ps.conditioning(np.zeros((12, 2)), ['a', 'b'])


def test_hayati_follows_the_tilt_that_sends_dh_to_infinity(ur5e) -> None:
    rows = {(r['about'], r['tilt_deg']): r for r in ps.tilt_study(ur5e, (0.1,))}
    y, x = rows[('y', 0.1)], rows[('x', 0.1)]
    assert y['dh_length'] > 100 and y['dh_angle'] == pytest.approx(90, abs=1e-6)   # a / tan(0.1 deg) = 243 m
    assert abs(y['beta_deg']) == pytest.approx(0.1) and y['hayati_length'] < 1e-12 and y['hayati_angle'] < 1e-9
    assert x['dh_length'] < 1e-12 and x['dh_angle'] == pytest.approx(0.1) and x['beta_deg'] == 0
    assert ps.tilt_study(load_robot('panda')) is None


def test_hayatis_table_moves_the_hand_as_the_tilted_arm(ur5e) -> None:
    chain = ps.origin_chain(ur5e)
    origins = chain.origins.copy()
    origins[2] = origins[2] @ ps._turn([0.3, 0.9, 0.1] / np.linalg.norm([0.3, 0.9, 0.1]), np.radians(0.5))
    tilted = ps.OriginChain(origins, chain.axes, chain.tool, chain.names)
    table, beta, base, tool = ps.derive_hayati(ps.as_urdf_chain(tilted), (1, 2))
    qs = np.random.default_rng(3).uniform(-2, 2, (10, 6))
    hand = ps._beta_hand(base, table, beta, qs) @ tool
    np.testing.assert_allclose(hand, tilted.frames(qs)[1], atol=1e-12)
    assert table[1, 1] == table[2, 1] == 0 and 0 < abs(np.degrees(beta[1])) < 0.5 and abs(beta[2]) < 1e-12


def test_the_command_prints_its_three_tables(capsys: pytest.CaptureFixture[str]) -> None:
    assert ps.main(['--robots', 'ur5e', '--configs', '12', '--seeds', '1', '--eval', '20']) == 0
    out = capsys.readouterr().out
    for row in ('| ur5e | dh | 24 | 22 |', '| ur5e | hayati | 24 | 24 |', '| ur5e | origins | 42 | 30 |'):
        assert row in out
    assert 'pair shoulder_lift_joint-elbow_joint' in out
    rows = [ln for ln in out.splitlines() if ln.startswith('| ur5e | hayati+bt |')]
    assert len(rows) == 2                                                        # conditioning and accuracy
    with pytest.raises(SystemExit):
        ps.main(['--configs', '3'])
