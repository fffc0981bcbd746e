"""The interface package: DH file round trip, status encoding, outcome vocabulary, parameters from
settings dataclasses, QoS from the contract, and purity (no rclpy in the pure modules)."""
from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from calibration_interfaces import contract
from calibration_interfaces.dh_file import DhFileError, read_dh_file, write_dh_file
from calibration_interfaces.outcome import Outcome, StatusFormatError, StatusKey, decode_status, encode_status
from calibration_interfaces.parameters import markdown_table, parameter_specs, setting, settings_from_parameters

PURE = ['contract', 'dh_file', 'outcome', 'parameters', 'messages', 'throttle']


def test_pure_modules_do_not_import_rclpy() -> None:
    code = ('import sys\n' + ''.join(f'import calibration_interfaces.{m}\n' for m in PURE)
            + 'print(sorted(m for m in sys.modules if m.split(".")[0] == "rclpy"))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == '[]'


def test_dh_file_round_trip_with_sigma(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    dh = rng.uniform(-1, 1, (7, 4))
    sigma = rng.uniform(0, 0.1, (7, 4))
    names = [f'j{i}' for i in range(7)]
    path = write_dh_file(tmp_path / 'out' / 'x_dh.yaml', dh, names, 'arm', sigma, extra={'updates': {'updates': 3}})
    table = read_dh_file(path, n_joints=7)
    np.testing.assert_allclose(table.dh, dh, atol=1e-12)
    np.testing.assert_allclose(table.sigma, sigma, atol=1e-12)
    assert table.names == tuple(names) and table.robot == 'arm'


def test_a_robot_description_is_a_dh_file() -> None:
    import body_schema
    from body_schema.robot import robot_path

    arm = body_schema.load_robot()
    table = read_dh_file(robot_path('icub_right_arm'), n_joints=arm.n_joints)
    np.testing.assert_allclose(table.dh, arm.dh, atol=1e-12)
    assert table.sigma is None and table.names == tuple(arm.joint_names)


@pytest.mark.parametrize('text, match', [
    ('joints: []', 'non-empty "joints"'),
    ('angle_unit: grad\njoints: [{dh: [0, 0, 0, 0]}]', "angle_unit must be 'deg' or 'rad', got 'grad'"),
    ('joints: [{dh: [0, 0, 0]}]', r'shape \(1, 3\)'),
    ('joints: [{dh: [0, .nan, 0, 0]}]', 'NaN'),
    ('joints: [{name: a}]', "every joint needs 'dh'"),
    ('joints: [{dh: [0, 0, 0, 0]}]', 'expected 7 joints, got 1'),
    ('joints: [', 'not valid YAML'),
])
def test_malformed_dh_files_are_refused_with_the_reason(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / 'bad.yaml'
    path.write_text(text)
    with pytest.raises(DhFileError, match=match):
        read_dh_file(path, n_joints=7)


def test_missing_dh_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(DhFileError, match='nope.yaml'):
        read_dh_file(tmp_path / 'nope.yaml')


def test_status_round_trip_and_errors() -> None:
    q = np.array([0.1, -0.2, 0.3])
    kv = encode_status(Outcome.REJECTED, 12.5, q, 5.25, 0.001, {'updates': 4, 'rejected': 1, 'duplicates': 2})
    assert set(kv) == {k.value for k in StatusKey} and all(type(k) is str for k in kv)
    s = decode_status(kv)
    assert s.outcome is Outcome.REJECTED and s.stamp == 12.5 and s.mahalanobis == 5.25
    np.testing.assert_allclose(s.joints, q)
    assert s.counters == {'updates': 4, 'rejected': 1, 'duplicates': 2, 'outliers': 0, 'changes': 0}
    mine = decode_status(encode_status(Outcome.OUTLIER, 1.0, q, 9.0, 0.01,
                                       {'updates': 4, 'rejected': 0, 'duplicates': 0, 'outliers': 1, 'changes': 1}))
    assert mine.outcome is Outcome.OUTLIER and mine.outcome.updated
    assert mine.counters['outliers'] == 1 and mine.counters['changes'] == 1
    # A bag recorded before the MAP estimator has no outlier / change counters: read as 0.
    old = {k: v for k, v in kv.items() if k not in ('outliers', 'changes')}
    assert decode_status(old).counters['outliers'] == 0
    with pytest.raises(StatusFormatError, match="'joints'"):
        decode_status({k: v for k, v in kv.items() if k != 'joints'})
    with pytest.raises(StatusFormatError, match='bogus'):
        decode_status({**kv, 'outcome': 'bogus'})


def test_outcome_values_are_plain_strings() -> None:
    assert f'{Outcome.ACCEPTED}' == 'accepted' and Outcome('timeout') is Outcome.TIMEOUT
    assert [o for o in Outcome if o.updated] == [Outcome.ACCEPTED, Outcome.OUTLIER, Outcome.REJECTED]


@dataclass(frozen=True)
class _Demo:
    rate: float = setting(2.5, 'Camera rate [Hz]', (0.0, 60.0))
    count: int = setting(3, 'How many', (1, 10), name='n_items')
    mode: str = setting('a', 'Mode', choices=('a', 'b'))
    eyes: tuple = setting(('left',), 'Eyes')
    internal: int = 7


def test_parameter_specs_from_dataclass_fields() -> None:
    specs = {s.name: s for s in parameter_specs(_Demo)}
    assert list(specs) == ['rate', 'n_items', 'mode', 'eyes']
    assert specs['n_items'].field == 'count' and specs['rate'].range == (0.0, 60.0)
    assert specs['mode'].full_description == 'Mode (a | b)'
    s = settings_from_parameters(_Demo, {'rate': 1.0, 'n_items': 4, 'mode': 'b', 'eyes': ['right']}, internal=1)
    assert s == _Demo(1.0, 4, 'b', ('right',), 1)
    with pytest.raises(ValueError, match=r"parameter mode: 'c' is not one of \['a', 'b'\]"):
        settings_from_parameters(_Demo, {'mode': 'c'})
    table = markdown_table(_Demo)
    assert "| `n_items` | `3` | 1 .. 10 | How many |" in table and "| `mode` | `'a'` | a \\| b | Mode |" in table


def test_setting_refuses_a_mutable_default() -> None:
    with pytest.raises(TypeError, match='use a tuple'):
        setting([1.0], 'list')


def test_contract_qos() -> None:
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    from calibration_interfaces.node_util import qos_profile

    latched = qos_profile('/body_schema/estimate')
    assert (latched.depth, latched.durability, latched.reliability) == (
        1, DurabilityPolicy.TRANSIENT_LOCAL, ReliabilityPolicy.RELIABLE)
    img = qos_profile('/camera/left/image_raw', depth=2)
    assert (img.depth, img.reliability) == (2, ReliabilityPolicy.BEST_EFFORT)
    assert contract.topic('/camera/left/pose').latched and contract.topic('/camera/left/image_raw').sensor
    with pytest.raises(KeyError, match='/nope'):
        qos_profile('/nope')


def test_spin_node_runs_the_given_loop_then_destroys_the_node_and_shuts_down(monkeypatch) -> None:
    import rclpy
    from rclpy.node import Node

    from calibration_interfaces.node_util import spin_node

    monkeypatch.setenv('ROS_DOMAIN_ID', '151')      # outside the fixtures' 1..100
    events: list[str] = []

    class Probe(Node):
        def __init__(self) -> None:
            super().__init__('spin_node_probe')

        def destroy_node(self) -> None:
            events.append('destroyed')
            super().destroy_node()

    def run(node: Node) -> None:
        assert rclpy.ok() and node.get_name() == 'spin_node_probe'
        events.append('ran')

    spin_node(Probe, ['probe'], run)
    assert events == ['ran', 'destroyed'] and not rclpy.ok()
    # A failing constructor still shuts rclpy down (and has no node to destroy).
    with pytest.raises(RuntimeError, match='boom'):
        spin_node(lambda: (_ for _ in ()).throw(RuntimeError('boom')), ['probe'])
    assert not rclpy.ok()


def test_spin_node_takes_a_shutdown_racing_the_wait_set_as_a_stop_and_other_rcl_errors_as_failures(
        monkeypatch) -> None:
    import rclpy
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.node import Node

    from calibration_interfaces.node_util import spin_node

    monkeypatch.setenv('ROS_DOMAIN_ID', '152')
    destroyed: list[str] = []

    class Probe(Node):
        def __init__(self) -> None:
            super().__init__('spin_node_race')

        def destroy_node(self) -> None:
            destroyed.append(self.get_name())
            super().destroy_node()

    def shut_then_fail(node: Node) -> None:
        # What rclpy.spin meets when a SIGINT's shutdown lands after its context check.
        node.context.shutdown()
        raise _rclpy.RCLError('failed to initialize wait set: the given context is not valid')

    spin_node(Probe, ['probe'], shut_then_fail)          # a stop: no exception, the node destroyed
    assert destroyed == ['spin_node_race'] and not rclpy.ok()

    def fail(node: Node) -> None:
        raise _rclpy.RCLError('failed to take message')

    with pytest.raises(_rclpy.RCLError, match='failed to take'):
        spin_node(Probe, ['probe'], fail)
    assert destroyed == ['spin_node_race'] * 2 and not rclpy.ok()


# A SIGINT that lands in a finalizer during the imports: Python prints "Exception ignored" and
# goes on (seen in tests/test_node_signals.py under load: the detector then ran until SIGKILLed).
_SWALLOWED_SIGINT = """
import os, signal{startup}

class Finalizer:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):   # let the interpreter run the handler here, inside the finalizer
            pass

Finalizer()
from calibration_interfaces.node_util import spin_node

def build():
    raise SystemExit(5)          # reaching this means the signal was lost

spin_node(build, ['probe'])
print('ended without building the node')
"""


@pytest.mark.parametrize('first', [True, False], ids=['startup imported first', 'without it'])
def test_a_sigint_python_swallowed_during_the_imports_still_ends_the_node(first: bool) -> None:
    code = _SWALLOWED_SIGINT.format(startup='\nfrom calibration_interfaces import startup' if first else '')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert 'Exception ignored' in done.stderr and 'KeyboardInterrupt' in done.stderr, done.stderr
    if first:
        assert done.returncode == 0 and 'ended without building the node' in done.stdout, done.stderr
    else:
        assert done.returncode == 5, 'without calibration_interfaces.startup the swallowed signal is lost'


def test_keyed_throttle_lets_every_kind_through_and_counts_what_it_hid() -> None:
    """Twelve distinct problems in a burst are twelve lines (one throttle per call site logged six);
    repeats of one kind within the period are suppressed and counted on its next line."""
    from calibration_interfaces.throttle import KeyedThrottle

    clock = [0.0]
    throttle = KeyedThrottle(2.0, clock=lambda: clock[0])
    logged = [throttle(f'kind{i % 12}', f'problem {i}') for i in range(120)]
    assert [t for t in logged if t is not None] == [f'problem {i}' for i in range(12)]
    assert throttle.counts['kind3'] == 10
    clock[0] = 2.5
    assert throttle('kind3', 'again') == 'again (9 more like it suppressed)'
    assert throttle('kind3', 'and again') is None
    with pytest.raises(ValueError, match='period'):
        KeyedThrottle(float('nan'))


def test_frame_verdict_round_trip_and_levels() -> None:
    from calibration_interfaces.outcome import FrameStatus, decode_frame, encode_frame

    r = decode_frame(encode_frame('bad_input', 3.25, 'image.step'))
    assert (r.status, r.stamp, r.kind) == (FrameStatus.BAD_INPUT, 3.25, 'image.step')
    assert [s.level for s in FrameStatus] == [0, 1, 2]
    assert not Outcome.BAD_INPUT.informs_visibility and Outcome.FAILED.informs_visibility
    with pytest.raises(StatusFormatError, match='status'):
        decode_frame({'stamp': '1.0'})


def test_frame_verdict_carries_each_eyes_own() -> None:
    from calibration_interfaces.outcome import FrameStatus, decode_frame, encode_frame

    values = encode_frame('detected', 1.5, eyes={'left': 'no_marker', 'right': FrameStatus.DETECTED})
    assert values['eyes'] == 'left=no_marker right=detected'
    r = decode_frame(values)
    assert r.status is FrameStatus.DETECTED
    assert dict(r.eyes) == {'left': FrameStatus.NO_MARKER, 'right': FrameStatus.DETECTED}
    assert decode_frame(encode_frame('no_marker', 1.5)).eyes == {}      # a detector that did not say
    with pytest.raises(StatusFormatError, match='eyes'):
        decode_frame({**values, 'eyes': 'left detected'})
    with pytest.raises(StatusFormatError, match="'seen'"):
        decode_frame({**values, 'eyes': 'left=seen'})
    with pytest.raises(ValueError, match="'left eye'"):
        encode_frame('detected', 1.5, eyes={'left eye': 'detected'})


def test_noise_parameters_take_the_description_law_unless_set() -> None:
    from body_schema.noise import ConstantNoise, PoseDependentNoise
    from body_schema.robot import load_robot
    from calibration_interfaces.noise import NoiseSettings, PoseDependentSettings

    ur = load_robot('ur5e')
    assert ur.noise_law, 'the UR5e description carries its fitted law'
    assert NoiseSettings().build(ur) == PoseDependentNoise.for_robot(ur)          # every pdn_* negative
    assert NoiseSettings().build() == PoseDependentNoise()                         # no description: built-in
    law = NoiseSettings().build(ur, PoseDependentSettings(pdn_a_rot=1e-3))
    assert law.a_rot == 1e-3 and law.a_pos == ur.noise_law['a_pos']                # only what was set
    assert isinstance(NoiseSettings(noise_model='constant').build(ur), ConstantNoise)
    # The whole law reaches the nodes: a description's depth_ratio and stereo ratios too.
    eyed = replace(ur, noise_law={**ur.noise_law, 'depth_ratio': 4.0, 'stereo_pos': 0.2, 'stereo_rot': 1.3})
    law = NoiseSettings().build(eyed, PoseDependentSettings(pdn_a_rot=1e-3))
    assert (law.depth_ratio, law.stereo_pos, law.stereo_rot, law.a_rot) == (4.0, 0.2, 1.3, 1e-3)
    with pytest.raises(ValueError, match='unknown noise model'):
        NoiseSettings(noise_model='gaussian').build(ur)
    spec = {s.name: s for s in parameter_specs(PoseDependentSettings)}['pdn_a_pos']
    assert spec.default == -1.0 and spec.range[0] == -1.0 and 'description' in spec.description
    # Equal coefficients for both blocks and no floors: the paper's single law R = sigma^2 I.
    paper = NoiseSettings().build(ur, PoseDependentSettings(pdn_a_pos=1e-4, pdn_a_rot=1e-4, pdn_b_pos=1e-7,
                                                            pdn_b_rot=1e-7, pdn_floor_pos=0.0, pdn_floor_rot=0.0))
    assert paper == PoseDependentNoise.paper(1e-4, 1e-7)
    assert np.allclose(paper.covariance(0.3, 15.0), (1e-4 * 0.09 + 1e-7 * 900) * np.eye(6))
