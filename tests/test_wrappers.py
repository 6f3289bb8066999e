"""Policy-side wrappers: harmonic integral features and force–stiffness action coordinates,
checked by identities (orthogonality of the harmonic basis over a period, round trips through
the nominal model's pressure Jacobian)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

import mpa_gym  # noqa: F401  (registers the env ids)
from mpa_gym.agents.learned.config import ConfigError, parse_config
from mpa_gym.agents.learned.frontend import (
    ADAPT_FLOOR_BAR,
    ADAPT_VAR_M2,
    HARMONIC_ERROR_M,
    HARMONIC_FIRST,
    HARMONIC_GAIN,
    HARMONIC_LAST,
    HARMONIC_LIMIT_M_S,
    HARMONIC_RELEASE_S,
    STATE,
    ActionSpec,
    FeatureSpec,
    Frontend,
    adapt_time_constant,
    new_state,
)
from mpa_gym.agents.learned.policies import LearnedPolicy
from mpa_gym.agents.learned.wrappers import (
    ForceStiffnessAction,
    ForceStiffnessVectorAction,
    TrackingErrorObservation,
    TrackingErrorVectorObservation,
)
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.analysis.simulate import whole_periods
from mpa_gym.design import affine_in_pressures
from mpa_gym.model.params import BAR
from mpa_gym.task.contract import OBS_KREF_SCALE

SHORT = {"name": "short", "duration_s": 6.0, "plant": {"extra_mass_kg": 1.0}}


def _error_obs(e, phi):
    """The env's observations (n, 9) with tracking error ``e`` (X = 0, X̂ = e) at phase φ."""
    obs = np.zeros((np.size(phi), 9), dtype=np.float32)
    obs[:, 2], obs[:, 4], obs[:, 5] = e, np.sin(phi), np.cos(phi)
    return obs


# The kernels take the env's float32 observation: e and the basis sin hφ, cos hφ each carry
# a rounding of 2^-24 relative, so an integral over T of |e| ≤ 5 mm is off by at most
# T · 5e-3 · 3 · 6e-8 ≈ 3e-9 m s (the exact sums below are ~1e-3).
INTEGRAL_ATOL = 5e-9


def test_harmonic_integrals_are_fourier_coefficients_over_a_period():
    # e = c0 + c1 sin φ + c2 cos φ + c3 sin 2φ + c4 cos 2φ integrated over one period T with step
    # dt: I_0 = c0 T, I_s1 = c1 T/2, I_c1 = c2 T/2, I_s2 = c3 T/2, I_c2 = c4 T/2 (orthogonality;
    # the rectangle rule is exact for trigonometric polynomials of degree < N on N equispaced
    # points). An episode's first observation is not integrated (its integrals are zero), so
    # every step here continues the zero record.
    T, n = 3.0, 300
    c0, c1, c2, c3, c4 = 1e-3, -2e-3, 0.5e-3, 0.7e-3, -0.4e-3
    front = Frontend(FeatureSpec(harmonics=2, limit_m_s=1.0), None, T / n)
    state = new_state(1)
    for i in range(n):
        phi = 2 * np.pi * i / n
        e = c0 + c1 * np.sin(phi) + c2 * np.cos(phi) + c3 * np.sin(2 * phi) + \
            c4 * np.cos(2 * phi)
        front.observe(_error_obs(e, phi), state, False)
    np.testing.assert_allclose(state["integ"][0],
                               [c0 * T, c1 * T / 2, c2 * T / 2, c3 * T / 2, c4 * T / 2, 0.0,
                                0.0, 0.0, 0.0, 0.0, 0.0], rtol=0, atol=INTEGRAL_ATOL)


def test_remodulated_integrals_are_the_resonant_output_and_its_quadrature():
    # after integrating e = c1 sin φ + c2 cos φ over one period T, (I_s1, I_c1) = (c1, c2) T/2,
    # so the remodulated pair is R(φ) = I_s1 sin φ + I_c1 cos φ = (T/2) e(φ), in phase with the
    # error (a resonant integrator's output), and Q(φ) = (T/2) e(φ + π/2), a quarter period
    # ahead. Read at zero error, which leaves the integrals as they are.
    T, n = 3.0, 300
    c1, c2 = -2e-3, 0.5e-3
    front = Frontend(FeatureSpec(harmonics=1, remodulate=True, errors_only=True,
                                 limit_m_s=1.0), None, T / n)
    state = new_state(1)
    for i in range(n):
        phi = 2 * np.pi * i / n
        front.observe(_error_obs(c1 * np.sin(phi) + c2 * np.cos(phi), phi), state, False)
    for phi in np.linspace(0, 2 * np.pi, 7):
        f = front.observe(_error_obs(0.0, phi), state.copy(), False)[0]
        assert f.shape == (2 + 3 + 2,)  # e, ė, I_0, I_s1, I_c1, R_1, Q_1
        e = c1 * np.sin(phi) + c2 * np.cos(phi)
        e_lead = c1 * np.sin(phi + np.pi / 2) + c2 * np.cos(phi + np.pi / 2)
        # the integrals' error, and the float32 features' rounding (6e-8 of ≤ 3e-3)
        np.testing.assert_allclose(f[-2:], [T / 2 * e, T / 2 * e_lead], rtol=0,
                                   atol=2 * INTEGRAL_ATOL)


def test_an_episode_starts_from_the_zero_record():
    # an episode's first observation restarts every field of the record (integrals, previous
    # action, each of the stiffness estimator's) but the rig's delays, and is not integrated;
    # the features then show zero integrals and previous action
    front = Frontend(FeatureSpec(harmonics=2, previous_action=True), None, 0.01)
    state = new_state(3)
    for name in STATE.names:  # every field away from its start
        state[name] = 1
    feats = front.observe(_error_obs(1e-3, np.array([0.1, 0.2, 0.3])), state,
                          np.array([True, False, True]))
    for name in STATE.names:
        if name != "delay_s":
            np.testing.assert_array_equal(state[name][[0, 2]], new_state(2)[name])
    assert np.all(state["delay_s"] == 1.0)  # the rig's, kept
    assert np.all(feats[[0, 2], 9 + 2:] == 0.0) and np.all(feats[1, 9 + 2:] != 0.0)
    assert np.all(feats[:, 9] == np.float32(1e-3))  # the error itself is there


def test_feature_and_map_misuse_is_named():
    with pytest.raises(ValueError, match=r"remodulate=True needs harmonics >= 1"):
        FeatureSpec(remodulate=True)
    with pytest.raises(ValueError, match=r"errors_only=1 must be true or false"):
        FeatureSpec(errors_only=1)
    # the map needs X̂ and k̂: over errors-only features it takes them from the observation
    # wrapper beneath, and says so when another wrapper sits in between, whatever the width
    for feats in ({"errors_only": True},
                  {"errors_only": True, "harmonics": 1, "remodulate": True,
                   "previous_action": True}):  # 9 columns, as many as the env's
        inner = TrackingErrorObservation(gym.make("MPALegResidual-v0"), **feats)
        with pytest.raises(ValueError, match=r"needs the env's observation .* has shape"):
            ForceStiffnessAction(gym.wrappers.TransformReward(inner, lambda r: r))


def test_integrals_are_clipped_to_the_anti_windup_limit():
    obs = _error_obs(0.5, 0.0)  # a 0.5 m error at φ = 0
    front = Frontend(FeatureSpec(harmonics=1, limit_m_s=0.02), None, 0.01)
    state = new_state(1)
    for _ in range(2):
        front.observe(obs, state, False)
    np.testing.assert_array_equal(state["integ"][0, :3], [0.01, 0.0, 0.01])
    for _ in range(10):
        front.observe(obs, state, False)
    np.testing.assert_array_equal(state["integ"][0, :3], [0.02, 0.0, 0.02])


def test_force_stiffness_action_round_trips_through_the_nominal_model():
    # the residual it returns changes the nominal model's F by a_F·force_N and k by
    # a_k·rel·k̂ at the reference position (inside the clip range)
    rng = np.random.default_rng(2)
    obs = np.zeros((20, 9), dtype=np.float32)  # the env's observations
    obs[:, 2] = rng.uniform(0.78, 0.82, 20)
    obs[:, 8] = rng.uniform(0.4, 0.6, 20)  # k̂ [kN/m]
    x_ref, k_ref = obs[:, 2].astype(float), obs[:, 8].astype(float) * 1000.0
    a = rng.uniform(-0.5, 0.5, (20, 2))
    scale = 1.5
    front = Frontend(None, ActionSpec(force_N=20.0, stiffness_rel=0.3), 0.01, scale)
    res = front.act(a, obs, new_state(20))
    assert res.dtype == np.float32 and np.all(np.abs(res) < 1.0)  # not clipped
    J = affine_in_pressures(x_ref, np.zeros(20)).J
    dp = res.astype(float) * scale * BAR
    dF, dk = np.einsum("nij,nj->ni", J, dp).T
    # float32 actions: 6e-8 relative of a residual ≤ 1.5 bar
    np.testing.assert_allclose(dF, a[:, 0] * 20.0, atol=1e-4)
    np.testing.assert_allclose(dk, a[:, 1] * 0.3 * k_ref, atol=1e-3)
    # a force correction alone leaves the nominal stiffness unchanged
    res_f = front.act(np.c_[a[:, 0], np.zeros(20)], obs, new_state(20))
    dk_f = np.einsum("nj,nj->n", J[:, 1], res_f.astype(float) * scale * BAR)
    np.testing.assert_allclose(dk_f, 0.0, atol=1e-3)


def test_zero_force_stiffness_action_is_the_feedforward_expert():
    env = ForceStiffnessAction(gym.make("MPALegResidual-v0", task={"episode_s": 0.5}))
    plain = gym.make("MPALegResidual-v0", task={"episode_s": 0.5})
    o1, _ = env.reset(seed=1)
    o2, _ = plain.reset(seed=1)
    for _ in range(50):
        o1, r1, *_ = env.step(np.zeros(2))
        o2, r2, *_ = plain.step(np.zeros(2))
        np.testing.assert_array_equal(o1, o2)
        assert r1 == r2


