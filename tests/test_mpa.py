"""MPA force model (Eq. 1-4, Appendix) held to identities, not to its own output."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import central_diff
from numpy.testing import assert_allclose

from mpa_gym.model import mpa
from mpa_gym.model.params import DEFAULT_PARAMS

P = DEFAULT_PARAMS.mpa
# Lengths across the physical domain (b/√3, b) that the leg actually visits and beyond.
LENGTHS = np.linspace(0.095, 0.142, 41)
H = 1e-5  # [m] FD step (five-point stencil): truncation and round-off both < 1e-8 relative


def scale_tol(ref):
    """Absolute tolerance 1e-8 × the largest magnitude: values near a zero crossing are judged
    against the function's scale, not their own tiny size."""
    return 1e-8 * float(np.max(np.abs(ref)))


def test_appendix_dW_dL_is_the_derivative_of_the_mooney_rivlin_energy():
    # The Appendix's printed dW/dL against a numerical derivative of W = C1(I1-3) + C2(I2-3).
    numeric = central_diff(lambda L: mpa.strain_energy_density(L, P), LENGTHS, H)
    assert_allclose(mpa.dW_dL(LENGTHS, P), numeric, rtol=1e-8, atol=scale_tol(numeric))


def test_d2W_dL2_is_the_derivative_of_dW_dL():
    numeric = central_diff(lambda L: mpa.dW_dL(L, P), LENGTHS, H)
    assert_allclose(mpa.d2W_dL2(LENGTHS, P), numeric, rtol=1e-8, atol=scale_tol(numeric))


def test_bladder_volume_derivatives_match_finite_differences():
    assert_allclose(mpa.dVb_dL(LENGTHS, P),
                    central_diff(lambda L: mpa.bladder_volume(L, P), LENGTHS, H),
                    rtol=1e-10, atol=1e-16)
    assert_allclose(mpa.d2Vb_dL2(LENGTHS, P),
                    central_diff(lambda L: mpa.dVb_dL(L, P), LENGTHS, H), rtol=1e-10)
    # Pressure makes tension exactly where the braid angle is below 54.7°: −dV_b/dL > 0.
    lo, hi = P.length_domain
    inside = (LENGTHS > lo) & (LENGTHS < hi)
    assert np.all(-mpa.dVb_dL(LENGTHS[inside], P) > 0)
    assert abs(float(mpa.dVb_dL(lo, P))) < 1e-15


def test_braid_geometry_is_consistent_with_the_resting_diameter():
    # Documented assumption: D(L0) reproduces Table A1's D0 = 15 mm (to 0.1 %).
    assert_allclose(mpa.braid_diameter(P.L0, P), P.D0, rtol=1e-3)
    # V_b = π D² L / 4 for the braided cylinder.
    assert_allclose(mpa.bladder_volume(LENGTHS, P),
                    math.pi * mpa.braid_diameter(LENGTHS, P) ** 2 * LENGTHS / 4, rtol=1e-12)


def test_rubber_volume_is_the_annulus_times_the_resting_length():
    ro = P.D0 / 2
    assert_allclose(P.Vr, math.pi * P.L0 * (ro**2 - (ro - P.thickness) ** 2), rtol=1e-15)
    assert_allclose(P.Vr, math.pi * 0.125 * (7.5e-3**2 - 6.5e-3**2), rtol=1e-12)


@pytest.mark.parametrize("pressure", [0.0, 1e5, 3e5, 7e5])
def test_force_velocity_slope_is_minus_gamma(pressure):
    # Eq. (3)/(4): df/dv = −γ < 0 at any pressure and length.
    L = LENGTHS
    numeric = central_diff(lambda v: mpa.force(pressure, L, v, P), 0.05, 1e-4)
    assert_allclose(numeric, -P.gamma, rtol=1e-9)


def test_force_length_derivative_matches_finite_differences():
    for pressure in (0.0, 2.5e5, 6e5):
        numeric = central_diff(lambda L, pr=pressure: mpa.force(pr, L, 0.0, P), LENGTHS, H)
        assert_allclose(mpa.dforce_dL(pressure, LENGTHS, P), numeric, rtol=1e-8,
                        atol=scale_tol(numeric))


def test_float_and_array_paths_agree():
    for L in (0.1, 0.125, 0.14):
        assert_allclose(mpa.force(2e5, L, 0.01, P), mpa.force(np.array([2e5]), np.array([L]),
                                                                np.array([0.01]), P)[0],
                        rtol=1e-14)
    assert math.isnan(mpa.braid_diameter(0.2, P))  # L > b: outside the domain, NaN not a crash
