"""ObservationPairer: which observations become EKF updates (pure, no rclpy)."""
import numpy as np
import pytest

from body_schema import load_robot, sampling
from body_schema.noise import ConstantNoise
from dh_estimator.estimator import EstimatorSettings, OnlineEstimator
from dh_estimator.pairing import MessageError, MessageFeeder, ObservationPairer, PairingSettings

R = ConstantNoise().covariance(0.0, 45.0)


@pytest.fixture
def setup():
    model = load_robot('icub_right_arm')
    est = OnlineEstimator(model, model.dh, sampling.initial_covariance(7, 0.046, np.radians(54)),
                          EstimatorSettings(iterations=1))
    return model, est, ObservationPairer(est, PairingSettings(static_window=0.1))


def _rest(pairer, q, t0, t1, dt=0.01):
    out = []
    for t in np.arange(t0, t1 + 1e-9, dt):
        out += pairer.joint_state(float(t), q)
    return out


def test_only_observations_at_the_commanded_target_are_attempts(setup):
    model, est, pairer = setup
    q = np.radians([-30, 30, 0, 45, 0, 0, 0])
    pose = model.forward_kinematics(q)
    _rest(pairer, q, 0.0, 1.0)
    assert pairer.hand_pose(0.5, pose, R) == []              # no command yet: not an attempt
    pairer.command(q + 0.1)
    assert pairer.hand_pose(0.6, pose, R) == []              # elsewhere than the target
    pairer.command(q)
    [a] = pairer.hand_pose(0.7, pose, R)
    assert a.outcome == 'accepted' and np.allclose(a.joints, q)
    assert est.counters['updates'] == 1
    [b] = pairer.hand_pose(0.8, pose, R)                     # same rest, second image
    assert b.outcome == 'duplicate' and est.counters['updates'] == 1


def test_an_image_waits_for_the_joint_states_of_its_stamp(setup):
    model, est, pairer = setup
    q = np.radians([-30, 30, 0, 45, 0, 0, 0])
    pairer.command(q)
    _rest(pairer, q, 0.0, 0.5)
    assert pairer.hand_pose(0.55, model.forward_kinematics(q), R) == []   # stamp after the newest state
    attempts = _rest(pairer, q, 0.51, 0.6)
    assert [a.outcome for a in attempts] == ['accepted']


def test_moving_arm_and_uncovered_stamps_are_reported_not_used(setup):
    model, est, pairer = setup
    q = np.radians([-30, 30, 0, 45, 0, 0, 0])
    pairer.command(q)
    for i, t in enumerate(np.arange(0.0, 0.5, 0.01)):        # approaching the target until 0.45 s
        pairer.joint_state(float(t), q + max(0.0, 0.45 - t) * 0.01)
    [a] = pairer.hand_pose(0.46, model.forward_kinematics(q), R)
    assert a.outcome == 'moving'
    pairer.buffer.add(20.0, q)                               # horizon drops the old samples
    [b] = pairer.hand_pose(5.0, model.forward_kinematics(q), R)
    assert b.outcome == 'dropped' and b.joints is None
    assert est.counters['updates'] == 0


class _Msg:
    """A message-shaped object (what rclpy and the bag decoder both give)."""

    def __init__(self, **fields):
        self.__dict__.update(fields)


def _stamp(t):
    return _Msg(sec=int(t), nanosec=int(round((t % 1) * 1e9)))


def test_feeder_reorders_joints_and_refuses_bad_messages(setup):
    model, est, pairer = setup
    feeder = MessageFeeder(pairer, model.joint_names)
    q = np.radians([-30, 30, 0, 45, 0, 0, 0])
    order = list(reversed(model.joint_names))
    for t in np.arange(0.0, 1.0, 0.01):
        feeder.feed('/joint_states', _Msg(name=order, position=list(q[::-1]), header=_Msg(stamp=_stamp(t))))
    np.testing.assert_allclose(pairer.buffer.latest[1], q)
    feeder.feed('/arm/command', _Msg(joint_names=order, points=[_Msg(positions=list(q[::-1]))]))
    np.testing.assert_allclose(pairer.target, q)
    with pytest.raises(MessageError, match=r"lacks joints \['r_elbow'\]") as e:
        feeder.joint_state(_Msg(name=[n for n in order if n != 'r_elbow'], position=[0.0] * 6,
                                header=_Msg(stamp=_stamp(1.0))))
    assert e.value.key == 'names' and e.value.once
    with pytest.raises(MessageError, match='non-finite') as e:
        feeder.joint_state(_Msg(name=order, position=[np.nan] * 7, header=_Msg(stamp=_stamp(1.0))))
    assert not e.value.once
    with pytest.raises(ValueError, match="not '/markers'"):
        feeder.feed('/markers', None)


