"""Ground force partials (Eq. 18, 20, 23) and the integrators (Eq. 15)."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from conftest import central_diff
from numpy.testing import assert_allclose

from mpa_gym.analysis.simulate import DT_DEFAULT, simulate
from mpa_gym.analysis.stability import a1_eq20
from mpa_gym.model import force_terms, ground_force, integrate_rk4, leg_dynamics
from mpa_gym.model.params import DEFAULT_PARAMS as P

RNG = np.random.default_rng(7)
N = 64
XS = RNG.uniform(0.72, 0.86, N)
VS = RNG.uniform(-0.4, 0.4, N)
PE = RNG.uniform(0.0, 7e5, N)
PF = RNG.uniform(0.0, 7e5, N)


def test_dF_dX_matches_numerical_derivative():
    # Eq. (23): k = −∂F/∂X at fixed pressures and V; h = 1e-6 m, O(h²) truncation.
    numeric = central_diff(lambda x: ground_force(x, VS, PE, PF, P), XS, 1e-6)
    assert_allclose(force_terms(XS, VS, PE, PF, P).dF_dX, numeric, rtol=1e-6, atol=1e-4)


def test_eq20_a1_matches_numerical_dF_dV():
    # Eq. (20): a1 = −(G_e² γ + G_f² γ)/m equals (1/m) ∂F/∂V computed numerically from Eq. (5).
    numeric = central_diff(lambda v: ground_force(XS, v, PE, PF, P), VS, 1e-4) / P.leg.m
    assert_allclose(a1_eq20(XS, P), numeric, rtol=1e-8)
    assert np.all(a1_eq20(XS, P) < 0)  # the basis of Theorem 1
    assert_allclose(force_terms(XS, VS, PE, PF, P).dF_dV / P.leg.m, a1_eq20(XS, P), rtol=1e-13)


def test_ground_force_is_affine_in_each_pressure():
    f = lambda pe, pf: ground_force(XS, VS, pe, pf, P)  # noqa: E731
    assert_allclose(f(PE, PF), 0.5 * (f(PE - 1e5, PF) + f(PE + 1e5, PF)), rtol=1e-12)
    assert_allclose(f(PE, PF), 0.5 * (f(PE, PF - 1e5) + f(PE, PF + 1e5)), rtol=1e-12)


def test_single_and_batched_integration_agree():
    u = np.array([3e5, 0.5e5])

    def f(t, y):
        return leg_dynamics(t, y, u, P)

    y0s = np.stack([XS[:5], VS[:5]], axis=-1)
    batch = integrate_rk4(f, 0.0, y0s, 1e-3, 200)
    for i in range(5):
        single = integrate_rk4(f, 0.0, y0s[i], 1e-3, 200)
        assert_allclose(batch[:, i], single, rtol=1e-12, atol=1e-15)


def test_rk4_is_fourth_order():
    # Halving the step divides the global error by 2^4 = 16 (within 20 %).
    u = np.array([3e5, 0.5e5])

    def f(t, y):
        return leg_dynamics(t, y, u, P)

    y0 = np.array([0.81, 0.1])
    exact = integrate_rk4(f, 0.0, y0, 1e-4, 2000)[-1]
    e1 = np.abs(integrate_rk4(f, 0.0, y0, 8e-3, 25)[-1] - exact).max()
    e2 = np.abs(integrate_rk4(f, 0.0, y0, 4e-3, 50)[-1] - exact).max()
    assert 16 / 1.2 < e1 / e2 < 16 * 1.2


@cache
def reference_run(scenario: str):
    return simulate(scenario, method="reference")


@pytest.mark.parametrize("scenario", ["nominal", "initial_error", "impulse", "kmin"])
@pytest.mark.parametrize("dt", [DT_DEFAULT, 0.01])
def test_fixed_step_rk4_within_1e6_m_of_solve_ivp_over_30s(scenario, dt):
    # The accuracy target: |X_rk4 − X_solve_ivp(rtol 1e-10)| < 1e-6 m over 30 s, at the
    # simulator's step and at the 100 Hz control step the environments use.
    ref = reference_run(scenario)
    rk = simulate(scenario, dt=dt)
    assert ref.t[-1] == pytest.approx(30.0)
    assert np.max(np.abs(rk.x - ref.x)) < 1e-6


def test_solve_ivp_reference_tracks_the_design_exactly():
    # Eq. (16) makes X̂ an exact solution: the accurate integrator stays on it from its start.
    ref = reference_run("nominal")
    assert np.max(np.abs(ref.x - ref.x_ref)) < 1e-8
