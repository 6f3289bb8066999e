"""Scalar-or-array helpers: the physics kernels run on Python floats (fast, one leg) and on numpy
arrays (a batch of legs) through the same code."""

from __future__ import annotations

import math
from typing import TypeAlias

import numpy as np

Array: TypeAlias = "float | np.ndarray"


def sqrt(x: Array) -> Array:
    """√x; NaN (never an exception) outside the domain, for floats as for arrays."""
    if isinstance(x, float):
        return math.sqrt(x) if x >= 0.0 else math.nan
    return np.sqrt(x)


def acos(x: Array) -> Array:
    """arccos x; NaN (never an exception) outside [−1, 1], for floats as for arrays."""
    if isinstance(x, float):
        return math.acos(x) if -1.0 <= x <= 1.0 else math.nan
    return np.arccos(x)



def tanh(x: Array) -> Array:
    """tanh x, for floats as for arrays."""
    if isinstance(x, float):
        return math.tanh(x)
    return np.tanh(x)