def test_feeder_constant_noise_replaces_the_message_covariance(setup):
    from calibration_interfaces.messages import matrix_to_pose_msg
    from geometry_msgs.msg import PoseWithCovarianceStamped

    model, est, pairer = setup
    q = np.radians([-30, 30, 0, 45, 0, 0, 0])
    seen = []
    pairer.hand_pose = lambda t, pose, R, now=None: seen.append(R) or []     # observe what the feeder passes on
    msg = PoseWithCovarianceStamped()
    msg.pose.pose = matrix_to_pose_msg(model.forward_kinematics(q))
    msg.pose.covariance = (np.eye(6) * 3.0).ravel().tolist()
    MessageFeeder(pairer, model.joint_names).hand_pose(msg)
    MessageFeeder(pairer, model.joint_names, ConstantNoise()).hand_pose(msg)
    np.testing.assert_allclose(seen[0], np.eye(6) * 3.0)
    np.testing.assert_allclose(seen[1], R)


def _js(order, q, t):
    return _Msg(name=order, position=list(q), header=_Msg(stamp=_stamp(t)))


def _hp(pose, t):
    from calibration_interfaces.messages import matrix_to_pose_msg
    from geometry_msgs.msg import PoseWithCovarianceStamped

    msg = PoseWithCovarianceStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(t), int(round((t % 1) * 1e9))
    msg.pose.pose = matrix_to_pose_msg(pose)
    msg.pose.covariance = R.ravel().tolist()
    return msg


def _rest_fed(feeder, q, t0, t1, dt=0.02):
    """Joint states resting at ``q``, each received at its own stamp."""
    out = []
    for t in np.arange(t0, t1 + 1e-9, dt):
        out += feeder.joint_state(_js(feeder.joint_names, q, float(t)), now=float(t))
    return out


def test_one_joint_state_stamped_in_the_future_does_not_stall_the_pairing(setup):
    # On main the stray stamp became the newest sample: every later real one was thrown away and
    # each following attempt was dropped ('no joint state covers').
    model, est, pairer = setup
    feeder = MessageFeeder(pairer, model.joint_names)
    configs = [np.radians([-30, 30, 0, 45, 0, 0, 0]), np.radians([-20, 40, 10, 50, 0, 10, 0]),
               np.radians([-40, 20, -10, 60, 10, 0, 5])]
    outcomes = []
    for k, q in enumerate(configs):
        t0 = 2.0 * k
        feeder.command(_Msg(joint_names=model.joint_names, points=[_Msg(positions=list(q))]))
        _rest_fed(feeder, q, t0, t0 + 0.3)
        if k == 0:
            with pytest.raises(MessageError, match=r'/joint_states stamp 1000\.000 s .* ahead .*\(1 so far\)') as e:
                feeder.joint_state(_js(model.joint_names, q, 1000.0), now=t0 + 0.3)
            assert e.value.throttled and not e.value.once
        outcomes += feeder.hand_pose(_hp(model.forward_kinematics(q), t0 + 0.25), now=t0 + 0.3)
        outcomes += _rest_fed(feeder, q, t0 + 0.32, t0 + 0.5)
    assert [a.outcome for a in outcomes] == ['accepted'] * 3
    assert pairer.counters['future_joint_states'] == 1 and est.counters['updates'] == 3


@pytest.fixture
def commanded(setup):
    """(model, pairer, feeder, q): the arm commanded to ``q``."""
    model, est, pairer = setup
    q = np.radians([-30, 30, 0, 45, 0, 0, 0])
    pairer.command(q)
    return model, pairer, MessageFeeder(pairer, model.joint_names), q


def test_a_hand_pose_stamped_in_the_future_is_refused_and_counted_not_kept_pending(commanded):
    model, pairer, feeder, q = commanded
    _rest_fed(feeder, q, 0.0, 0.3)
    for n in (1, 2):
        with pytest.raises(MessageError, match=rf'/hand_pose stamp 500\.000 s .* ahead .*\({n} so far\)'):
            feeder.hand_pose(_hp(model.forward_kinematics(q), 500.0), now=0.3)
    assert pairer.counters['future_hand_poses'] == 2 and pairer._pending == []


def test_images_that_never_get_their_joint_states_are_reported_dropped(commanded):
    model, pairer, feeder, q = commanded
    _rest(pairer, q, 0.0, 0.3)
    pose = model.forward_kinematics(q)
    out = []
    for k in range(pairer.settings.max_pending + 2):          # joint states stopped at 0.3 s
        out += pairer.hand_pose(0.5 + 0.1 * k, pose, R)
    assert [a.outcome for a in out] == ['dropped'] * 2
    assert [a.stamp for a in out] == pytest.approx([0.5, 0.6]) and 'newer images' in out[0].message
    assert pairer.counters['pending_dropped'] == 2


def test_the_clock_stepping_back_restarts_the_pairing_on_the_new_timeline(commanded):
    model, pairer, feeder, q = commanded
    _rest_fed(feeder, q, 100.0, 100.3)
    assert feeder.hand_pose(_hp(model.forward_kinematics(q), 100.6), now=100.3) == []   # waits
    # The simulator restarts at 0: the waiting image belongs to the old timeline.
    [gone] = _rest_fed(feeder, q, 0.0, 0.0)
    assert gone.outcome == 'dropped' and 'stepped back' in gone.message
    _rest_fed(feeder, q, 0.02, 0.3)
    [a] = feeder.hand_pose(_hp(model.forward_kinematics(q), 0.25), now=0.3)
    assert a.outcome == 'accepted' and pairer.counters['clock_resets'] == 1
