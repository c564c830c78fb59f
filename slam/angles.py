"""Angle helpers shared by the motion and measurement models (radians)."""
from __future__ import annotations

import numpy as np


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles in rad to [-pi, pi); works elementwise on arrays of any shape."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi
