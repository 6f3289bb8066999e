"""Feedforward (Eq. 16), stiffness (Eq. 23), stiffness design (Eq. 25) and feasibility."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from mpa_gym.analysis.simulate import simulate
from mpa_gym.design import (
    ConstantStiffness,
    FeedforwardDesign,
    FlexorPattern,
    InfeasibleDesignError,
    Reference,
    StiffnessEnvelope,
    StiffnessProfile,
    affine_in_pf,
    affine_in_pressures,
    constant_flexor,
    feasible_stiffness_range,
    joint_stiffness,
    mode_pattern,
    stiffness_sweep,
)
from mpa_gym.model import ground_force
from mpa_gym.model.dynamics import force_terms
from mpa_gym.model.params import BAR
from mpa_gym.model.params import DEFAULT_PARAMS as P

REF = Reference()
T = np.linspace(0.0, 3.0, 601)  # 5 ms grid over one period
W = 2 * np.pi / 3.0


def designs():
    yield "pf_const", FeedforwardDesign(REF, flexor=constant_flexor(0.5))
    for m in (1, 2, 3):
        yield f"mode{m}", FeedforwardDesign(REF, flexor=mode_pattern(m))
    for kind in ("kmax", "kmin"):
        yield kind, FeedforwardDesign(REF, stiffness=StiffnessEnvelope(kind, REF))
    # feasible constant k̂ along this reference lies in [717, 1093] N/m (feasible_stiffness_range)
    yield "k_const", FeedforwardDesign(REF, stiffness=ConstantStiffness(900.0))


@pytest.mark.parametrize(("name", "design"), list(designs()))
def test_eq16_pressures_balance_the_reference_dynamics(name, design):
    # Eq. (15) on the reference: F(X̂, V̂, P'_e, P'_f) = m (dV̂/dt + g) at every time.
    pe, pf = design.pressures(T).T
    F = ground_force(REF.position(T), REF.velocity(T), pe, pf, P)
    assert_allclose(F, P.leg.m * (REF.acceleration(T) + P.leg.g), rtol=1e-12)


@pytest.mark.parametrize("scenario", ["nominal", "kmax", "kmin"])
def test_eq16_round_trip_plant_driven_by_the_design_tracks_the_reference(scenario):
    # Forward map (RK4 plant) undoes the inverse map (Eq. 16): from the reference's initial state
    # the plant stays on X̂ to the integrator's accuracy (< 1e-6 m, test_dynamics) over 30 s.
    r = simulate(scenario)
    assert np.max(np.abs(r.x - r.x_ref)) < 1e-6


@pytest.mark.parametrize("kind", ["kmax", "kmin"])
def test_eq25_round_trip_designed_pressures_give_back_k_hat(kind):
    target = StiffnessEnvelope(kind, REF)
    s = FeedforwardDesign(REF, stiffness=target).sample(T)
    assert_allclose(s.k, target(T), rtol=1e-9)
    assert_allclose(joint_stiffness(s.x_ref, s.v_ref, s.pe, s.pf, P), target(T), rtol=1e-9)


def test_eq25_round_trip_for_constant_and_profile_targets():
    ts = np.linspace(0.0, 3.0, 13)
    lo, hi = feasible_stiffness_range(REF.position(ts), REF.velocity(ts), REF.acceleration(ts))
    for target in (ConstantStiffness(900.0),
                   StiffnessProfile(tuple(ts), tuple(0.5 * (lo + hi)), 3.0)):
        d = FeedforwardDesign(REF, stiffness=target).require_feasible()
        assert_allclose(d.sample(T).k, target(T), rtol=1e-9)


def test_k_and_pe_are_affine_in_pf():
    x, v, a = REF.position(T), REF.velocity(T), REF.acceleration(T)
    c = affine_in_pf(x, v, a, P)
    for pf_bar in (0.3, 1.7, 4.2):
        d = FeedforwardDesign(REF, flexor=constant_flexor(pf_bar))
        s = d.sample(T)
        assert_allclose(s.pe, c.e0 + c.e1 * pf_bar * BAR, rtol=1e-10)
        assert_allclose(s.k, c.k0 + c.k1 * pf_bar * BAR, rtol=1e-10)


def _phase_corr(design):
    s = design.sample(T)
    return np.corrcoef(s.pe, s.pf)[0, 1]


def test_table1_modes_phase_relations():
    # Sec. 4.1: modes 1 and 3 give in-phase P'_e/P'_f, mode 2 anti-phase.
    assert _phase_corr(FeedforwardDesign(REF, flexor=mode_pattern(1))) > 0.9
    assert _phase_corr(FeedforwardDesign(REF, flexor=mode_pattern(2))) < -0.9
    assert _phase_corr(FeedforwardDesign(REF, flexor=mode_pattern(3))) > 0.9


def test_mode3_needs_lower_peak_pe_than_mode1_and_is_antiphase_with_the_reference():
    s1 = FeedforwardDesign(REF, flexor=mode_pattern(1)).sample(T)
    s3 = FeedforwardDesign(REF, flexor=mode_pattern(3)).sample(T)
    assert s3.pe.max() < s1.pe.max()
    assert np.corrcoef(s3.pe, s3.x_ref)[0, 1] < -0.9
    assert np.corrcoef(s3.pf, s3.x_ref)[0, 1] < -0.9


AMPS = np.linspace(-0.4, 0.4, 9) * BAR


def test_fig9_stiffness_peaks_at_top_of_reference_for_every_amplitude():
    k = stiffness_sweep(REF, 0.4 * BAR, AMPS, T, P)
    t_peak = T[np.argmax(k, axis=1)]
    assert_allclose(t_peak, 0.75, atol=0.05)  # top of X̂ at T/4; grid 5 ms, paper "≈ 0.8 s"


def test_fig9_stiffness_lowest_in_second_half_period():
    k = stiffness_sweep(REF, 0.4 * BAR, AMPS, T, P)
    t_min = T[np.argmin(k, axis=1)]
    assert np.all((t_min > 1.5) & (t_min < 3.0))
    # Near the bottom of X̂ (2.25 s) k is flat (at A_f = 0 it changes < 1 % over ±0.2 s), so the
    # arg-min is located to ±0.1 s; the paper reads "t ≈ 2.3 s" off its Fig. 9.
    assert_allclose(t_min[AMPS >= 0], 2.25, atol=0.1)


def test_fig9_extremes_spread_with_af_and_larger_pf0_raises_k():
    k = stiffness_sweep(REF, 0.4 * BAR, AMPS, T, P)
    spread = k.max(axis=0) - k.min(axis=0)
    i_top, i_zero = np.argmin(np.abs(T - 0.75)), np.argmin(np.abs(T - 1.5))
    assert spread[i_zero] < 1e-9 * k.max()  # sin ωt = 0: every A_f gives the same P'_f
    assert spread[i_top] > 0.1 * k[:, i_top].mean()  # the spread is widest at the extremes
    k_low = stiffness_sweep(REF, 0.4 * BAR, [0.0], T, P)[0]
    k_high = stiffness_sweep(REF, 0.8 * BAR, [0.0], T, P)[0]
    assert np.all(k_high > k_low)


def test_fig11_envelopes_bound_the_sweep_and_touch_it():
    k = stiffness_sweep(REF, 0.4 * BAR, AMPS, T, P)
    kmax, kmin = StiffnessEnvelope("kmax", REF)(T), StiffnessEnvelope("kmin", REF)(T)
    assert_allclose(kmax, k.max(axis=0), rtol=1e-12)
    assert_allclose(kmin, k.min(axis=0), rtol=1e-12)
    assert np.all(kmax >= kmin)
    # k is affine in A_f, so the envelope is reached at A_f = ±P'_f0 (the sweep's ends).
    assert_allclose(kmax, np.maximum(k[0], k[-1]), rtol=1e-12)


def test_feasibility_reports_time_pressure_and_amount():
    d = FeedforwardDesign(REF, stiffness=ConstantStiffness(2000.0))
    rep = d.feasibility(p_max=7 * BAR)
    assert not rep.feasible
    v = rep.violations[0]
    assert v.quantity in ("P'_e", "P'_f")
    assert 0.0 <= v.t_worst <= 3.0 and v.amount > 0
    # the reported worst value is the design's own value at that time
    pe, pf = d.pressures(v.t_worst)
    assert v.value == pytest.approx(pe if v.quantity == "P'_e" else pf, rel=1e-12)
    assert "bar" in v.describe() and "t = " in v.describe()


def test_infeasible_k_hat_raises_naming_the_feasible_range():
    d = FeedforwardDesign(REF, stiffness=ConstantStiffness(2000.0))
    with pytest.raises(InfeasibleDesignError, match=r"k̂ = 2000.0 N/m, allowed \[") as e:
        d.require_feasible()
    assert "outside [0, 7] bar" in str(e.value)


def test_feasible_stiffness_range_edges_hit_the_pressure_limits():
    x, v, a = REF.position(T), REF.velocity(T), REF.acceleration(T)
    lo, hi = feasible_stiffness_range(x, v, a, P, 7 * BAR)
    assert np.all(lo < hi)
    for edge in (lo, hi):
        s = FeedforwardDesign(REF, stiffness=StiffnessProfile(tuple(T), tuple(edge), 3.0)).sample(T)
        # at each edge one pressure sits on a bound (0 or 7 bar) and neither is outside
        on_bound = np.minimum.reduce([np.abs(s.pe), np.abs(s.pe - 7 * BAR), np.abs(s.pf),
                                      np.abs(s.pf - 7 * BAR)])
        assert np.all(on_bound < 1e-6 * BAR)
        assert np.all((s.pe > -1e-6) & (s.pe < 7 * BAR + 1e-6))
        assert np.all((s.pf > -1e-6) & (s.pf < 7 * BAR + 1e-6))


def test_default_designs_are_feasible():
    for _, d in designs():
        assert d.feasibility().feasible, d.feasibility().describe()


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"mean": -1e5}, "pf_mean_bar"), ({"mean": 1e5, "amp": 2e5}, "pf_amp_bar"),
     ({"mean": float("nan")}, "pf_mean_bar"), ({"period": 0.0}, "period_s")],
)
def test_bad_flexor_pattern_names_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        FlexorPattern(**kwargs)


def test_bad_reference_names_field():
    with pytest.raises(ValueError, match=r"reference.amp_m=-0.1 m is outside the allowed range"):
        Reference(amp=-0.1)
    with pytest.raises(ValueError, match="x0_m"):
        FeedforwardDesign(Reference(x0=0.9, amp=0.1), flexor=constant_flexor(0.5))


def test_mode_must_be_one_of_table1():
    with pytest.raises(ValueError, match=r"mode=4 is not one of Table 1's modes \[1, 2, 3\]"):
        mode_pattern(4)


def test_pressures_enter_force_and_stiffness_affinely():
    # F and k are exactly affine in (P'_e, P'_f) at fixed (X, V): the three-point coefficients
    # reproduce force_terms at arbitrary pressures (only rounding remains).
    rng = np.random.default_rng(0)
    x = rng.uniform(0.72, 0.85, 50)
    v = rng.uniform(-0.1, 0.1, 50)
    p = rng.uniform(0.0, 7.0, (50, 2)) * BAR
    c = affine_in_pressures(x, v)
    t = force_terms(x, v, p[:, 0], p[:, 1], P)
    np.testing.assert_allclose(c.F0 + np.einsum("nj,nj->n", c.J[:, 0], p), t.F,
                               rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(c.k0 + np.einsum("nj,nj->n", c.J[:, 1], p), -t.dF_dX,
                               rtol=1e-9, atol=1e-7)
