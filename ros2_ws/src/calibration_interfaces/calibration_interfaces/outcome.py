"""One vocabulary for what became of an observation or an iteration, at every stage (no rclpy).

The estimator decides ACCEPTED / REJECTED / DUPLICATE for an observation it was offered; its
pairing stage adds MOVING / INVALID / DROPPED; the selector's loop adds FAILED / UNREACHABLE /
TIMEOUT for an iteration that produced no estimator outcome. Every stage uses these members, the
progress records and the bag hold their values.

The estimator publishes one ``diagnostic_msgs/DiagnosticStatus`` per attempt on
``/body_schema/update_status``; its key/value pairs are named by :class:`StatusKey` and
encoded by :func:`encode_status` / decoded by :func:`decode_status`, so the selector and the
offline evaluation read them through this module rather than through a string convention.
"""
from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['Outcome', 'StatusKey', 'UpdateStatus', 'encode_status', 'decode_status', 'StatusFormatError']


class Outcome(enum.StrEnum):
    """What became of one observation (estimator, pairing) or one iteration (selector loop)."""

    ACCEPTED = 'accepted'         # estimator: EKF updated
    REJECTED = 'rejected'         # estimator: outside the Mahalanobis gate; state unchanged
    DUPLICATE = 'duplicate'       # estimator: same configuration as the previous attempt
    MOVING = 'moving'             # pairing: the arm was not still at the image stamp
    INVALID = 'invalid'           # pairing: the filter refused the input (NaN, bad shape)
    DROPPED = 'dropped'           # pairing: no joint state covers the image stamp
    FAILED = 'failed'             # loop: no marker detected after settling
    UNREACHABLE = 'unreachable'   # loop: the target was not reached in time
    TIMEOUT = 'timeout'           # loop: settled and seen, but no estimator outcome in time

    @property
    def updated(self) -> bool:
        """Whether the estimator evaluated the observation (accepted or gated out)."""
        return self in (Outcome.ACCEPTED, Outcome.REJECTED)


class StatusKey(enum.StrEnum):
    """Keys of the estimator's ``/body_schema/update_status`` DiagnosticStatus values."""

    OUTCOME = 'outcome'           # an Outcome value
    STAMP = 'stamp'               # image stamp [s], '%.9f'
    JOINTS = 'joints'             # joint positions [rad] used for the update, space separated
    MAHALANOBIS = 'mahalanobis'   # Mahalanobis distance of the innovation
    UPDATE_S = 'update_s'         # wall seconds of the last EKF update
    UPDATES = 'updates'           # counters of the estimator so far: accepted updates,
    REJECTED = 'rejected'         # ... gated-out observations,
    DUPLICATES = 'duplicates'     # ... repeated configurations


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


def encode_status(outcome: Outcome, stamp: float, joints: ArrayLike | None, mahalanobis: float,
                  update_seconds: float, counters: Mapping[str, int]) -> dict[str, str]:
    """The key/value strings of one update status (the DiagnosticStatus ``values``)."""
    q = np.asarray([] if joints is None else joints, dtype=float)
    kv = {StatusKey.OUTCOME: Outcome(outcome).value, StatusKey.STAMP: f'{stamp:.9f}',
          StatusKey.JOINTS: ' '.join(f'{v:.9f}' for v in q),
          StatusKey.MAHALANOBIS: f'{mahalanobis:.6f}', StatusKey.UPDATE_S: f'{update_seconds:.6f}',
          **{k: str(int(counters[k.value])) for k in _COUNTERS}}
    return {k.value: v for k, v in kv.items()}


def decode_status(values: Mapping[str, str]) -> UpdateStatus:
    """Parse the key/value strings written by :func:`encode_status`.

    Raises
    ------
    StatusFormatError
        If a key is missing or a value does not parse; the message names it.
    """
    try:
        return UpdateStatus(
            outcome=Outcome(values[StatusKey.OUTCOME]), stamp=float(values[StatusKey.STAMP]),
            joints=np.array([float(v) for v in values[StatusKey.JOINTS].split()], dtype=float),
            mahalanobis=float(values[StatusKey.MAHALANOBIS]),
            update_seconds=float(values[StatusKey.UPDATE_S]),
            counters={k.value: int(values[k]) for k in _COUNTERS})
    except KeyError as exc:
        raise StatusFormatError(f'update status lacks key {exc.args[0]!r}; has {sorted(values)}') from None
    except ValueError as exc:
        raise StatusFormatError(f'update status {dict(values)!r} does not parse: {exc}') from exc
