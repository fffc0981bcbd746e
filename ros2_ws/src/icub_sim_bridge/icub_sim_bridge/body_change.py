"""A change of the simulated body, written as text (pure; no rclpy).

The paper's motivation is a body schema that follows a body that changes (wear, a bent link, a
tool). The simulator applies such a change mid-run from a spec like

    r_wrist_prosup.d+0.010 r_shoulder_yaw.offset+3

(joint name, DH column ``a`` / ``d`` [m] or ``alpha`` / ``offset`` [deg], signed increment;
several terms separated by spaces or commas).
"""
from __future__ import annotations

import re
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = ['BodyChangeError', 'parse_body_change']

_COLUMNS = {'a': 0, 'd': 1, 'alpha': 2, 'offset': 3}
_TERM = re.compile(r'^(?P<joint>[A-Za-z0-9_]+)\.(?P<col>a|d|alpha|offset)(?P<delta>[+-][0-9.eE+-]+)$')


class BodyChangeError(ValueError):
    """A body-change spec that does not parse; the message names the bad term."""


def parse_body_change(spec: str, joint_names: Sequence[str]) -> NDArray[np.float64]:
    """The DH increments a spec describes.

    Parameters
    ----------
    spec : str
        Terms ``<joint>.<a|d|alpha|offset><+|-><value>``; lengths in m, angles in deg.
    joint_names : sequence of str
        The arm's joints, in DH-table order.

    Returns
    -------
    ndarray, shape (L, 4)
        Increments in the table's units (m, rad); zero where the spec says nothing.

    Raises
    ------
    BodyChangeError
        On an empty spec, an unknown joint, a malformed term or a non-finite value.
    """
    names = list(joint_names)
    delta = np.zeros((len(names), 4))
    terms = [t for t in re.split(r'[\s,]+', spec.strip()) if t]
    if not terms:
        raise BodyChangeError('empty body change: expected terms like "r_elbow.d+0.01"')
    for term in terms:
        m = _TERM.match(term)
        if m is None:
            raise BodyChangeError(f'body change term {term!r}: expected <joint>.<a|d|alpha|offset><+|-><value>, '
                                  'e.g. "r_wrist_prosup.d+0.010" (m) or "r_shoulder_yaw.offset+3" (deg)')
        if m['joint'] not in names:
            raise BodyChangeError(f'body change term {term!r}: unknown joint {m["joint"]!r}; expected one of {names}')
        try:
            value = float(m['delta'])
        except ValueError:
            raise BodyChangeError(f'body change term {term!r}: {m["delta"]!r} is not a number') from None
        if not np.isfinite(value):
            raise BodyChangeError(f'body change term {term!r}: the increment must be finite')
        col = _COLUMNS[m['col']]
        delta[names.index(m['joint']), col] += np.radians(value) if col >= 2 else value
    return delta
