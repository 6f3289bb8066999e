"""Theorem 1 and Floquet analysis (Eq. 17-20), checked by Liouville and by the nonlinear plant."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.testing import assert_allclose

from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.analysis.simulate import simulate
from mpa_gym.analysis.stability import (
    a1_eq20,
    analyze,
    linear_steady_state_error,
    linearisation,
    monodromy_matrix,
    theorem1_integral,
)
from mpa_gym.design import (
    FeedforwardDesign,
    Reference,
    StiffnessEnvelope,
    constant_flexor,
    mode_pattern,
)
from mpa_gym.model.params import DEFAULT_PARAMS as P

REF = Reference()
DESIGNS = {
    "pf_const": FeedforwardDesign(REF, flexor=constant_flexor(0.5)),
    "mode1": FeedforwardDesign(REF, flexor=mode_pattern(1)),
    "mode2": FeedforwardDesign(REF, flexor=mode_pattern(2)),
    "kmin": FeedforwardDesign(REF, stiffness=StiffnessEnvelope("kmin", REF)),
}


@pytest.mark.parametrize("name", DESIGNS)
def test_liouville_product_of_multipliers_is_exp_integral_a1(name):
    rep = analyze(DESIGNS[name])
    # monodromy integrated at rtol 1e-11: det and exp(∫a1) agree to ~1e-10 relative
    assert_allclose(np.prod(rep.multipliers).real, np.exp(rep.int_a1), rtol=1e-8)
    assert_allclose(np.linalg.det(rep.monodromy), np.exp(rep.int_a1), rtol=1e-8)
    assert abs(np.prod(rep.multipliers).imag) < 1e-12


@pytest.mark.parametrize("name", DESIGNS)
def test_theorem1_holds_and_motion_is_stable(name):
    rep = analyze(DESIGNS[name])
    assert rep.theorem1_holds and rep.int_a1 < 0
    assert rep.stable and rep.spectral_radius < 1.0


def test_theorem1_integral_is_the_integral_of_the_linearisation_a1():
    d = DESIGNS["mode1"]
    t = np.linspace(0.0, 3.0, 4001)
    a1, _ = linearisation(d, t)
    # trapezoid on a smooth periodic integrand converges spectrally: 1e-9 is generous
    assert_allclose(theorem1_integral(d), np.trapezoid(a1, t), rtol=1e-9)
    assert_allclose(a1, a1_eq20(REF.position(t), P), rtol=1e-13)


def test_integral_a1_scales_with_gamma():
    # Eq. (20) is linear in γ, so is its integral.
    half = dataclasses.replace(P, mpa=dataclasses.replace(P.mpa, gamma=15.0))
    d_half = FeedforwardDesign(REF, flexor=constant_flexor(0.5), params=half)
    assert_allclose(theorem1_integral(d_half), 0.5 * theorem1_integral(DESIGNS["pf_const"]),
                    rtol=1e-12)


@pytest.mark.parametrize("column", [0, 1])
def test_monodromy_matrix_predicts_the_nonlinear_plant(column):
    # A perturbation δ0 of the initial state, propagated one period by the nonlinear plant
    # (solve_ivp, rtol 1e-10), equals Φ(T) δ0 up to O(|δ0|²): relative 1e-3 for δ0 ~ 1e-5.
    d = DESIGNS["pf_const"]
    phi = monodromy_matrix(d)
    delta = np.array([1e-5, 0.0]) if column == 0 else np.array([0.0, 1e-4])
    x0, v0 = REF.position(0.0) + delta[0], REF.velocity(0.0) + delta[1]
    sc = {"name": "floquet", "duration_s": 3.0, "initial_state": {"x_m": float(x0),
          "v_mps": float(v0)}}
    r = simulate(sc, method="reference", output_dt=None)
    err_T = np.array([r.x[-1] - REF.position(3.0), r.v[-1] - REF.velocity(3.0)])
    assert_allclose(err_T, phi @ delta, rtol=1e-3, atol=1e-3 * np.abs(phi @ delta).max())


def _window_error(r, start):
    w = r.t >= start - 1e-9
    return r.t[w], r.error[w]


def test_linear_prediction_of_mass_mismatch_error_is_first_order_accurate():
    # Small Δm: the linearised periodic error matches the nonlinear steady state, and the
    # discrepancy is second order (relative discrepancy doubles when Δm doubles).
    rel = []
    for dm in (0.02, 0.04):
        sc = load_scenario({"name": "dm", "duration_s": 30.0, "plant": {"mass_kg": 3.74 + dm}})
        r = simulate(sc)
        t, e = _window_error(r, 27.0)
        pred = linear_steady_state_error(sc.design(), sc.plant_params(), t)
        rel.append(np.abs(e - pred).max() / np.abs(pred).max())
    assert rel[0] < 0.01
    assert 1.8 < rel[1] / rel[0] < 2.2
