"""Ground force partials (Eq. 18, 20, 23) and the integrators (Eq. 15)."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
from conftest import central_diff
from numpy.testing import assert_allclose
from scipy.optimize import brentq

from mpa_gym.analysis.simulate import DT_DEFAULT, simulate
from mpa_gym.analysis.stability import a1_eq20
from mpa_gym.model import (
    force_terms,
    ground_force,
    integrate_reference,
    integrate_rk4,
    kinematics,
    leg_dynamics,
    mpa,
)
from mpa_gym.model.dynamics import dissipated_power, mechanical_energy
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
    # The accuracy target (docs/design.md#targets): |X_rk4 − X_solve_ivp(rtol 1e-10)| < 1e-6 m
    # over 30 s, at the simulator's step and at the 100 Hz control step the environments use.
    ref = reference_run(scenario)
    rk = simulate(scenario, dt=dt)
    assert ref.t[-1] == pytest.approx(30.0)
    assert np.max(np.abs(rk.x - ref.x)) < 1e-6


def test_solve_ivp_reference_tracks_the_design_exactly():
    # Eq. (16) makes X̂ an exact solution: the accurate integrator stays on it from its start.
    ref = reference_run("nominal")
    assert np.max(np.abs(ref.x - ref.x_ref)) < 1e-8


# ----------------------------------------------------------------------------- plant effects
FRICTION = dataclasses.replace(
    P, mpa=dataclasses.replace(P.mpa, friction=0.05),
    leg=dataclasses.replace(P.leg, friction_coulomb=2.0, friction_viscous=5.0))


@pytest.mark.parametrize("params", [P, FRICTION], ids=["paper", "friction"])
def test_force_partials_match_numerical_derivatives_with_braid_friction(params):
    # ∂F/∂X (Eq. 23's general form) and ∂F/∂V against central differences of F itself;
    # h = 1e-7 m and 1e-6 m/s are well inside the 1 mm/s friction regularisation, O(h²).
    ft = force_terms(XS, VS, PE, PF, params)
    dX = central_diff(lambda x: ground_force(x, VS, PE, PF, params), XS, 1e-7)
    dV = central_diff(lambda v: ground_force(XS, v, PE, PF, params), VS, 1e-6)
    assert_allclose(ft.dF_dX, dX, rtol=1e-5, atol=1e-2)
    assert_allclose(ft.dF_dV, dV, rtol=1e-6, atol=1e-6)


def test_friction_only_dissipates_energy_along_a_trajectory():
    # Constant pressures, no external force: E = m V²/2 + m g X + U_e + U_f has
    # dE/dt = −D, D = viscous + braid + slider friction power ≥ 0 (mechanical_energy's
    # docstring). The dissipated work W (dW/dt = D) is integrated beside (X, V) by solve_ivp
    # (rtol 1e-11): E + W stays at E(0) to 1e-7 J (the integrator's tolerance on a ~1e2 J
    # total), while W grows to ~0.1 J, so a friction term that fed energy in, or a potential
    # that did not match the forces, would show a thousand times over.
    u = np.array([3.2e5, 0.6e5])

    def rhs(t, y):
        d = dissipated_power(y[0], y[1], u[0], u[1], FRICTION)
        return np.append(leg_dynamics(t, y[:2], u, FRICTION), d)

    t = np.linspace(0.0, 1.5, 1501)
    ys = integrate_reference(rhs, t, [0.80, 0.3, 0.0], rtol=1e-11, atol=1e-13)
    X, V, W = ys.T
    E = mechanical_energy(X, V, u[0], u[1], FRICTION)
    D = dissipated_power(X, V, u[0], u[1], FRICTION)
    assert np.all(D >= 0.0)
    assert W[-1] > 0.05  # the kick makes the check meaningful (J)
    assert_allclose(E + W, E[0], rtol=0, atol=1e-7)
    assert np.all(np.diff(E) <= 1e-9)  # never gains energy
    # each friction is a part of it: the paper's plant from the same start loses less
    ys0 = integrate_reference(lambda tt, y: leg_dynamics(tt, y, u, P), t, [0.80, 0.3],
                              rtol=1e-11, atol=1e-13)
    lost0 = mechanical_energy(0.80, 0.3, *u, P) - mechanical_energy(*ys0[-1], *u, P)
    assert 0.0 < lost0 < W[-1]


def _sweep(mu):
    # P'_e rises 2.6 → 3.6 bar in 4 s and falls back (raised cosine: no jerk at the turns),
    # P'_f = 0.5 bar; start at rest on the static equilibrium.
    params = dataclasses.replace(P, mpa=dataclasses.replace(P.mpa, friction=mu))
    lo, hi, pf, T = 2.6e5, 3.6e5, 0.5e5, 4.0

    def pe(t):
        return lo + (hi - lo) * 0.5 * (1.0 - np.cos(np.pi * t / T))

    x0 = brentq(lambda x: ground_force(x, 0.0, lo, pf, params) - params.leg.m * params.leg.g,
                0.7, 0.86)
    t = np.linspace(0.0, 2.0 * T, 4001)
    ys = integrate_reference(lambda tt, y: leg_dynamics(tt, y, [pe(tt), pf], params), t,
                             [x0, 0.0], rtol=1e-9, atol=1e-12)
    return params, pe(t), ys[:, 0], pf


def _static_branch(params, pe, pf, sign):
    """X where the static force minus (sign) the full braid friction carries m g."""
    paper = dataclasses.replace(params, mpa=dataclasses.replace(params.mpa, friction=0.0))

    def residual(x):
        kin = kinematics(x, params.leg, params.mpa)
        fr = params.mpa.friction * (kin.Ge * -pe * mpa.dVb_dL(kin.Le, params.mpa)
                                    + kin.Gf * -pf * mpa.dVb_dL(kin.Lf, params.mpa))
        return ground_force(x, 0.0, pe, pf, paper) - sign * fr - params.leg.m * params.leg.g

    return brentq(residual, 0.7, 0.86)


def test_braid_friction_gives_a_hysteresis_loop_of_the_right_sign_and_width():
    # Rising P'_e lifts the hip (extensor contracts, flexor extends): braid friction opposes
    # both, so the rising branch sits below the falling one, each at the static equilibrium
    # with the full friction 2 μ_b f_P subtracted / added (Tondu & Lopez's loop). Tolerance:
    # the frictionless sweep at the same rate leaves its static curve by up to 0.18 mm
    # (inertia, viscosity; measured), so each branch is held to 0.25 mm of a ~7 mm loop.
    params, pe, x, pf = _sweep(0.03)
    _, _, x0, _ = _sweep(0.0)
    half = pe.size // 2
    for p_test in (2.9e5, 3.1e5, 3.3e5):
        up = np.argmin(np.abs(pe[:half] - p_test))
        down = half + np.argmin(np.abs(pe[half:] - p_test))
        x_up, x_down = _static_branch(params, p_test, pf, +1), _static_branch(params, p_test,
                                                                               pf, -1)
        assert x_down - x_up > 5e-3  # the predicted loop is wide (5-8 mm at these pressures)
        assert abs(x[up] - x_up) < 2.5e-4
        assert abs(x[down] - x_down) < 2.5e-4
        assert x[down] > x[up]
        assert abs(x0[down] - x0[up]) < 0.05 * (x[down] - x[up])  # without friction: no loop


@pytest.mark.parametrize("plant,tol", [
    ({"pressure_dead_time_s": 0.0237}, 1e-6),
    ({"pressure_slew_bar_per_s": 0.5}, 1e-6),
    ({"braid_friction_ratio": 0.03}, 2e-5),
    ({"slider_friction_N": 1.5, "slider_viscous_Ns_per_m": 3.0}, 2e-5),
], ids=["dead_time", "slew", "braid_friction", "slider_friction"])
def test_simulate_with_plant_effects_stays_near_solve_ivp(plant, tol):
    # `mpa-gym simulate` on a 30 ms-lag plant with each effect, an impulse at 2 s, 9 s, RK4 at
    # the simulator's 5 ms step against DOP853 (rtol 1e-10). The regulator effects keep the
    # paper plant's 1e-6 m (measured 9e-8 m, 7e-7 m: the slew limit's kinks are not on the
    # grid). The friction regularisations are fast near a velocity reversal (braid: about
    # 80 /s at 5 ms steps, λh ≈ 0.4), where RK4 loses digits: measured 6e-6 m and 4e-6 m,
    # held to 2e-5 m; each effect itself moves X by more than ten times its tolerance.
    sc = {"name": "effects", "duration_s": 9.0, "plant": {"pressure_lag_s": 0.03, **plant},
          "disturbances": [{"type": "impulse", "t_s": 2.0, "force_N": 20.0, "duration_s": 0.05}]}
    ref = simulate(sc, method="reference")
    rk = simulate(sc)
    assert np.max(np.abs(rk.x - ref.x)) < tol
    paper = simulate({**sc, "plant": {"pressure_lag_s": 0.03}})
    assert np.max(np.abs(rk.x - paper.x)) > 10 * tol  # the effect is there to be resolved
