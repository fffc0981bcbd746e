"""One vocabulary for what became of an observation or an iteration, at every stage (no rclpy).

The estimator decides ACCEPTED / REJECTED / DUPLICATE for an observation it was offered; its
pairing stage adds MOVING / INVALID / DROPPED; the selector's loop adds FAILED / UNREACHABLE /
TIMEOUT / BAD_INPUT for an iteration that produced no estimator outcome. Every stage uses these members, the
progress records and the bag hold their values.

The estimator publishes one ``diagnostic_msgs/DiagnosticStatus`` per attempt on
``/body_schema/update_status``; its key/value pairs are named by :class:`StatusKey` and
encoded by :func:`encode_status` / decoded by :func:`decode_status`, so the selector and the
offline evaluation read them through this module rather than through a string convention.

The simulator checks the real arm for contacts with the obstacles and itself while it moves and
publishes what it has seen on ``/diagnostics`` too (one status named :data:`CONTACT_DIAGNOSTIC`,
keys :class:`ContactKey`, :func:`encode_contacts` / :func:`decode_contacts`): level OK while there
was none, ERROR after the first.

The detector judges every camera frame (:class:`FrameStatus`: the hand detected, no marker, or an
input it cannot judge) and publishes that verdict per frame on ``/diagnostics``
(``diagnostic_msgs/DiagnosticArray``, one status per eye named :data:`DETECTOR_DIAGNOSTIC`, keys
:class:`FrameKey`, written by :func:`encode_frame` and read by :func:`decode_frame`): only a
``no_marker`` frame is evidence that the hand was not visible.
"""
from __future__ import annotations

import enum
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['Outcome', 'StatusKey', 'UpdateStatus', 'encode_status', 'decode_status', 'StatusFormatError',
           'recorded_statuses',
           'FrameStatus', 'FrameKey', 'FrameReport', 'DETECTOR_DIAGNOSTIC', 'encode_frame', 'decode_frame',
           'CONTACT_DIAGNOSTIC', 'ContactKey', 'ContactStatus', 'encode_contacts', 'decode_contacts']

T = TypeVar('T')


class Outcome(enum.StrEnum):
    """What became of one observation (estimator, pairing) or one iteration (selector loop)."""

    ACCEPTED = 'accepted'         # estimator: the estimate used it
    OUTLIER = 'outlier'           # estimator (MAP): used under the robust loss, but its residual at the
                                  # solution is beyond the outlier bound (counted and logged)
    REJECTED = 'rejected'         # estimator (EKF): outside the Mahalanobis gate; state unchanged
    DUPLICATE = 'duplicate'       # estimator: same configuration as the previous attempt
    MOVING = 'moving'             # pairing: the arm was not still at the image stamp
    INVALID = 'invalid'           # pairing: the filter refused the input (NaN, bad shape)
    DROPPED = 'dropped'           # pairing: no joint state covers the image stamp
    FAILED = 'failed'             # loop: no marker detected after settling
    UNREACHABLE = 'unreachable'   # loop: the target was not reached in time
    TIMEOUT = 'timeout'           # loop: settled and seen, but no estimator outcome in time
    BAD_INPUT = 'bad_input'       # loop: after settling, only frames the detector could not judge
                                  # (bad image or camera_info): says nothing about visibility

    @property
    def updated(self) -> bool:
        """Whether the estimator evaluated the observation (accepted, outlier or gated out)."""
        return self in (Outcome.ACCEPTED, Outcome.OUTLIER, Outcome.REJECTED)

    @property
    def informs_visibility(self) -> bool:
        """Whether the iteration may teach the occlusion model (a frame was judged at the reached
        configuration): not for an unreached target nor for frames that were bad input."""
        return self not in (Outcome.UNREACHABLE, Outcome.BAD_INPUT)


class StatusKey(enum.StrEnum):
    """Keys of the estimator's ``/body_schema/update_status`` DiagnosticStatus values."""

    OUTCOME = 'outcome'           # an Outcome value
    STAMP = 'stamp'               # image stamp [s], '%.9f'
    JOINTS = 'joints'             # joint positions [rad] used for the update, space separated
    MAHALANOBIS = 'mahalanobis'   # Mahalanobis distance of the innovation
    UPDATE_S = 'update_s'         # wall seconds of the last EKF update
    UPDATES = 'updates'           # counters of the estimator so far: accepted updates,
    REJECTED = 'rejected'         # ... gated-out observations,
    DUPLICATES = 'duplicates'     # ... repeated configurations,
    OUTLIERS = 'outliers'         # ... observations beyond the outlier bound (MAP: at the current solution),
    CHANGES = 'changes'           # ... body changes detected (MAP)


class StatusFormatError(ValueError):
    """An update status lacks a key or holds a value that does not parse."""


@dataclass(frozen=True)
class UpdateStatus:
    """One estimator attempt as carried by ``/body_schema/update_status``.

    Attributes
    ----------
    outcome : Outcome
    stamp : float
        Image stamp [s].
    joints : ndarray, shape (L,)
        Joint positions of the attempt [rad]; empty when unknown.
    mahalanobis : float
    update_seconds : float
    counters : dict of str to int
        ``updates``, ``rejected``, ``duplicates``.
    """

    outcome: Outcome
    stamp: float
    joints: NDArray[np.float64]
    mahalanobis: float
    update_seconds: float
    counters: Mapping[str, int]


