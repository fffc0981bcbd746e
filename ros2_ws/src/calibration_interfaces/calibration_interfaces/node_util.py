"""Helpers every node shares (imports rclpy; the pure modules of this package do not).

* :func:`qos_profile`: the ``rclpy.qos.QoSProfile`` of a contract topic or a :class:`QosSpec`;
* :func:`descriptor` and :func:`declare_settings`: parameters declared from a settings dataclass
  (:mod:`calibration_interfaces.parameters`);
* :class:`WarnOnce`: a warning logged once per key;
* :func:`message_class`;
* :class:`RunGuard`: stops a node that shares its domain with another run;
* :func:`spin_node`: a node's ``main``.
"""
from __future__ import annotations

import importlib
import signal
from collections.abc import Callable, Mapping
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
import rclpy
from rclpy.exceptions import ParameterUninitializedException
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions, install_signal_handlers
from std_msgs.msg import String

from . import startup
from .contract import RUN_ID_TOPIC, Durability, QosSpec, Reliability, RunSettings, topic
from .parameters import ParameterSpec, parameter_specs, settings_from_parameters
from .throttle import KeyedThrottle

__all__ = ['qos_profile', 'descriptor', 'declare_settings', 'WarnOnce', 'WarnThrottled', 'message_class', 'RunGuard',
           'spin_node', 'RUN_CONFLICT_STATUS']

#: Exit status of a node stopped by :class:`RunGuard`.
RUN_CONFLICT_STATUS = 3
#: Wall seconds a node stopped by :class:`RunGuard` keeps its run id published before it exits.
LINGER_S = 5.0


def qos_profile(spec: QosSpec | str, depth: int | None = None) -> QoSProfile:
    """The QoS profile of a contract topic (by name) or of a :class:`QosSpec`.

    Parameters
    ----------
    spec : QosSpec or str
        A spec, or the name of a contract topic (its publisher's QoS).
    depth : int, optional
        Keep-last depth instead of the spec's (a subscriber's queue).

    Raises
    ------
    KeyError
        If ``spec`` names no contract topic.
    """
    s = topic(spec).qos if isinstance(spec, str) else spec
    return QoSProfile(
        depth=s.depth if depth is None else depth, history=HistoryPolicy.KEEP_LAST,
        reliability=(ReliabilityPolicy.RELIABLE if s.reliability is Reliability.RELIABLE
                     else ReliabilityPolicy.BEST_EFFORT),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if s.durability is Durability.TRANSIENT_LOCAL
                    else DurabilityPolicy.VOLATILE))


def descriptor(description: str, range: tuple[float, float] | None = None, *,  # noqa: A002
               integer: bool = False, read_only: bool = False) -> ParameterDescriptor:
    """A parameter descriptor with a description and, optionally, an inclusive range."""
    d = ParameterDescriptor(description=description, read_only=read_only)
    if range is not None:
        if integer:
            d.integer_range = [IntegerRange(from_value=int(range[0]), to_value=int(range[1]))]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(range[0]), to_value=float(range[1]))]
    return d


_ARRAY_TYPES = {'string': Parameter.Type.STRING_ARRAY, 'double': Parameter.Type.DOUBLE_ARRAY,
                'integer': Parameter.Type.INTEGER_ARRAY}


def _declare(node: Node, spec: ParameterSpec, default: Any, read_only: bool) -> Any:
    desc = descriptor(spec.full_description, spec.range,
                      integer=isinstance(default, int) and not isinstance(default, bool), read_only=read_only)
    if isinstance(default, tuple) and not default:
        # rclpy cannot type an empty list: declare the array type without a value (unset = empty).
        node.declare_parameter(spec.name, _ARRAY_TYPES[spec.array_type], desc)
        try:
            return tuple(node.get_parameter(spec.name).value or ())
        except ParameterUninitializedException:
            return ()
    value = list(default) if isinstance(default, tuple) else default
    return node.declare_parameter(spec.name, value, desc).value


def declare_settings(node: Node, cls: type, *, defaults: Mapping[str, Any] | None = None,
                     read_only: bool = False, **fixed: Any) -> Any:
    """Declare the parameters of settings dataclass ``cls`` on ``node``; return the settings.

    Parameters
    ----------
    node : Node
    cls : type
        A dataclass whose parameter fields are declared with
        :func:`calibration_interfaces.parameters.setting`.
    defaults : mapping, optional
        Defaults that depend on the robot, by parameter name (the field's description says so).
    read_only : bool
        Declare the parameters read-only (they are read once at start).
    **fixed
        Values of fields that are not parameters.

    Raises
    ------
    ValueError
        If a string parameter is not one of its choices (or the dataclass rejects a value).
    """
    defaults = defaults or {}
    values = {s.name: _declare(node, s, defaults.get(s.name, s.default), read_only)
              for s in parameter_specs(cls)}
    return settings_from_parameters(cls, values, **fixed)


class WarnOnce:
    """Logs a warning the first time a key is seen (a malformed stream warns once, not per message).

    Parameters
    ----------
    node : Node
        Whose logger is used.
    """

    def __init__(self, node: Node) -> None:
        self._logger = node.get_logger()
        self.keys: set[str] = set()

    def __call__(self, key: str, text: str) -> None:
        if key not in self.keys:
            self.keys.add(key)
            self._logger.warning(text)


class WarnThrottled:
    """Logs warnings throttled per kind of problem (:class:`~calibration_interfaces.throttle.KeyedThrottle`):
    the first of each key at once, then one per ``period`` seconds with the count suppressed.

    Parameters
    ----------
    node : Node
        Whose logger is used.
    period : float
        Seconds between two warnings of one key.
    """

    def __init__(self, node: Node, period: float = 2.0) -> None:
        self._node = node
        self.throttle = KeyedThrottle(period)

    def __call__(self, key: str, text: str) -> None:
        out = self.throttle(key, text)
        if out is not None:
            self._node.get_logger().warning(out)   # the node's logger at the time (tests replace it)


