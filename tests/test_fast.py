"""The compiled plant kernels against the readable numpy model they transcribe."""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.testing import assert_allclose

from mpa_gym.model import fast, force_terms, integrate_reference
from mpa_gym.model.dynamics import plant_rhs
from mpa_gym.model.params import DEFAULT_PARAMS as P

RNG = np.random.default_rng(3)
XS = RNG.uniform(0.72, 0.86, 50)
VS = RNG.uniform(-0.5, 0.5, 50)
PE = RNG.uniform(0.0, 7e5, 50)
PF = RNG.uniform(0.0, 7e5, 50)
OTHER = dataclasses.replace(P, mpa=dataclasses.replace(P.mpa, C1=150e3, C2=3e3, gamma=20.0,
                                                       thickness=1.3e-3),
                            leg=dataclasses.replace(P.leg, m=4.5))


def test_force_and_stiffness_equal_the_reference_model():
    for params in (P, OTHER):
        c = fast.pack(params)
        ref = force_terms(XS, VS, PE, PF, params)
        got = np.array([fast.force_and_stiffness(x, v, pe, pf, c)
                        for x, v, pe, pf in zip(XS, VS, PE, PF, strict=True)])
        # same formulas in another order of operations: agreement to rounding (1e-12 relative
        # to the magnitude of the terms that are summed)
        assert_allclose(got[:, 0], ref.F, rtol=1e-12, atol=1e-9)
        assert_allclose(got[:, 1], -ref.dF_dX, rtol=1e-11, atol=1e-7)


def test_outside_domain_is_nan():
    assert np.isnan(fast.force_and_stiffness(0.9, 0.0, 1e5, 1e5, fast.pack(P))).all()


def _reference_step(y0, cmd, lag, dt):
    if lag > 0:
        return integrate_reference(lambda t, y: plant_rhs(y, cmd, P, lag), [0.0, dt], y0,
                                   rtol=1e-13, atol=1e-15)[-1]
    xv = integrate_reference(lambda t, y: plant_rhs(y, cmd, P), [0.0, dt], y0[:2], rtol=1e-13,
                             atol=1e-15)[-1]
    return np.concatenate([xv, cmd[:2]])


def test_plant_step_is_rk4_of_the_reference_ode():
    # One step with held commands (and a first-order regulator) against DOP853 on the same ODE:
    # the pressures follow the exact exponential, and the (X, V) error is RK4's local error
    # C h⁵, so halving the step divides it by 32 (within 25 %); at 10 ms it is below 1e-8.
    c = fast.pack(P)
    y0 = np.array([0.8, 0.05, 3e5, 0.5e5])
    cmd = np.array([3.4e5, 0.8e5, 2.0])
    for lag in (0.0, 0.03):
        errs = []
        for dt in (0.01, 0.005):
            got = np.array(fast.plant_step(*y0, cmd[0], cmd[1], cmd[2], lag, dt, c))
            ref = _reference_step(y0, cmd, lag, dt)
            assert_allclose(got[2:], ref[2:], rtol=1e-10)
            errs.append(np.abs(got[:2] - ref[:2]))
        assert np.all(errs[0] < np.array([1e-8, 1e-7]))
        assert np.all((32 / 1.25 < errs[0] / errs[1]) & (errs[0] / errs[1] < 32 * 1.25))
