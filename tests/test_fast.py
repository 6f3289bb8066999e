"""The compiled plant kernels against the readable numpy model they transcribe."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.testing import assert_allclose

from mpa_gym.model import dynamics, fast, force_terms, integrate_reference
from mpa_gym.model.dynamics import plant_rhs
from mpa_gym.model.params import DEFAULT_PARAMS as P
from mpa_gym.model.params import RegulatorParams

RNG = np.random.default_rng(3)
XS = RNG.uniform(0.72, 0.86, 50)
VS = RNG.uniform(-0.5, 0.5, 50)
PE = RNG.uniform(0.0, 7e5, 50)
PF = RNG.uniform(0.0, 7e5, 50)
OTHER = dataclasses.replace(P, mpa=dataclasses.replace(P.mpa, C1=150e3, C2=3e3, gamma=20.0,
                                                       thickness=1.3e-3),
                            leg=dataclasses.replace(P.leg, m=4.5))


# the plant effects on (braid friction, slider friction, regulator dead time and slew)
EFFECTS = dataclasses.replace(
    OTHER, mpa=dataclasses.replace(OTHER.mpa, friction=0.04),
    leg=dataclasses.replace(OTHER.leg, friction_coulomb=1.5, friction_viscous=4.0),
    regulator=RegulatorParams(lag=0.03, dead_time=0.025, slew=20e5))


@pytest.mark.parametrize("params", [P, OTHER, EFFECTS], ids=["paper", "other", "effects"])
def test_force_and_stiffness_equal_the_reference_model(params):
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
        pl = dataclasses.replace(P, regulator=RegulatorParams(lag=lag))
        return integrate_reference(lambda t, y: plant_rhs(y, cmd, pl), [0.0, dt], y0,
                                   rtol=1e-13, atol=1e-15)[-1]
    xv = integrate_reference(lambda t, y: plant_rhs(y, cmd, P), [0.0, dt], y0[:2], rtol=1e-13,
                             atol=1e-15)[-1]
    return np.concatenate([xv, cmd[:2]])


def test_plant_step_is_rk4_of_the_reference_ode():
    # One step with held commands (and a first-order regulator) against DOP853 on the same ODE:
    # the pressures follow the exact exponential, and the (X, V) error is RK4's local error
    # C h⁵, so halving the step divides it by 32 (within 25 %); at 10 ms it is below 1e-8.
    y0 = np.array([0.8, 0.05, 3e5, 0.5e5])
    cmd = np.array([3.4e5, 0.8e5, 2.0])
    for lag in (0.0, 0.03):
        c = fast.pack(dataclasses.replace(P, regulator=RegulatorParams(lag=lag)))
        errs = []
        for dt in (0.01, 0.005):
            got = np.array(fast.plant_step(*y0, *cmd[:2], *cmd[:2], 0.0, cmd[2], dt, c))
            ref = _reference_step(y0, cmd, lag, dt)
            assert_allclose(got[2:], ref[2:], rtol=1e-10)
            errs.append(np.abs(got[:2] - ref[:2]))
        assert np.all(errs[0] < np.array([1e-8, 1e-7]))
        assert np.all((32 / 1.25 < errs[0] / errs[1]) & (errs[0] / errs[1] < 32 * 1.25))


# ----------------------------------------------------------------------------- plant effects


@pytest.mark.parametrize("lag,slew", [(0.03, 20e5), (0.03, 0.0), (0.0, 20e5), (0.0, 0.0)])
def test_regulator_solution_solves_its_ode(lag, slew):
    # The closed form (numpy and compiled) against solve_ivp of dP'/dt = sat((c − P')/τ, r)
    # (τ > 0), and against the ramp it must be for τ = 0: P'0 + clip(c − P'0, ±r s).
    p = dataclasses.replace(P, regulator=RegulatorParams(lag=lag, slew=slew))
    s = np.linspace(0.0, 0.3, 61)
    for p0, cmd in ((1e5, 5e5), (6e5, 0.5e5), (3e5, 3.02e5)):
        closed = dynamics.regulator_pressure(p0, cmd, s, p)
        kernel = [fast.regulator_pressure(p0, cmd, si, lag, slew) for si in s]
        assert_allclose(kernel, closed, rtol=1e-13, atol=1e-7)
        if lag > 0.0:
            # a kink where the ramp ends: the breakpoint keeps DOP853 from straddling it
            kink = ((abs(cmd - p0) - slew * lag) / slew,) if slew else ()
            ode = integrate_reference(
                lambda t, y, c=cmd: np.atleast_1d(dynamics.regulator_rate(y[0], c, p)), s, [p0],
                rtol=1e-12, atol=1e-6, breakpoints=kink)[:, 0]
            assert_allclose(closed, ode, rtol=1e-9, atol=1e-3)  # 1e-3 Pa of 1e5 Pa
        elif slew > 0.0:
            assert_allclose(closed, p0 + np.clip(cmd - p0, -slew * s, slew * s), rtol=1e-14)
        else:
            assert_allclose(closed, cmd)


def _reference_period(y0, old, new, t_sw, f_ext, dt, params):
    """solve_ivp of the full plant (Eq. 15, regulator ODE, friction) over one control period
    with the delayed command switching from ``old`` to ``new`` at ``t_sw``."""
    def rhs(t, y):
        cmd = old if t < t_sw else new
        return dynamics.plant_rhs(y, np.array([*cmd, f_ext]), params)

    return integrate_reference(rhs, [0.0, dt], y0, rtol=1e-13, atol=1e-12,
                               breakpoints=(t_sw,))[-1]


@pytest.mark.parametrize("t_sw", [0.0, 0.0037, 0.0061])
def test_plant_step_with_every_effect_is_rk4_of_the_reference_ode(t_sw):
    # Lag, slew limit, braid and slider friction on, and the delayed command switching inside
    # the period: the compiled step against DOP853 on plant_rhs. The pressures are exact
    # (closed form, 1e-9 relative: solve_ivp's tolerance across the slew kink); (X, V) carry
    # RK4's error, below 1e-9 m and 1e-8 m/s at 2 substeps (measured ≤ 1.3e-10 m: a thousand
    # times inside the env's 1e-6 m budget) and smaller at 4. (No clean h⁴ ratio here: the
    # steps are split at the switch and the ramp's end, and those pieces do not halve.)
    c = fast.pack(EFFECTS)
    y0 = np.array([0.8, 0.05, 3e5, 0.5e5])
    old, new = (2.9e5, 0.6e5), (3.6e5, 0.3e5)
    ref = _reference_period(y0, old, new, t_sw, 2.0, 0.01, EFFECTS)
    errs = []
    for sub in (2, 4):
        got = np.array(fast.plant_step(*y0, *old, *new, t_sw, 2.0, 0.01, c, sub))
        assert_allclose(got[2:], ref[2:], rtol=1e-9)
        errs.append(np.abs(got[:2] - ref[:2]))
    assert np.all(errs[0] < np.array([1e-9, 1e-8]))
    assert np.all(errs[1] < errs[0])