def message_class(type_name: str) -> type:
    """The Python class of ``pkg/msg/Type``.

    Raises
    ------
    ImportError
        If the package or type is not installed.
    """
    pkg, _, name = type_name.partition('/msg/')
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError) as exc:
        raise ImportError(f'message type {type_name!r} is not installed: {exc}') from exc


class RunGuard:
    """Latches the node's run id on ``/calibration/run_id``; another id there stops the node.

    Two graphs on one ROS domain would otherwise mix their messages silently (joint states of one
    robot paired with hand poses of the other). On the first foreign id, or a second node of this
    node's name (a graph started without run ids), the guard logs an error, records what it saw
    in :attr:`conflict`, destroys the node's other subscriptions and timers (it takes no more
    input and drives nothing) and shuts the context down :data:`LINGER_S` later, once its own id
    has reached the other run; :func:`spin_node` then exits with :data:`RUN_CONFLICT_STATUS`.

    Parameters
    ----------
    node : Node
    run_id : str
        Non-empty id of this node's run.
    period : float
        Wall seconds between two looks at the graph for a node of the same name.
    """

    def __init__(self, node: Node, run_id: str, period: float = 1.0) -> None:
        if not run_id:
            raise ValueError('RunGuard needs a non-empty run id')
        self.node, self.run_id = node, run_id
        self.conflict: str | None = None
        self.domain_id = node.context.get_domain_id()
        qos = qos_profile(RUN_ID_TOPIC)
        self._pub = node.create_publisher(String, RUN_ID_TOPIC, qos)
        self._pub.publish(String(data=run_id))
        self._sub = node.create_subscription(String, RUN_ID_TOPIC, self._on_run_id, qos)
        # A graph started without run ids (another launcher, by hand) shows as a second node of
        # this node's name; the graph is polled on a wall-clock timer (sim time may stand still).
        self._timer = node.create_timer(period, self._check_names, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _on_run_id(self, msg: String) -> None:
        if msg.data != self.run_id:
            self._stop(f'another run ({msg.data!r})')

    def _check_names(self) -> None:
        me = (self.node.get_name(), self.node.get_namespace())
        if self.node.get_node_names_and_namespaces().count(me) > 1:
            self._stop(f'another node named {self.node.get_fully_qualified_name()!r}')

    def _stop(self, what: str) -> None:
        if self.conflict is not None:
            return
        self.conflict = what
        self.node.get_logger().error(
            f'{what} is on ROS_DOMAIN_ID {self.domain_id}; this node of run {self.run_id!r} stops rather '
            'than mix the two runs\' messages (give each run its own domain)')
        # Stop taking input now, but linger before shutting the context down: our latched id must
        # reach the other run too (a reader that matched us later would otherwise find it gone),
        # so that both runs stop, not only the one that noticed first.
        for sub in list(self.node.subscriptions):
            if sub is not self._sub:
                self.node.destroy_subscription(sub)
        for timer in list(self.node.timers):
            if timer is not self._timer:
                self.node.destroy_timer(timer)
        self._timer.cancel()
        self._linger = self.node.create_timer(LINGER_S, self.node.context.try_shutdown,
                                              clock=Clock(clock_type=ClockType.STEADY_TIME))


def spin_node(make_node: Callable[[], Node], args: list[str] | None = None,
              run: Callable[[Node], None] | None = None) -> None:
    """A node executable's ``main``: init, build, spin until Ctrl-C or shutdown, destroy, shut down.

    ``run(node)`` drives the node (default ``rclpy.spin``: until shutdown); a node that ends by
    itself passes its own loop. SIGINT and SIGTERM end it at any moment after this is called:
    while ``make_node`` builds the node (seconds for some) a signal is only remembered, so the
    node is built whole and then destroyed without spinning (a KeyboardInterrupt raised inside
    its constructor would lose the node, and with it the estimator's export); after that,
    rclpy's handlers shut the context down. ``destroy_node`` runs in every case, so a node can
    finish its files, exports or servers there. The node declares ``run_id``
    (:class:`~calibration_interfaces.contract.RunSettings`); a non-empty one is guarded by
    :class:`RunGuard`.

    Raises
    ------
    SystemExit
        With :data:`RUN_CONFLICT_STATUS` when the node stopped on another run's id.
    """
    # A signal during the imports whose KeyboardInterrupt Python swallowed (see .startup): stop now.
    received: list[int] = list(startup.RECEIVED)
    for signum in (signal.SIGINT, signal.SIGTERM):
        # Also undoes an inherited SIG_IGN (a background job of a script starts with SIGINT ignored).
        signal.signal(signum, lambda s, _frame: received.append(s))
    if received:
        return
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    guard = None
    try:
        node = make_node()
        run_id = declare_settings(node, RunSettings, read_only=True).run_id
        if run_id:
            guard = RunGuard(node, run_id)
        # From now on a signal shuts the context down (and still reaches the recorder above).
        install_signal_handlers(SignalHandlerOptions.ALL)
        if not received:
            (rclpy.spin if run is None else run)(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except _rclpy.RCLError:
        # A signal's shutdown between rclpy.spin's context check and the executor building its
        # wait set ("failed to initialize wait set: the given context is not valid") is the same
        # stop, seen once under load in tests/test_node_signals.py; anything else is a failure.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if guard is not None and guard.conflict is not None:
        raise SystemExit(RUN_CONFLICT_STATUS)
