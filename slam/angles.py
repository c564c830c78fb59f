"""Angle helpers shared by the motion and measurement models (radians)."""

from __future__ import annotations

import numpy as np


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles in rad to [-pi, pi); works elementwise on arrays of any shape. (The remainder of a tiny
    negative number rounds up to 2 pi, which would give +pi: that end is folded to -pi.)"""
    wrapped = (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi
    return wrapped - 2.0 * np.pi * (wrapped >= np.pi)
