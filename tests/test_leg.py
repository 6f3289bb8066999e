"""Knee geometry and transmission (Eq. 8-14): derivatives and virtual work."""

from __future__ import annotations

import math

import numpy as np
from conftest import central_diff
from numpy.testing import assert_allclose

from mpa_gym.model import ground_force, kinematics
from mpa_gym.model.dynamics import force_terms
from mpa_gym.model.params import DEFAULT_PARAMS

LEG, MPA = DEFAULT_PARAMS.leg, DEFAULT_PARAMS.mpa
X = np.linspace(0.70, 0.86, 33)
H = 1e-6  # [m]: O(h²) truncation well below the 1e-7 relative tolerances used here


def kin(x):
    return kinematics(x, LEG, MPA)


def test_Ge_is_minus_dLe_dX_and_Gf_is_dLf_dX():
    assert_allclose(kin(X).Ge, -central_diff(lambda x: kin(x).Le, X, H), rtol=1e-7)
    assert_allclose(kin(X).Gf, central_diff(lambda x: kin(x).Lf, X, H), rtol=1e-7)


def test_Ge_Gf_derivatives_match_finite_differences():
    assert_allclose(kin(X).dGe, central_diff(lambda x: kin(x).Ge, X, H), rtol=1e-6)
    assert_allclose(kin(X).dGf, central_diff(lambda x: kin(x).Gf, X, H), rtol=1e-6, atol=1e-9)


def test_knee_angle_closes_the_triangle():
    # Law of cosines: X² = Lo² + Lu² − 2 Lo Lu cos β.
    b = kin(X).beta
    assert_allclose(LEG.Lo**2 + LEG.Lu**2 - 2 * LEG.Lo * LEG.Lu * np.cos(b), X**2, rtol=1e-13)


def test_both_mpas_have_resting_length_at_the_rest_posture():
    k = kin(LEG.x_rest)
    assert_allclose([k.Le, k.Lf], [MPA.L0, MPA.L0], rtol=1e-14)


def test_virtual_work_power_balance():
    # F V = f_e v_e + f_f v_f: the ground force does the work the MPAs' tensions do
    # (contractile velocities v_e = −dL_e/dt, v_f = −dL_f/dt).
    rng = np.random.default_rng(0)
    x = rng.uniform(0.72, 0.85, 50)
    v = rng.uniform(-0.5, 0.5, 50)
    pe, pf = rng.uniform(0, 7e5, 50), rng.uniform(0, 7e5, 50)
    ft = force_terms(x, v, pe, pf, DEFAULT_PARAMS)
    dLe_dt = central_diff(lambda xx: kin(xx).Le, x, H) * v
    dLf_dt = central_diff(lambda xx: kin(xx).Lf, x, H) * v
    assert_allclose(ft.F * v, ft.fe * (-dLe_dt) + ft.ff * (-dLf_dt), rtol=1e-6, atol=1e-9)


def test_outside_reachable_heights_gives_nan_not_an_exception():
    _lo, hi = LEG.x_domain
    assert math.isnan(ground_force(hi + 0.01, 0.0, 1e5, 1e5, DEFAULT_PARAMS))
    with np.errstate(invalid="ignore"):  # numpy's warning for NaN is expected here
        assert np.isnan(ground_force(np.array([hi + 0.01]), 0.0, 1e5, 1e5, DEFAULT_PARAMS)).all()
