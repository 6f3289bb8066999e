"""Shared fixtures."""

from __future__ import annotations

import numpy as np
import pytest

from mpa_gym.model.params import DEFAULT_PARAMS, Params


@pytest.fixture
def params() -> Params:
    return DEFAULT_PARAMS


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def central_diff(f, x, h):
    """Fourth-order (five-point) central difference: truncation O(h⁴ f⁽⁵⁾), round-off
    O(eps |f| / h); with the steps used in the tests both are below 1e-8 relative."""
    return (f(x - 2 * h) - 8 * f(x - h) + 8 * f(x + h) - f(x + 2 * h)) / (12.0 * h)
