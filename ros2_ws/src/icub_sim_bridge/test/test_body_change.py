"""Parsing a body change (pure)."""
import numpy as np
import pytest

from body_schema.robot import load_robot
from icub_sim_bridge.body_change import BodyChangeError, parse_body_change

NAMES = load_robot().joint_names


def test_terms_add_up_in_table_units() -> None:
    delta = parse_body_change('r_wrist_prosup.d+0.010, r_shoulder_yaw.offset+3  r_elbow.a-1e-3 r_elbow.a-1e-3',
                              NAMES)
    expected = np.zeros((7, 4))
    expected[4, 1] = 0.010
    expected[2, 3] = np.radians(3.0)
    expected[3, 0] = -2e-3
    np.testing.assert_allclose(delta, expected)


@pytest.mark.parametrize('spec, words', [('', 'empty'), ('r_elbow.q+1', 'expected'), ('r_knee.d+0.1', 'r_knee'),
                                         ('r_elbow.d0.1', 'expected'), ('r_elbow.d+1.2.3', 'not a number'),
                                         ('r_elbow.alpha+inf', 'expected')])
def test_bad_specs_name_the_term(spec: str, words: str) -> None:
    with pytest.raises(BodyChangeError, match=words):
        parse_body_change(spec, NAMES)
