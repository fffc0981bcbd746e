"""Seeded draws: initial DH guesses around a true table and joint configurations in a box."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['PAPER_WIDTH_LENGTH', 'PAPER_WIDTH_ANGLE', 'as_rng', 'perturb_dh', 'uniform_configs',
           'initial_covariance']

#: The paper's initial-guess widths (sec. V): 46 mm for a and d, 54 deg for alpha and offset.
PAPER_WIDTH_LENGTH = 0.046
PAPER_WIDTH_ANGLE = float(np.radians(54.0))


def as_rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    """A numpy Generator from a seed (or the generator itself)."""
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def _widths(n_links: int, width_length: float, width_angle: float) -> NDArray[np.float64]:
    if not (np.isfinite(width_length) and np.isfinite(width_angle)) or width_length < 0 or width_angle < 0:
        raise ValueError(f'widths must be finite and >= 0, got {width_length}, {width_angle}')
    return np.tile([width_length, width_length, width_angle, width_angle], (n_links, 1))


def perturb_dh(dh: ArrayLike, seed: int | np.random.Generator | None = None,
               width_length: float = PAPER_WIDTH_LENGTH,
               width_angle: float = PAPER_WIDTH_ANGLE) -> NDArray[np.float64]:
    """A DH table drawn uniformly around ``dh``: each parameter in ``[x - w/2, x + w/2]``.

    Parameters
    ----------
    dh : array_like, shape (L, 4)
        Centre table ``(a, d, alpha, offset)``.
    seed : int, Generator or None
    width_length : float
        Full width of the interval for ``a`` and ``d`` [m] (paper: 0.046).
    width_angle : float
        Full width for ``alpha`` and ``offset`` [rad] (paper: 54 deg).

    Returns
    -------
    ndarray, shape (L, 4)
    """
    dh = np.asarray(dh, dtype=float)
    if dh.ndim != 2 or dh.shape[1] != 4:
        raise ValueError(f'dh must have shape (L, 4), got {dh.shape}')
    w = _widths(dh.shape[0], width_length, width_angle)
    return dh + as_rng(seed).uniform(-0.5, 0.5, size=dh.shape) * w


def initial_covariance(n_links: int, width_length: float = PAPER_WIDTH_LENGTH,
                       width_angle: float = PAPER_WIDTH_ANGLE) -> NDArray[np.float64]:
    """Diagonal covariance of the uniform initial-guess distribution: ``w^2 / 12`` per parameter.

    Returns
    -------
    ndarray, shape (4 L, 4 L)
    """
    return np.diag((_widths(n_links, width_length, width_angle) ** 2 / 12.0).ravel())


def uniform_configs(box: ArrayLike, n: int, seed: int | np.random.Generator | None = None) -> NDArray[np.float64]:
    """``n`` joint configurations uniform in ``box``.

    Parameters
    ----------
    box : array_like, shape (L, 2)
        ``[min, max]`` per joint [rad].

    Returns
    -------
    ndarray, shape (n, L)
    """
    box = np.asarray(box, dtype=float)
    return as_rng(seed).uniform(box[:, 0], box[:, 1], size=(int(n), box.shape[0]))