_COUNTERS = (StatusKey.UPDATES, StatusKey.REJECTED, StatusKey.DUPLICATES)
#: Counters added with the MAP estimator: absent from older bags, read as 0 there.
_NEWER_COUNTERS = (StatusKey.OUTLIERS, StatusKey.CHANGES)


def encode_status(outcome: Outcome, stamp: float, joints: ArrayLike | None, mahalanobis: float,
                  update_seconds: float, counters: Mapping[str, int]) -> dict[str, str]:
    """The key/value strings of one update status (the DiagnosticStatus ``values``)."""
    q = np.asarray([] if joints is None else joints, dtype=float)
    kv = {StatusKey.OUTCOME: Outcome(outcome).value, StatusKey.STAMP: f'{stamp:.9f}',
          StatusKey.JOINTS: ' '.join(f'{v:.9f}' for v in q),
          StatusKey.MAHALANOBIS: f'{mahalanobis:.6f}', StatusKey.UPDATE_S: f'{update_seconds:.6f}',
          **{k: str(int(counters[k.value])) for k in _COUNTERS},
          **{k: str(int(counters.get(k.value, 0))) for k in _NEWER_COUNTERS}}
    return {k.value: v for k, v in kv.items()}


def decode_status(values: Mapping[str, str]) -> UpdateStatus:
    """Parse the key/value strings written by :func:`encode_status`.

    Raises
    ------
    StatusFormatError
        If a key is missing or a value does not parse; the message names it.
    """
    return _parsed('update status', values, lambda: UpdateStatus(
        outcome=Outcome(values[StatusKey.OUTCOME]), stamp=float(values[StatusKey.STAMP]),
        joints=np.array([float(v) for v in values[StatusKey.JOINTS].split()], dtype=float),
        mahalanobis=float(values[StatusKey.MAHALANOBIS]),
        update_seconds=float(values[StatusKey.UPDATE_S]),
        counters={**{k.value: int(values[k]) for k in _COUNTERS},
                  **{k.value: int(values.get(k, 0)) for k in _NEWER_COUNTERS}}))


def recorded_statuses(bag: str | os.PathLike[str], skip_malformed: bool = False) -> Iterator[UpdateStatus]:
    """The estimator's verdicts recorded on ``/body_schema/update_status`` in a bag, in order.

    Parameters
    ----------
    bag : path
        An MCAP file (read with :func:`calibration_interfaces.mcap_reader.read_messages`, so a
        bag cut by a crash is read up to its last complete record).
    skip_malformed : bool
        Leave out a status that does not decode instead of raising.

    Raises
    ------
    StatusFormatError
        If a status does not decode and ``skip_malformed`` is false.
    """
    from . import mcap_reader          # the bag reader only for those who read bags

    for _topic, _t, msg in mcap_reader.read_messages(bag, ['/body_schema/update_status']):
        try:
            yield decode_status({v.key: v.value for v in msg.values})
        except StatusFormatError:
            if not skip_malformed:
                raise


class FrameStatus(enum.StrEnum):
    """The detector's verdict on one frame (one eye, or a stereo pair)."""

    DETECTED = 'detected'         # the hand was found (/hand_pose published)
    NO_MARKER = 'no_marker'       # a valid frame without an accepted marker: the hand not visible
    BAD_INPUT = 'bad_input'       # the frame or its camera_info could not be judged: no /markers

    @property
    def level(self) -> int:
        """The ``diagnostic_msgs/DiagnosticStatus`` level: OK (0), WARN (1) or ERROR (2)."""
        return {FrameStatus.DETECTED: 0, FrameStatus.NO_MARKER: 1, FrameStatus.BAD_INPUT: 2}[self]


class FrameKey(enum.StrEnum):
    """Keys of the detector's per-frame DiagnosticStatus values."""

    STATUS = 'status'             # a FrameStatus value
    STAMP = 'stamp'               # image stamp [s], '%.9f'
    KIND = 'kind'                 # what was bad (e.g. 'image.encoding', 'camera_info.D'); '' otherwise
    EYES = 'eyes'                 # each eye's own verdict, 'left=detected right=no_marker' (absent: unknown)


#: ``name`` of the detector's per-frame DiagnosticStatus (``hardware_id`` is the eye).
DETECTOR_DIAGNOSTIC = 'marker_detector'


@dataclass(frozen=True)
class FrameReport:
    """One frame's verdict as carried by ``/diagnostics``.

    Attributes
    ----------
    status : FrameStatus
    stamp : float
        Image stamp [s].
    kind : str
        What was bad, for ``bad_input``; empty otherwise.
    eyes : dict of str to FrameStatus
        Each eye's own verdict (a stereo pair's status is ``detected`` when either eye saw the
        hand); empty when the detector did not say (a bag recorded before the key existed).
    """

    status: FrameStatus
    stamp: float
    kind: str = ''
    eyes: Mapping[str, FrameStatus] = field(default_factory=dict)


