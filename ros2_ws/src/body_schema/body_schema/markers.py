"""ArUco marker facts the simulator and the detector share: the dictionary lookup and the
black square's corner geometry (cv2 is imported only when a dictionary is looked up)."""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ['aruco_dictionary', 'marker_corners']


def aruco_dictionary(name: str) -> Any:
    """The cv2.aruco predefined dictionary called ``name`` (e.g. ``'DICT_4X4_50'``).

    Raises
    ------
    ValueError
        If ``name`` is not a cv2.aruco ``DICT_*`` name.
    """
    import cv2

    code = getattr(cv2.aruco, name, None)
    if not name.startswith('DICT_') or not isinstance(code, int):
        raise ValueError(f'unknown ArUco dictionary {name!r}; expected a cv2.aruco DICT_* name')
    return cv2.aruco.getPredefinedDictionary(code)


def marker_corners(side: float) -> NDArray[np.float64]:
    """The black square's corners in the marker frame (z out of the face), ArUco/OpenCV order
    (top-left, top-right, bottom-right, bottom-left), shape (4, 3) [m]."""
    h = side / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