def test_force_stiffness_action_needs_the_residual_env_and_valid_actions():
    with pytest.raises(ValueError, match="needs MPALegResidual-v0"):
        ForceStiffnessAction(gym.make("MPALeg-v0"))
    with pytest.raises(ValueError, match=r"force_N=-1 must be a number in \(0, 200\]"):
        ForceStiffnessAction(gym.make("MPALegResidual-v0"), force_N=-1)
    env = ForceStiffnessAction(gym.make("MPALegResidual-v0"))
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="must be finite"):
        env.step(np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        env.step(np.zeros(3))


@pytest.mark.parametrize(
    ("harmonics", "previous_action", "mask", "fine", "errors_only", "remod", "adapt", "hf"),
    [(0, False, False, None, False, False, None, None),
     (1, True, False, None, False, False, None, None),
     (2, True, True, 1e-3, False, True, None, None),
     (0, False, True, 5e-4, False, False, None, None),
     (1, True, False, 5e-4, True, True, None, None),
     (1, True, False, None, True, True, 0.05, None),
     (1, True, False, None, True, True, 0.05, 1.0)])
def test_wrappers_agree_single_and_vector(harmonics, previous_action, mask, fine, errors_only,
                                          remod, adapt, hf):
    # observation features and action coordinates (with the stiffness estimator and the
    # harmonic force correction: their state restarts with each episode), across a same-step
    # autoreset
    kw = {"scenario": SHORT, "task": {"episode_s": 0.3}}
    feats = {"harmonics": harmonics, "previous_action": previous_action, "mask_pressures": mask,
             "fine_error_m": fine, "errors_only": errors_only, "remodulate": remod}
    single = ForceStiffnessAction(TrackingErrorObservation(
        gym.make("MPALegResidual-v0", **kw), **feats), stiffness_adapt_s=adapt,
        harmonic_force_N=hf)
    vec = ForceStiffnessVectorAction(TrackingErrorVectorObservation(gym.make_vec(
        "MPALegResidual-v0", num_envs=2, vectorization_mode="vector_entry_point", **kw),
        **feats), stiffness_adapt_s=adapt, harmonic_force_N=hf)
    m = 1 + 2 * harmonics
    b = 0 if errors_only else 9  # the env's observation, or nothing of it
    r = 2 * harmonics if remod else 0  # R_h, Q_h last
    d = b + 2 + m + (2 if previous_action else 0) + (1 if fine else 0) + r
    so, _ = single.reset(seed=4)
    vo, _ = vec.reset(seed=4)
    assert so.shape == (d,) and vo.shape == (2, d)
    assert single.observation_space.contains(so)
    assert vec.single_observation_space.contains(vo[0])
    np.testing.assert_array_equal(so, vo[0])
    rng = np.random.default_rng(1)
    charged = False  # the correction's integrals moved
    for _ in range(45):  # crosses the 30-step episode end
        a = rng.uniform(-1, 1, (2, 2))
        env_obs = single.env.env_obs  # the map works at the env's X̂ and k̂, shown or not
        applied = single.frontend.act(np.clip(a[:1], -1, 1), env_obs, single.state.copy())[0]
        so, _, te, tr, _ = single.step(a[0])
        vo, _, _, _, vinfo = vec.step(a)
        env_obs = single.env.env_obs
        e = env_obs[2] - env_obs[0]
        assert so[b] == np.float32(e) and so[b + 1] == np.float32(env_obs[3] - env_obs[1])
        if not errors_only:
            assert np.all(so[6:8] == 0.0) == mask  # measured pressures hidden, or not
        if previous_action:  # the residual the env applied, in its action units
            np.testing.assert_array_equal(so[b + 2 + m:b + 4 + m], applied)
        if fine:  # the error again, clipped to ±fine
            assert so[d - r - 1] == np.float32(np.clip(e, -fine, fine))
        charged = charged or bool(np.any(single.state["harm"][0] != 0.0))
        if te or tr:
            np.testing.assert_array_equal(so, vinfo["final_obs"][0])
            so, _ = single.reset()
            assert not np.any(so[b + 2:])  # integrals and previous action restart
            # the action map's record restarts too, the autoreset row of the vector's as well
            for st in (single.state[0], vec.state[0]):
                assert not np.any(st["harm"]) and st["harm_env_m"] == 0.0
                assert not st["est_started"]
        np.testing.assert_array_equal(so, vo[0])
    assert np.all(np.any(vo[:, b + 2:b + 2 + m] != 0.0, axis=0))  # every integral moves
    assert charged == (hf is not None)


def test_rate_penalty_charges_the_action_change_and_restarts_each_episode():
    # r(w) = r(0) − w |a_t − a_{t−1}|², a_{−1} = 0 at every episode's first step; actions are
    # taken as the env applies them (clipped to [−1, 1]); the vector wrapper agrees across its
    # same-step autoreset
    w = 2.5
    kw = {"scenario": SHORT, "task": {"episode_s": 0.3}}
    plain = ForceStiffnessAction(gym.make("MPALegResidual-v0", **kw))
    pen = ForceStiffnessAction(gym.make("MPALegResidual-v0", **kw), rate_penalty=w)
    vec = ForceStiffnessVectorAction(gym.make_vec(
        "MPALegResidual-v0", num_envs=2, vectorization_mode="vector_entry_point", **kw),
        rate_penalty=w)
    plain.reset(seed=3)
    pen.reset(seed=3)
    vec.reset(seed=3)
    rng = np.random.default_rng(2)
    prev = np.zeros(2)
    for _ in range(70):  # two episode ends (30 steps each)
        a = rng.uniform(-1.3, 1.3, (2, 2))
        _, r0, te, tr, _ = plain.step(a[0])
        _, r1, *_ = pen.step(a[0])
        _, rv, *_ = vec.step(a)
        applied = np.clip(a[0], -1, 1)
        assert r1 == pytest.approx(r0 - w * np.sum((applied - prev) ** 2), rel=1e-12, abs=1e-12)
        assert rv[0] == pytest.approx(r1, rel=1e-12, abs=1e-12)
        prev = applied
        if te or tr:
            plain.reset()
            pen.reset()
            prev = np.zeros(2)
    with pytest.raises(ValueError, match=r"rate_penalty=-1 must be a number in \[0, 100\]"):
        ForceStiffnessAction(gym.make("MPALegResidual-v0"), rate_penalty=-1)


def _estimate(slope, t_end, kick=None, tau=3.0, k_ref=545.0, damping=0.0, error_lag=None,
              velocity=False):
    """â_k of the stiffness estimator fed ΔF = slope·(X̂ − x0) + damping·V̂ + 5 N along the
    20 mm, 3 s reference, and its state. Tracking is exact, or with ``error_lag`` = λ the
    error is 1 mm·|sin(φ − λ)| (largest just after each reversal); ``kick`` = (t0, t1, e):
    from t0 to t1 the tracking error is e and ΔF swings ±20 N at 5 Hz. ``velocity``: the
    estimator regresses on X̂ and V̂ (``stiffness_adapt_velocity``)."""
    dt, w = 0.01, 2 * np.pi / 3.0
    obs = np.zeros((1, 9), dtype=np.float32)
    obs[0, 8] = k_ref / 1000.0  # k̂ [kN/m]
    front = Frontend(None, ActionSpec(force_N=20.0, stiffness_rel=0.3, stiffness_adapt_s=tau,
                                      stiffness_adapt_velocity=velocity), dt, 1.0)
    state = new_state(1)
    a_k = 0.0
    for i in range(round(t_end / dt)):
        t = i * dt
        x_ref, v_ref = 0.8 + 0.02 * np.sin(w * t), 0.02 * w * np.cos(w * t)
        e = 0.0 if error_lag is None else 1e-3 * abs(np.sin(w * t - error_lag))
        obs[0, 2], obs[0, 3], obs[0, 0] = x_ref, v_ref, x_ref - e
        dF = slope * (x_ref - 0.8) + damping * v_ref + 5.0
        if kick is not None and kick[0] <= t < kick[1]:
            obs[0, 0] = x_ref - kick[2]
            dF = 20.0 * np.sign(np.sin(2 * np.pi * 5.0 * t))
        a_k = front.estimate(np.array([dF / 20.0]), obs, state)[0]
    return a_k, state


@pytest.mark.parametrize("slope", [34.0, -4.4, 0.0, 80.0])
def test_stiffness_estimator_is_the_slope_of_the_force_correction(slope):
    # ΔF = s (X̂ − x0) + c: whatever the offset c, ΔF minus its low-passed mean is s times
    # X̂ minus its own (one filter, a linear map), so the covariance is s·v and the estimate
    # s·v/(v + v₀), v X̂'s variance about its low-passed mean: (A²/2)·(ωτ)²/(1 + (ωτ)²).
    # â_k = −that/(rel k̂) (the policy's own a_k, 0.7 here, is replaced). After 40 s (13 τ)
    # the start has decayed (e^-13 · 13 ≈ 3e-5); the 2ω ripple of the product passes two
    # low-passes, each ≈ 1/(2ωτ) = 0.08, so ≈ 0.6 % of the slope: 1 % of it, plus 1e-3.
    a_k, _ = _estimate(slope, 40.0)
    wt = 2 * np.pi / 3.0 * 3.0
    v = 0.02 ** 2 / 2 * wt ** 2 / (1 + wt ** 2)
    expected = -slope * v / (v + ADAPT_VAR_M2) / (0.3 * 545.0)
    assert a_k == pytest.approx(expected, rel=0.01, abs=1e-3)
    # past the clip: ±rel·k̂ is the largest correction it makes (reached as the start decays)
    assert _estimate(400.0, 40.0)[0] == pytest.approx(-1.0, abs=1e-4)


def test_stiffness_estimator_ignores_a_kick_and_restarts_each_episode():
    # a 0.5 s transient with a 20 mm error and ΔF swinging ±20 N: each update's weight is
    # w = 1/(1 + 20²), so the regression's statistics move by under 0.5 %; the same swing at
    # zero error moves the covariance by a third (the check can fail). The rest of the rate
    # returns the estimate towards zero: over the kick it is the settled one times
    # e^(−(1 − w) 0.5 s / τ), to what the weight still learns (0.5 % of it), and once the
    # leg tracks again it is back within 1 % of the settled one after 10 s (3 τ: e^-3 of the
    # 15 % dip is 0.7 %).
    settled, s0 = _estimate(34.0, 40.0)
    kicked, s1 = _estimate(34.0, 40.5, kick=(40.0, 40.5, 0.02))
    _, s2 = _estimate(34.0, 40.5, kick=(40.0, 40.5, 0.0))
    for name in ("est_cov_Fq", "est_var_q", "est_force_N"):
        assert s1[name][0] == pytest.approx(s0[name][0], rel=5e-3)
    assert abs(s2["est_cov_Fq"][0] - s0["est_cov_Fq"][0]) > 0.3 * abs(s0["est_cov_Fq"][0])
    assert kicked == pytest.approx(settled * np.exp(-0.5 / 3.0 * (1.0 - 1.0 / 401.0)),
                                   rel=5e-3)
    assert _estimate(34.0, 50.5, kick=(40.0, 40.5, 0.02))[0] == pytest.approx(settled,
                                                                              rel=0.01)
    # a zero state (an episode's start) starts from the first observation: no estimate yet
    a_k, state = _estimate(34.0, 0.01)
    assert a_k == 0.0 and state["est_started"][0] and state["est_q_mean"][0] == np.float32(0.8)


@pytest.mark.parametrize("slope, damping", [(-40.0, 100.0), (-40.0, -100.0), (34.0, 100.0)])
def test_velocity_regression_keeps_the_slope_where_the_weights_follow_the_phase(slope, damping):
    # An error that peaks just after each reversal (friction's, slew's) makes the updates'
    # weights 1/(1 + (e/1 mm)²) uneven within a period: under them X̂ and V̂ are no longer
    # orthogonal, and ΔF's part c·V̂ (a friction or damping correction; 100 N s/m is 4.2 N at
    # this reference's speed) leaks into X̂'s slope. On X̂ alone the estimate moves by more
    # than half the slope (the check can fail: the rig file's symptom, -40 N/m read as ~0).
    # Regressed on X̂ and V̂ it moves by what two exact effects leave, and no more:
    # - the update pairs X̂ with last step's ΔF, and c·V̂(t − dt) = c·V̂(t) + c·ω²·dt·(X̂ − x0)
    #   to first order, an X̂ slope of exactly c·ω²·dt;
    # - V̂'s regulariser v₀ᵥ keeps a share v₀ᵥ/(vv + v₀ᵥ − c_xv²/(v + v₀)) of the X̂-only
    #   leak: 0.05 with X̂ and V̂ uncorrelated under the weights (vv = (Aω)²/2 ≈ 8.8e-4
    #   m²/s², v₀ᵥ a twentieth of it), at most 0.1 while their weighted correlation ρ² ≤ 0.5
    #   (here, with a 1 mm error, it is far below).
    # (Both reads are shrunk by the mean weight, 0.7 here, as the module docstring says; the
    # leak with them.)
    def leak(velocity):  # [N/m] how far c·V̂ moves the slope read
        def read(c):
            return -_estimate(slope, 40.0, damping=c, error_lag=0.6, velocity=velocity)[0] \
                * 0.3 * 545.0
        return abs(read(damping) - read(0.0))

    x_only = leak(False)
    assert x_only > 0.5 * abs(slope)
    assert leak(True) < abs(damping) * (2 * np.pi / 3.0) ** 2 * 0.01 + 0.1 * x_only
    # without a velocity part both read the same slope: the regression on (X̂, V̂) of a ΔF
    # that V̂ does not enter is X̂'s alone, to V̂'s regularisation (1e-3 of k̂ here)
    assert _estimate(slope, 40.0, error_lag=0.6, velocity=True)[0] == pytest.approx(
        _estimate(slope, 40.0, error_lag=0.6)[0], abs=2e-3)


def _relative_stream(relative, ratio, k_swing, t_end=40.0):
    """The estimator (``stiffness_adapt_relative`` or not) fed the 20 mm, 3 s reference with
    k̂(X̂) = 545 N/m · (1 + k_swing (X̂ − x0) / A) (the designed k̂ of the reference is a
    function of X̂ that spans 409–821 N/m: ``k_swing`` ≈ 0.35) and the ΔF that tracks a
    plant stiffer by ``ratio`` · k̂ everywhere, ΔF = ratio · ∫ k̂ dX̂ + 5 N (exact tracking).
    Returns the relative stiffness error left over the last period, (k − k̂ + Δk) / k̂ =
    ratio + Δk / k̂ with Δk = a_k · 0.3 · k̂ (what ``force_stiffness_row`` applies)."""
    dt, w, amp, k0 = 0.01, 2 * np.pi / 3.0, 0.02, 545.0
    front = Frontend(None, ActionSpec(force_N=20.0, stiffness_rel=0.3, stiffness_adapt_s=3.0,
                                      stiffness_adapt_relative=relative), dt, 1.0)
    state = new_state(1)
    obs = np.zeros((1, 9), dtype=np.float32)
    obs[0, 6], obs[0, 7] = 2.0, 0.5  # [bar] both muscles above their floor
    left = []
    n = round(t_end / dt)
    for i in range(n):
        s = np.sin(w * i * dt)
        obs[0, 0] = obs[0, 2] = 0.8 + amp * s
        obs[0, 3] = amp * w * np.cos(w * i * dt)
        k_ref = k0 * (1.0 + k_swing * s)
        obs[0, 8] = k_ref / OBS_KREF_SCALE
        # ∫ k̂ dX̂ from x0, exactly: k0 A (s + k_swing s² / 2)
        dF = ratio * k0 * amp * (s + k_swing * s * s / 2.0) + 5.0
        a_k = front.estimate(np.array([dF / 20.0]), obs, state)[0]
        if i >= n - round(3.0 / dt):
            left.append(ratio + a_k * 0.3)
    return np.array(left)


@pytest.mark.parametrize("ratio", [0.06, -0.04])
def test_the_relative_estimator_follows_a_stiffness_excess_in_proportion_to_k_ref(ratio):
    # a plant whose muscles are not the model's is stiffer by a share of k̂ along the whole
    # motion (rc on heldout_bladder: 6.0 % with 0.007 %/mm of slope against X̂). Fitted as a
    # share of k̂ (ΔF regressed on the path coordinate z = ∫ k̂ dX̂), the correction follows
    # k̂: the error left is the regulariser's shrink of the estimate, v₀/(var z + v₀) with
    # v₀ = ADAPT_VAR_M2 k̂², at most a tenth of the excess where k̂ peaks at 1.35 times its
    # mean (a twentieth at k̂'s mean; (1.35)² / 20 = 0.09), and the same all along the motion
    # to that share. Fitted in N/m, a constant Δk, the error left varies with k̂ by about
    # the excess times k_swing (0.35) across the motion (the check can fail).
    relative = _relative_stream(True, ratio, 0.35)
    assert np.all(np.abs(relative) < 0.1 * abs(ratio)), relative
    absolute = _relative_stream(False, ratio, 0.35)
    assert np.ptp(absolute) > 0.5 * abs(ratio) * 0.35
    assert np.ptp(relative) < 0.2 * np.ptp(absolute)


def test_on_a_constant_k_ref_both_estimators_apply_the_same_correction():
    # with k̂ constant, z = k̂ (X̂ − x_start) exactly (the trapezoid rule is exact), so the
    # regression on z is the one on X̂ scaled by k̂ in every moment, v₀ scaled by k̂² too: the
    # fitted share is the fitted slope / k̂ and both give the same a_k, to float64 rounding
    # over 4000 steps (measured 2e-16; starting z's mean at X̂ instead of z₀ = 0 leaves 3e-6)
    for ratio in (0.06, -0.04):
        np.testing.assert_allclose(_relative_stream(True, ratio, 0.0),
                                   _relative_stream(False, ratio, 0.0), rtol=0, atol=1e-12)
    # k̂ = 0 (no stiffness design) gives no estimate, not NaN: z stays 0 and so does its
    # variance, and the regulariser v₀ k̂² is 0 too
    front = Frontend(None, ActionSpec(stiffness_adapt_s=3.0, stiffness_adapt_relative=True),
                     0.01, 1.0)
    state = new_state(1)
    obs = np.zeros((1, 9), dtype=np.float32)
    obs[0, 6], obs[0, 7] = 2.0, 0.5
    for i in range(10):
        obs[0, 0] = obs[0, 2] = 0.8 + 0.001 * i
        assert front.estimate(np.array([0.1]), obs, state)[0] == 0.0
    assert np.isfinite(state["est_slope"][0])


def test_the_relative_estimator_forgets_a_correction_a_muscle_at_its_floor_cannot_make():
    # a muscle whose measured pressure is at its floor (under ADAPT_FLOOR_BAR) cannot realise
    # the pressures the map asks: the ΔF applied is not the ΔF the regression assumes, and
    # learning on it winds the estimate up (load_1kg_kmin, whose flexor the kmin design holds
    # at 0 bar over 15 % of the period, ran to the clip). There nothing is learned and the
    # whole rate returns the estimate to zero: exactly s (1 − dt/τ)^n over n steps, at zero
    # error and at 3 mm alike (a rate weighted by the error, 1/(1 + 3²), would decay a tenth
    # as fast: the check can fail); above the floor the same stream keeps it (the check can
    # fail).
    dt, tau, w = 0.01, 3.0, 2 * np.pi / 3.0
    for p_f, decays, err in ((0.0, True, 0.0), (0.0, True, 3e-3),
                             (ADAPT_FLOOR_BAR + 0.01, False, 0.0)):
        front = Frontend(None, ActionSpec(force_N=20.0, stiffness_rel=0.3, stiffness_adapt_s=tau,
                                          stiffness_adapt_relative=True), dt, 1.0)
        state = new_state(1)
        obs = np.zeros((1, 9), dtype=np.float32)
        obs[0, 6], obs[0, 7], obs[0, 8] = 2.0, 0.5, 0.545
        for i in range(4000):  # the estimate of a plant 6 % stiffer settles, then the floor
            s = np.sin(w * i * dt)
            obs[0, 0] = obs[0, 2] = 0.8 + 0.02 * s
            if i == 3000:
                obs[0, 7] = p_f
                settled = state["est_slope"][0]
            if i >= 3000:  # the error from the floor on
                obs[0, 0] = obs[0, 2] - err
            dF = 0.06 * 545.0 * 0.02 * s
            a_k = front.estimate(np.array([dF / 20.0]), obs, state)[0]
        assert settled == pytest.approx(0.06, rel=0.1)
        if decays:
            assert state["est_slope"][0] == pytest.approx(settled * (1 - dt / tau) ** 1000,
                                                          rel=1e-9)
            assert a_k == pytest.approx(-state["est_slope"][0] / 0.3, rel=1e-12)
        else:
            assert state["est_slope"][0] == pytest.approx(settled, rel=0.02)


class _XOnlyRecursion:
    """The module docstring's estimator (no option), written out in Python and fed the
    kernel's stream: X̂ and the error from the observation, then the ΔF applied. ``hold``:
    the estimate held while the weight is low, the rule before it returned towards zero."""

    def __init__(self, dt, tau, span, hold=False):
        self.dt, self.tau, self.span, self.hold = dt, tau, span, hold
        self.ref = None

    def step(self, obs, applied_N):
        x, e = float(obs[0, 2]), float(obs[0, 2]) - float(obs[0, 0])
        ref = self.ref = self.ref or {"x": x, "F": 0.0, "c": 0.0, "v": 0.0, "s": 0.0,
                                      "applied": 0.0}
        al = self.dt / self.tau / (1.0 + (e / 1e-3) ** 2)
        lost = 0.0 if self.hold else self.dt / self.tau - al
        ref["x"] += al * (x - ref["x"])
        ref["F"] += al * (ref["applied"] - ref["F"])
        dx, dF = x - ref["x"], ref["applied"] - ref["F"]
        ref["c"] += al * (dF * dx - ref["c"])
        ref["v"] += al * (dx * dx - ref["v"])
        fit = min(max(ref["c"] / (ref["v"] + ADAPT_VAR_M2), -self.span), self.span)
        ref["s"] += al * (fit - ref["s"]) - lost * ref["s"]
        ref["applied"] = applied_N
        return ref["s"]  # [N/m] the slope read: â_k = −slope / span, clipped to ±1


def test_without_the_option_the_estimator_is_the_documented_x_only_recursion():
    # the module docstring's estimator, written out in Python over one stream (a ΔF with a
    # velocity part, an error that follows the phase, a start): the compiled kernel without
    # stiffness_adapt_velocity keeps the same slope to float64 rounding
    dt, tau, w = 0.01, 3.0, 2 * np.pi / 3.0
    front = Frontend(None, ActionSpec(force_N=20.0, stiffness_rel=0.3, stiffness_adapt_s=tau),
                     dt, 1.0)
    st = new_state(1)
    obs = np.zeros((1, 9), dtype=np.float32)
    obs[0, 8] = 0.545  # k̂ [kN/m], as the observation holds it (float32)
    span = 0.3 * float(obs[0, 8]) * OBS_KREF_SCALE
    ref = _XOnlyRecursion(dt, tau, span)
    for i in range(900):
        t = i * dt
        obs[0, 2], obs[0, 3] = 0.8 + 0.02 * np.sin(w * t), 0.02 * w * np.cos(w * t)
        obs[0, 0] = obs[0, 2] - 1e-3 * abs(np.sin(w * t - 0.6))
        a_F = np.clip(0.5 * np.sin(w * t + 0.3) + 0.1, -1.0, 1.0)
        a_k = front.estimate(np.array([a_F]), obs, st)[0]
        slope = ref.step(obs, a_F * 20.0)
        assert a_k == pytest.approx(min(max(-slope / span, -1.0), 1.0), rel=1e-12, abs=1e-15)
    assert abs(slope) > 1.0  # the stream moves the estimate (the check can fail)


def test_a_stiffness_read_while_the_leg_does_not_track_returns_towards_zero():
    # A leg 1.6 kg heavier than the model sags at the start (5 mm, corrected within 0.4 s) and
    # the policy's ΔF settles to the load's 15 N (time constant 0.5 s) on top of the part that
    # follows X̂, the mass error's −Δm ω² = −7 N/m. Until the low-passed mean of ΔF catches up,
    # the step correlates with X̂: two seconds in, the regression reads a stiffness excess of
    # over 50 N/m (the closed loop under 40 ms of dead time read 52-78 N/m). Then the leg does
    # not track: it stays 3 mm off the reference for 10 s (in the closed loop, a limit cycle),
    # so each update's weight is w = 1/(1 + 3²). Held while the weights are down, the rule
    # before, the estimate keeps over 80 % of the false excess (the check can fail); returned
    # towards zero by the rest of each step's rate, e^(−(1 − w) 10 s / τ) = 5 % of it, plus what
    # it still learns: under a tenth. When the leg tracks again the statistics still hold part
    # of the false read (it comes back for a few seconds: 29 N/m at 15 s), and new updates
    # replace it: within 1 N/m of the true slope times the regression's v/(v + v₀) (the first
    # estimator test) 15 s (5 τ) after.
    dt, tau, w, true = 0.01, 3.0, 2 * np.pi / 3.0, -7.0
    front = Frontend(None, ActionSpec(force_N=20.0, stiffness_rel=0.3, stiffness_adapt_s=tau),
                     dt, 1.0)
    st = new_state(1)
    obs = np.zeros((1, 9), dtype=np.float32)
    obs[0, 8] = 0.545
    span = 0.3 * float(obs[0, 8]) * OBS_KREF_SCALE
    held = _XOnlyRecursion(dt, tau, span, hold=True)
    read = {}
    for i in range(round(27.0 / dt) + 1):
        t = i * dt
        obs[0, 2], obs[0, 3] = 0.8 + 0.02 * np.sin(w * t), 0.02 * w * np.cos(w * t)
        e = 3e-3 if 2.0 < t <= 12.0 else 5e-3 * np.exp(-t / 0.25)
        obs[0, 0] = obs[0, 2] - e
        dF = true * (float(obs[0, 2]) - 0.8) + 15.0 * (1.0 - np.exp(-t / 0.5))
        a_k = front.estimate(np.array([dF / 20.0]), obs, st)[0]
        before = held.step(obs, dF)
        if i in (200, 1200, 2700):
            read[i] = (-a_k * span, before)
    assert read[200][0] > 50.0 and read[200][1] > 50.0
    assert read[1200][1] > 0.8 * read[200][1]
    assert abs(read[1200][0]) < 0.1 * read[200][0]
    wt = w * tau
    v = 0.02 ** 2 / 2 * wt ** 2 / (1 + wt ** 2)
    assert read[2700][0] == pytest.approx(true * v / (v + ADAPT_VAR_M2), abs=1.0)


@pytest.mark.parametrize("relative", [False, True])
def test_the_action_kernel_and_the_estimator_read_the_reference_velocity(relative):
    # act_row (every policy's path: training wrapper, loaded, deployed) and estimate run one
    # estimator, and with the option on it reads V̂ (the reference), not the measured V: fed
    # a stream whose V is noise, both keep the same record, bit for bit. With
    # stiffness_adapt_relative both read the same path coordinate and the same measured
    # pressures, here crossing the floor for a second in every three.
    dt, w = 0.01, 2 * np.pi / 3.0
    front = Frontend(None, ActionSpec(force_N=20.0, stiffness_rel=0.3, stiffness_adapt_s=3.0,
                                      stiffness_adapt_velocity=True,
                                      stiffness_adapt_relative=relative), dt, 1.0)
    acted, estimated = new_state(1), new_state(1)
    obs = np.zeros((1, 9), dtype=np.float32)
    obs[0, 6] = 2.0
    rng = np.random.default_rng(0)
    for i in range(600):
        t = i * dt
        obs[0, 2], obs[0, 3] = 0.8 + 0.02 * np.sin(w * t), 0.02 * w * np.cos(w * t)
        obs[0, 0], obs[0, 1] = obs[0, 2] - 1e-3 * abs(np.sin(w * t - 0.6)), rng.normal(0, 0.05)
        obs[0, 7] = 0.0 if (i // 100) % 3 == 2 else 0.5  # [bar] the flexor's pressure
        obs[0, 8] = 0.545 * (1.0 + 0.3 * np.sin(w * t))  # k̂ [kN/m]
        a = rng.uniform(-1.0, 1.0, (1, 2)).astype(np.float32)
        front.act(a, obs, acted)
        front.estimate(a[:, 0], obs, estimated)
    for field in ("est_v_ref_mps", "est_cov_N_mps", "est_cov_qv", "est_slope", "est_path_N"):
        assert acted[field][0] == estimated[field][0], field
    assert acted["est_cov_N_mps"][0] != 0.0
    assert (acted["est_path_N"][0] != 0.0) == relative


def _default_config(**action_kwargs):
    """The shipped training config, its ForceStiffnessAction kwargs updated by these."""
    raw = yaml.safe_load(open("configs/ppo_residual.yaml"))
    for wrapper in raw["MPALegResidual-v0"]["env_wrapper"]:
        for name, kwargs in wrapper.items():
            if name.endswith("ForceStiffnessAction"):
                kwargs.update(action_kwargs)
    return raw


def test_a_config_with_the_option_gives_a_policy_with_it():
    # config → parse_config → the loaded policy's front-end (what evaluate, rollout and the
    # deployed path build from a run folder)
    for on in (True, False):
        for option, field in (("stiffness_adapt_velocity", "adapt_velocity"),
                              ("stiffness_adapt_relative", "adapt_relative")):
            raw = _default_config(**{option: on})
            policy = LearnedPolicy.from_config(None, None, parse_config(raw, "cfg.yaml"))
            assert getattr(policy.action, option) is on
            assert policy.frontend.settings[0][field] == on
    # and the harmonic force correction's bound, or none
    for bound in (0.5, None):
        raw = _default_config(harmonic_force_N=bound)
        policy = LearnedPolicy.from_config(None, None, parse_config(raw, "cfg.yaml"))
        assert policy.action.harmonic_force_N == bound
        assert policy.frontend.settings[0]["harmonic"] == (bound is not None)
        assert policy.frontend.settings[0]["harmonic_force_N"] == (bound or 0.0)


def _refused_by_the_wrapper(field, out_of_range, allowed):
    """``field`` of ForceStiffnessAction refuses each value of ``out_of_range`` naming the
    range ``allowed`` (a regex), and a bool or a string as not a number."""
    for bad in out_of_range:
        with pytest.raises(ValueError, match=rf"{field}=.*allowed range {allowed}"):
            ForceStiffnessAction(gym.make("MPALegResidual-v0"), **{field: bad})
    for bad in (True, "3"):
        with pytest.raises(ValueError, match=rf"{field}=.* is not a number"):
            ForceStiffnessAction(gym.make("MPALegResidual-v0"), **{field: bad})


def test_stiffness_estimator_setting_is_checked():
    # one check for the training wrapper, LearnedPolicy and DeployedPolicy (test_inference)
    _refused_by_the_wrapper("stiffness_adapt_s", (0, -1.0, 61.0, float("nan")),
                            r"\(0, 60\] s \(or null: no estimator\)")
    assert adapt_time_constant(None) is None and adapt_time_constant(3) == 3.0
    with pytest.raises(ValueError, match=r"stiffness_adapt_velocity='yes' must be true or "
                                         r"false"):
        ForceStiffnessAction(gym.make("MPALegResidual-v0"), stiffness_adapt_s=3.0,
                             stiffness_adapt_velocity="yes")
    with pytest.raises(ValueError, match=r"stiffness_adapt_velocity=true needs "
                                         r"stiffness_adapt_s"):
        ActionSpec(stiffness_adapt_velocity=True)
    with pytest.raises(ValueError, match=r"stiffness_adapt_relative=1 must be true or false"):
        ForceStiffnessAction(gym.make("MPALegResidual-v0"), stiffness_adapt_s=3.0,
                             stiffness_adapt_relative=1)
    with pytest.raises(ValueError, match=r"stiffness_adapt_relative=true needs "
                                         r"stiffness_adapt_s"):
        ActionSpec(stiffness_adapt_relative=True)
    # run folders written before the fields read as the X̂-only estimator, in N/m, they were
    # run with
    assert ActionSpec(stiffness_adapt_s=3.0).stiffness_adapt_velocity is False
    assert ActionSpec(stiffness_adapt_s=3.0).stiffness_adapt_relative is False


def test_harmonic_force_setting_is_checked():
    # one check (ActionSpec) for the training wrapper, the config, LearnedPolicy and
    # DeployedPolicy; run folders written before the field read as without the correction
    assert ActionSpec().harmonic_force_N is None
    assert ActionSpec(harmonic_force_N=1).harmonic_force_N == 1.0
    _refused_by_the_wrapper("harmonic_force_N", (0, -1.0, 31.0, float("nan")),
                            r"\(0, 30\] N \(or null: no harmonic force correction\)")
    with pytest.raises(ConfigError, match=r"cfg\.yaml: MPALegResidual-v0\.env_wrapper: .*"
                                          r"harmonic_force_N=-2 N is outside"):
        parse_config(_default_config(harmonic_force_N=-2), "cfg.yaml")


def test_stiffness_time_constant_shorter_than_the_control_period_is_refused():
    # an update's weight is dt/τ: above 1 the low-passed variance of X̂ can turn negative, so
    # τ < dt is refused where the action map meets the control period (the env's 0.01 s)
    env = gym.make("MPALegResidual-v0")
    dt = env.unwrapped.cfg.dt_s
    with pytest.raises(ValueError, match=r"stiffness_adapt_s=0\.005 s is outside the allowed "
                                         r"range \[0\.01, 60\] s \(at least the control "
                                         r"period dt_s, or null: no estimator\)"):
        ForceStiffnessAction(env, stiffness_adapt_s=dt / 2)
    # a training config is refused at parsing, before a run folder exists, against its own
    # task's control period
    raw = _default_config(stiffness_adapt_s=0.015)
    raw["MPALegResidual-v0"]["env_kwargs"]["task"]["dt_s"] = 0.02
    with pytest.raises(ConfigError, match=r"cfg\.yaml: MPALegResidual-v0\.env_wrapper: .*"
                                          r"ForceStiffnessAction: stiffness_adapt_s=0\.015 s .*"
                                          r"\[0\.02, 60\] s"):
        parse_config(raw, "cfg.yaml")
    assert Frontend(None, ActionSpec(stiffness_adapt_s=dt), dt, 1.0).settings[0][
        "stiffness_adapt_s"] == dt  # the bound itself is allowed
    # why: on the same noisy reference, X̂'s low-passed variance stays ≥ 0 at τ = dt and
    # turns negative at τ = dt/2 (set past the check, in the kernel's settings)
    obs, _ = env.reset(seed=0)
    lowest = {}
    for tau in (dt, dt / 2):
        front = Frontend(None, ActionSpec(stiffness_adapt_s=dt), dt, 1.0)
        front.settings[0]["stiffness_adapt_s"] = tau
        st, rng, lowest[tau] = front.new_state(1), np.random.default_rng(3), np.inf
        for _ in range(300):
            raw = obs[None] + rng.normal(0.0, 0.02, (1, obs.size)).astype(np.float32)
            front.estimate(rng.uniform(-1.0, 1.0, 1), raw, st)
            lowest[tau] = min(lowest[tau], st["est_var_q"][0])
    assert lowest[dt] >= 0.0 > lowest[dt / 2]


def test_action_history_holds_the_last_actions_applied_newest_first():
    # the H actions still in flight, as the env applied them (clipped), newest first, zeros
    # before the episode's first action; single and vector agree across the autoreset
    H = 5
    kw = {"scenario": SHORT, "task": {"episode_s": 0.3}}
    feats = {"harmonics": 1, "action_history": H, "errors_only": True}
    single = TrackingErrorObservation(gym.make("MPALegResidual-v0", **kw), **feats)
    vec = TrackingErrorVectorObservation(gym.make_vec(
        "MPALegResidual-v0", num_envs=2, vectorization_mode="vector_entry_point", **kw), **feats)
    at = 2 + 3  # after e, ė and I_0, I_s1, I_c1
    so, _ = single.reset(seed=2)
    vec.reset(seed=2)
    assert so.shape == (at + 2 * H,) and single.observation_space.contains(so)
    rng = np.random.default_rng(5)
    given: list[np.ndarray] = []
    for _ in range(40):  # crosses the 30-step episode end
        a = rng.uniform(-1.2, 1.2, (2, 2)).astype(np.float32)
        so, _, te, tr, _ = single.step(a[0])
        vo, *_ = vec.step(a)
        given.insert(0, np.clip(a[0], -1, 1))
        want = np.zeros((H, 2))
        k = min(H, len(given))
        want[:k] = given[:k]
        if te or tr:
            so, _ = single.reset()
            given, want = [], np.zeros((H, 2))
        np.testing.assert_array_equal(so[at:].reshape(H, 2), want.astype(np.float32))
        np.testing.assert_array_equal(so, vo[0])


def test_previous_action_is_a_history_of_one_and_both_cannot_be_given():
    assert FeatureSpec(previous_action=True).n_actions == 1
    assert FeatureSpec(action_history=4).n_actions == 4
    with pytest.raises(ValueError, match="previous_action=True and action_history=3"):
        FeatureSpec(previous_action=True, action_history=3)
    with pytest.raises(ValueError, match=r"action_history=17 must be a whole number in \[0, 16\]"):
        FeatureSpec(action_history=17)


def test_delay_observation_carries_each_episodes_regulator_delays():
    # training: each row's features end in its own plant's (dead time, lag), a new episode's
    # after an autoreset; values drawn by the env's randomisation, never by the wrapper
    sc = {"name": "delays", "duration_s": 0.3,
          "randomize": {"pressure_dead_time_s": [0.0, 0.05], "pressure_lag_s": [0.0, 0.06]}}
    feats = {"delay_observation": True, "errors_only": True}
    vec = TrackingErrorVectorObservation(gym.make_vec(
        "MPALegResidual-v0", num_envs=3, vectorization_mode="vector_entry_point", scenario=sc,
        task={"episode_s": 0.3}), **feats)
    obs, _ = vec.reset(seed=7)
    engine = vec.env.unwrapped.engine

    def truth() -> np.ndarray:
        return np.array([(p.pressure_dead_time_s, p.pressure_lag_s) for p in engine.plants],
                        dtype=np.float32)

    first = truth()
    assert np.all(first > 0.0) and len(np.unique(first[:, 0])) == 3  # drawn, per row
    np.testing.assert_array_equal(obs[:, -2:], first)
    for _ in range(31):  # crosses the 30-step episode end
        obs, *_ = vec.step(np.zeros((3, 2), dtype=np.float32))
    assert not np.array_equal(truth(), first)  # new episodes, new plants
    np.testing.assert_array_equal(obs[:, -2:], truth())


def _leg_obs(e, phi):
    """The env's observations (n, 9) on the reference X̂ = 0.8 m with tracking error ``e``
    (X = X̂ − e) at phase φ, k̂ = 545 N/m."""
    obs = np.zeros((np.size(phi), 9), dtype=np.float32)
    obs[:, 2] = 0.8
    obs[:, 0] = 0.8 - np.asarray(e)
    obs[:, 4], obs[:, 5], obs[:, 8] = np.sin(phi), np.cos(phi), 545.0 / OBS_KREF_SCALE
    return obs


def _harmonic_reference(raw, dt):
    """The harmonic force correction as the module docstring writes it, in Python: ΔF_h per
    step and the integrals (J_s2, J_c2, J_s3, J_c3) after each."""
    env_m, J = 0.0, np.zeros(2 * (HARMONIC_LAST - HARMONIC_FIRST + 1))
    dFs, Js = [], []
    for row in raw.astype(np.float64):
        e, s1, c1 = row[2] - row[0], row[4], row[5]
        env_m = max(abs(e), env_m * (1.0 - dt / HARMONIC_RELEASE_S))
        w = dt * e / (1.0 + (env_m / HARMONIC_ERROR_M) ** 2)
        phi = np.arctan2(s1, c1)
        out = 0.0
        for j, h in enumerate(range(HARMONIC_FIRST, HARMONIC_LAST + 1)):
            J[2 * j] = np.clip(J[2 * j] + w * np.sin(h * phi), -HARMONIC_LIMIT_M_S,
                               HARMONIC_LIMIT_M_S)
            J[2 * j + 1] = np.clip(J[2 * j + 1] + w * np.cos(h * phi), -HARMONIC_LIMIT_M_S,
                                   HARMONIC_LIMIT_M_S)
            out += J[2 * j] * np.sin(h * phi) + J[2 * j + 1] * np.cos(h * phi)
        dFs.append(out)
        Js.append(J.copy())
    return np.array(dFs), np.array(Js)


def test_harmonic_force_correction_is_the_documented_integral_action():
    # the kernel against the docstring's recursion written out here, on an error with a
    # first-harmonic part, second- and third-harmonic parts and a kick's millimetres; its ΔF
    # enters the map as a force correction (the front-end without it, given a_F + ΔF/force_N,
    # answers the same action), bounded by harmonic_force_N
    dt, bound, force_N = 0.01, 0.5, 20.0
    t = np.arange(3000) * dt
    phi = 2 * np.pi * t / 3.0
    rng = np.random.default_rng(5)
    e = (2e-4 * np.sin(phi) + 1e-4 * np.sin(2 * phi + 0.3) + 5e-5 * np.cos(3 * phi)
         + 3e-3 * np.exp(-((t - 12.0) / 0.2) ** 2) + rng.normal(0.0, 2e-5, t.size))
    raw = _leg_obs(e, phi)
    on = Frontend(None, ActionSpec(force_N=force_N, harmonic_force_N=bound), dt, 2.0)
    off = Frontend(None, ActionSpec(force_N=force_N), dt, 2.0)
    dF, J = _harmonic_reference(raw, dt)
    dF = np.clip(HARMONIC_GAIN * dF, -bound, bound)
    assert 0.0 < (abs(dF) == bound).mean() < 0.5  # the bound binds, at times
    # tolerances: the observation's sin φ, cos φ are float32, |z| = 1 ± 6e-8, which the
    # kernel's recurrence raises to the third power and the reference's arctan2 does not: a
    # relative 1e-6 of the integrals' size
    st_on, st_off = on.new_state(1), off.new_state(1)
    a = rng.uniform(-0.5, 0.5, (t.size, 2))
    for k in range(t.size):
        got = on.act(a[k:k + 1], raw[k:k + 1], st_on)
        assert np.allclose(st_on["harm"][0], J[k], rtol=0, atol=1e-6 * abs(J[k]).max()), k
        shifted = a[k:k + 1].copy()
        shifted[0, 0] += dF[k] / force_N
        assert np.allclose(got, off.act(shifted, raw[k:k + 1], st_off), rtol=0, atol=1e-6), k
    # the stiffness estimator pairs X̂ with the whole ΔF applied, the correction included
    both = Frontend(None, ActionSpec(force_N=force_N, harmonic_force_N=bound,
                                     stiffness_adapt_s=3.0), dt, 2.0)
    st = both.new_state(1)
    for k in range(t.size):
        both.act(a[k:k + 1], raw[k:k + 1], st)
        applied = np.clip(a[k, 0] + dF[k] / force_N, -1.0, 1.0) * force_N
        assert abs(st["est_applied_N"][0] - applied) < 1e-6 * force_N, k


def test_harmonic_force_correction_integrals_stop_at_their_bound():
    # a steady 2ω error of a millimetre winds the integrals up to ±HARMONIC_LIMIT_M_S, where
    # the kernel holds them, as the reference does (the output is bounded far earlier)
    dt = 0.01
    phi = 2 * np.pi * np.arange(12000) * dt / 3.0  # 120 s
    raw = _leg_obs(1e-3 * np.sin(2 * phi), phi)
    _, J = _harmonic_reference(raw, dt)
    assert abs(J[-1, 0]) == HARMONIC_LIMIT_M_S  # the reference reaches the bound
    front = Frontend(None, ActionSpec(harmonic_force_N=1.0), dt, 2.0)
    st = front.new_state(1)
    for k in range(raw.shape[0]):
        front.act(np.zeros((1, 2)), raw[k:k + 1], st)
    assert np.allclose(st["harm"][0], J[-1], rtol=0, atol=1e-6 * HARMONIC_LIMIT_M_S)
    assert abs(st["harm"][0][0]) == HARMONIC_LIMIT_M_S


def test_harmonic_force_correction_barely_feeds_a_first_harmonic_error_to_the_others():
    # weighted by the error itself (as the stiffness estimator weights), w e = e / (1 + (e /
    # E)²), E = HARMONIC_ERROR_M, has a third harmonic: a first-harmonic error of amplitude E
    # charges the third harmonic's integrals at over a tenth of the rate of a pure third
    # harmonic a tenth its size. The update's weight follows the error's envelope instead;
    # that still falls by 14 % between two peaks (1.5 s of a 10 s release), so w varies by
    # about as much within a period and the leak is a share of the other's: 0.14 of it
    # (measured), under a quarter asserted
    dt = 0.01
    phi = 2 * np.pi * np.arange(3000) * dt / 3.0  # ten periods
    e = HARMONIC_ERROR_M * np.sin(phi)
    _, J = _harmonic_reference(_leg_obs(e, phi), dt)
    own = np.abs(J[-1]).max()
    w_e = dt * e / (1.0 + (e / HARMONIC_ERROR_M) ** 2)
    instantaneous = abs(np.sum(w_e * np.sin(3 * phi)))
    # the charge of a third harmonic of a tenth the amplitude
    pure = np.sum(dt * 0.1 * HARMONIC_ERROR_M * np.sin(3 * phi) ** 2)
    assert instantaneous > 0.1 * pure
    assert own < 0.25 * instantaneous, (own, instantaneous)


def _fixed_loop_errors(sc, bound):
    """The tracking errors X̂ − X [m] of 30 s of a fixed linear "network" (PID on the features
    e, ė, I_0: a_F = (600 e + 30 ė + 3000 I_0) / force_N, a_k = 0) on scenario ``sc``, with
    the harmonic force correction bounded to ``bound`` [N] (None: off): the reports' last
    three periods of them (``whole_periods``)."""
    from mpa_gym.agents.learned.inference import DeployedPolicy

    features, force_N, dt = FeatureSpec(errors_only=True, harmonics=1), 30.0, 0.01
    net = np.zeros((2, 5))
    net[0, :3] = np.array([600.0, 30.0, 3000.0]) / force_N
    policy = DeployedPolicy([(net, np.zeros(2))], "Tanh", 9, features, None, dt,
                            ActionSpec(force_N=force_N, harmonic_force_N=bound), 2.0)
    env = gym.make("MPALegResidual-v0", scenario=sc, task={"residual_scale_bar": 2.0})
    obs, _ = env.reset(seed=1)
    err = []
    for k in range(int(30.0 / dt)):
        obs, _, terminated, _, _ = env.step(policy.act(obs, k == 0))
        err.append(obs[2] - obs[0])
        assert not terminated
    return np.array(err)[whole_periods(dt * np.arange(1, len(err) + 1), sc.reference.period)]


def _harmonic_amplitudes(tail, harmonics):
    """[m] amplitudes of the reference's ``harmonics`` in ``tail``, three whole periods."""
    return (np.abs(np.fft.rfft(tail)) / tail.size * 2)[[3 * h for h in harmonics]]


def test_harmonic_force_correction_removes_the_harmonics_a_feedback_loop_leaves():
    # closed loop on a plant the policy never saw: a fixed linear "network"
    # (_fixed_loop_errors) leaves heldout_bladder's muscle nonlinearity at 2ω and 3ω
    # (amplitudes 0.044 and 0.010 mm); with the correction at a bound of 1 N both fall,
    # measured 61x and 13x over the last three periods of 30 s (21x and 5x with the envelope
    # weight's earlier 1 mm square): at least 5x and 2.5x asserted, the bounds set then (the
    # 3rd's time constant is longer at its lower dynamic stiffness)
    sc = load_scenario("heldout_bladder")
    amp = {bound: _harmonic_amplitudes(_fixed_loop_errors(sc, bound), (2, 3))
           for bound in (None, 1.0)}
    assert amp[None][0] > 3e-5 and amp[None][1] > 5e-6  # there is something to remove
    assert amp[1.0][0] < amp[None][0] / 5 and amp[1.0][1] < amp[None][1] / 2.5, amp


def test_harmonic_force_correction_learns_a_rigs_friction_error_within_an_episode():
    # closed loop on a rig unlike the model (configs/rigs/offnominal.yaml: braid and slider
    # friction, 20 bar/s slew, 20 ms dead time + 30 ms lag, +0.6 kg, C1 -10 %), the fixed
    # linear "network" of the test above: the friction leaves 1.1 mm at 3ω (measured), a
    # steady periodic error, the kind this correction is for. This loop also leaves 3 mm at
    # the first harmonic (a trained policy tracks this rig within 0.5 mm), so the envelope
    # sits at 4-6 mm (w ≈ 0.3 at the weight's 3 mm scale): the 3rd harmonic falls to 0.10 mm
    # over the 30 s rollout (11x, measured); at the weight's earlier 1 mm scale (w ≈ 0.04) to
    # 0.82 mm (1.3x). At least 4x asserted; the first harmonic, the feedback's, is left to the
    # network
    sc = load_scenario(str(Path(__file__).resolve().parents[1] / "configs" / "rigs"
                           / "offnominal.yaml"))
    amp = {bound: _harmonic_amplitudes(_fixed_loop_errors(sc, bound), (1, 3))
           for bound in (None, 1.0)}
    assert amp[None][0] > HARMONIC_ERROR_M / 2  # the envelope is over the weight's scale
    assert amp[None][1] > 5e-4  # the friction's 3rd harmonic: something to remove
    assert amp[1.0][1] < amp[None][1] / 4, amp


def test_harmonic_force_correction_after_a_kick():
    # the price of the weight's 3 mm scale: the paper's impulse scenario (20 N for 50 ms at
    # 9 s, the nominal plant), the fixed "network" of the tests above. Without the correction
    # the loop tracks the last three periods (12-21 s after the kick) within 0.001 mm RMS. The
    # kick's few millimetres charge the integrals nearly as if unweighted, and what they hold
    # then adds 0.018 mm (measured; unweighted 0.0195, at the earlier 1 mm scale 0.008, with
    # a 4th power at 3 mm 0.010). Under 0.025 mm asserted: a correction that charged more on
    # a kick, or took longer to discharge, would show here
    sc = load_scenario("impulse")
    rms = {bound: np.sqrt(np.mean(np.square(_fixed_loop_errors(sc, bound))))
           for bound in (None, 1.0)}
    assert rms[None] < 2e-6, rms  # the loop itself has settled
    assert rms[1.0] < 2.5e-5, rms