def encode_frame(status: FrameStatus | str, stamp: float, kind: str = '',
                 eyes: Mapping[str, FrameStatus | str] | None = None) -> dict[str, str]:
    """The key/value strings of one frame verdict (the DiagnosticStatus ``values``); ``eyes``, each
    eye's own verdict, is written when given.

    Raises
    ------
    ValueError
        If an eye's name is empty or holds a space or '=' (the value's separators).
    """
    values = {FrameKey.STATUS.value: FrameStatus(status).value, FrameKey.STAMP.value: f'{stamp:.9f}',
              FrameKey.KIND.value: kind}
    if eyes is not None:
        for eye in eyes:
            if not eye or ' ' in eye or '=' in eye:
                raise ValueError(f"eye name {eye!r} must be non-empty, without spaces or '='")
        values[FrameKey.EYES.value] = ' '.join(f'{eye}={FrameStatus(v).value}' for eye, v in eyes.items())
    return values


def decode_frame(values: Mapping[str, str]) -> FrameReport:
    """The frame verdict :func:`encode_frame` wrote; a :class:`StatusFormatError` names a missing
    key or a value that does not parse."""
    def eyes() -> dict[str, FrameStatus]:
        pairs = [item.partition('=') for item in values.get(FrameKey.EYES, '').split()]
        if any(not eye or not sep for eye, sep, _ in pairs):
            raise ValueError(f"eyes must be 'name=status' items, got {values[FrameKey.EYES]!r}")
        return {eye: FrameStatus(v) for eye, _, v in pairs}

    return _parsed('frame status', values, lambda: FrameReport(
        FrameStatus(values[FrameKey.STATUS]), float(values[FrameKey.STAMP]), values.get(FrameKey.KIND, ''), eyes()))


def _parsed(what: str, values: Mapping[str, str], build: Callable[[], T]) -> T:
    """``build()``, with a missing key or a value that does not parse as a StatusFormatError."""
    try:
        return build()
    except KeyError as exc:
        raise StatusFormatError(f'{what} lacks key {exc.args[0]!r}; has {sorted(values)}') from None
    except ValueError as exc:
        raise StatusFormatError(f'{what} {dict(values)!r} does not parse: {exc}') from exc


#: ``name`` of the simulator's contact DiagnosticStatus (``hardware_id`` is the robot's name).
CONTACT_DIAGNOSTIC = 'icub_sim/contacts'


class ContactKey(enum.StrEnum):
    """Keys of the simulator's contact DiagnosticStatus values."""

    CHECKS = 'checks'                       # configurations checked so far
    CONTACTS = 'contacts'                   # of them, configurations with a contact
    PAIRS = 'pairs'                         # 'a:b=n;c:d=m': configurations in contact per body pair
    MIN_CLEARANCE = 'min_clearance_m'       # least distance arm - static body seen [m], '%.6f' ('inf': none)
    MIN_CLEARANCE_PAIR = 'min_clearance_pair'   # 'link:body'
    STAMP = 'stamp'                         # sim time of the report [s]


@dataclass(frozen=True)
class ContactStatus:
    """The simulator's contact report as carried by ``/diagnostics``."""

    checks: int
    contacts: int
    pairs: dict[tuple[str, str], int]
    min_clearance: float
    min_clearance_pair: tuple[str, str]
    stamp: float

    @property
    def level(self) -> int:
        """OK (0) without contacts, ERROR (2) with."""
        return 0 if self.contacts == 0 else 2


def encode_contacts(checks: int, contacts: int, pairs: Mapping[tuple[str, str], int], min_clearance: float,
                    min_clearance_pair: tuple[str, str], stamp: float) -> dict[str, str]:
    """The key/value strings of a contact report."""
    return {ContactKey.CHECKS.value: str(int(checks)), ContactKey.CONTACTS.value: str(int(contacts)),
            ContactKey.PAIRS.value: ';'.join(f'{a}:{b}={n}' for (a, b), n in sorted(pairs.items())),
            ContactKey.MIN_CLEARANCE.value: f'{min_clearance:.6f}',
            ContactKey.MIN_CLEARANCE_PAIR.value: ':'.join(min_clearance_pair),
            ContactKey.STAMP.value: f'{stamp:.9f}'}


def decode_contacts(values: Mapping[str, str]) -> ContactStatus:
    """The report :func:`encode_contacts` wrote; a :class:`StatusFormatError` names what is wrong."""
    def pairs(text: str) -> dict[tuple[str, str], int]:
        out = {}
        for item in filter(None, text.split(';')):
            names, _, n = item.rpartition('=')
            a, _, b = names.partition(':')
            out[(a, b)] = int(n)
        return out

    return _parsed('contact status', values, lambda: ContactStatus(
        int(values[ContactKey.CHECKS]), int(values[ContactKey.CONTACTS]), pairs(values[ContactKey.PAIRS]),
        float(values[ContactKey.MIN_CLEARANCE]), tuple(values[ContactKey.MIN_CLEARANCE_PAIR].split(':', 1)),
        float(values[ContactKey.STAMP])))
