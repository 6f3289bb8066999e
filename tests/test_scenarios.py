"""The paper's scenarios (Sec. 3.2, 4.4): loading, validation and the behaviour it reports."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from mpa_gym.analysis.scenario import (
    PLANT_RANGES,
    Inputs,
    Plant,
    Randomization,
    ScenarioError,
    load_scenario,
    scenario_from_dict,
    scenario_names,
)
from mpa_gym.analysis.simulate import SimulationError, simulate
from mpa_gym.analysis.stability import analyze, linear_steady_state_error
from mpa_gym.design.reference import Reference
from mpa_gym.model.leg import kinematics
from mpa_gym.model.params import DEFAULT_PARAMS
from mpa_gym.model.params import DEFAULT_PARAMS as P

NAMED = ["nominal", "initial_error", "impulse", "gamma_mismatch", "mass_mismatch", "kmax", "kmin",
         "load_1kg", "load_1kg_kmin"]


def test_every_named_scenario_exists_and_round_trips():
    assert set(NAMED) <= set(scenario_names())
    for name in NAMED:
        sc = load_scenario(name)
        assert sc.name == name and sc.description
        assert scenario_from_dict(sc.to_dict(), name) == sc


def test_initial_error_scenario_is_the_papers():
    sc = load_scenario("initial_error")
    x0, v0 = sc.start_state()
    assert x0 - sc.reference.position(0.0) == pytest.approx(0.02, abs=1e-9)
    assert v0 - sc.reference.velocity(0.0) == pytest.approx(0.1, abs=1e-6)


def _max_err(r, t0, t1):
    w = (r.t >= t0 - 1e-9) & (r.t <= t1 + 1e-9)
    return float(np.max(np.abs(r.error[w])))


def _period_maxima(r, t0, n):
    return np.array([_max_err(r, t0 + 3.0 * k, t0 + 3.0 * (k + 1) - 1e-6) for k in range(n)])


def _assert_decays_at_floquet_rate(r, t0):
    # The error shrinks per period by the spectral radius ρ of the monodromy matrix. With complex
    # multipliers the ratio of successive period maxima oscillates around ρ (±12 % here), so the
    # geometric mean over 5 periods is compared with ρ to 10 %.
    rho = analyze(r.scenario.design()).spectral_radius
    m = _period_maxima(r, t0, 6)
    assert np.all(np.diff(m) < 0)
    assert (m[5] / m[0]) ** (1 / 5) == pytest.approx(rho, rel=0.10)


def test_converges_after_initial_error():
    r = simulate("initial_error")
    assert _max_err(r, 0.0, 3.0) > 0.015
    _assert_decays_at_floquet_rate(r, 0.0)
    assert r.max_abs_err_m < 1e-4 * _max_err(r, 0.0, 3.0)


def test_converges_after_impulse():
    sc = load_scenario("impulse")
    imp = sc.disturbances[0]
    assert (imp.force_N, imp.duration_s) == (20.0, 0.05)
    r = simulate(sc)
    assert _max_err(r, 0.0, imp.t_s) < 1e-6  # on the reference until pushed
    after = _max_err(r, imp.t_s, imp.t_s + 3.0)
    assert after > 5e-3  # the push is felt (impulse 1 N s on 3.74 kg)
    _assert_decays_at_floquet_rate(r, imp.t_s + imp.duration_s)


def test_gamma_mismatch_converges_almost_onto_the_reference():
    # Fig. 4(c): almost the same trajectory. The error is bounded by the force the design
    # mis-predicts, |Δγ| (G_e² + G_f²) |V̂|, over the lowest stiffness along the reference,
    # the linearised periodic error matches it to first order.
    sc = load_scenario("gamma_mismatch")
    r = simulate(sc)
    d = sc.design()
    s = d.sample(np.linspace(0, 3, 301))
    kin = kinematics(s.x_ref, P.leg, P.mpa)
    bound = np.max(abs(30.0 - 15.0) * (kin.Ge**2 + kin.Gf**2) * np.abs(s.v_ref)) / s.k.min()
    assert r.max_abs_err_m < bound
    w = r.t >= 27.0 - 1e-9
    pred = linear_steady_state_error(d, sc.plant_params(), r.t[w])
    assert np.max(np.abs(r.error[w] - pred)) < 0.05 * np.max(np.abs(pred))


def test_mass_mismatch_gives_a_stable_periodic_motion_with_steady_state_error():
    # Fig. 4(d): converges to a periodic motion (error repeats period to period) that sits
    # below X̂ (heavier plant); magnitude as linear theory predicts to second order in Δm/m = 13 %.
    sc = load_scenario("mass_mismatch")
    r = simulate(sc)
    w1 = (r.t >= 24.0 - 1e-9) & (r.t < 27.0 - 1e-9)
    w2 = (r.t >= 27.0 - 1e-9) & (r.t < 30.0 - 1e-9)
    assert np.max(np.abs(r.error[w1] - r.error[w2])) < 1e-6
    sag = r.error[w2].mean()
    assert sag < -5e-3
    pred = linear_steady_state_error(sc.design(), sc.plant_params(), r.t[w2])
    assert sag == pytest.approx(pred.mean(), rel=0.15)
    assert analyze(sc.design()).stable


def test_load_1kg_kmin_sags_more_than_kmax():
    # Fig. 14: under the unknown +1 kg the lower-stiffness design tracks worse.
    kmax, kmin = simulate("load_1kg"), simulate("load_1kg_kmin")
    assert kmin.rmse_m > kmax.rmse_m
    assert kmin.error[kmin.metric_window()].mean() < kmax.error[kmax.metric_window()].mean() < 0


# ------------------------------------------------------------------------------ malformed input
BASE = {"name": "t", "duration_s": 6.0}


@pytest.mark.parametrize(
    ("patch", "match"),
    [
        ({"colour": 1}, r"unknown key\(s\) \['colour'\]"),
        ({"plant": {"mas_kg": 4}}, r"plant: unknown key\(s\) \['mas_kg'\]; allowed keys"),
        ({"plant": {"mass_kg": -1.0}}, r"plant.mass_kg=-1 kg is outside the allowed range"),
        ({"plant": {"mass_kg": "heavy"}}, r"plant.mass_kg='heavy' must be a number"),
        ({"plant": {"gamma_Ns_per_m": float("nan")}}, r"gamma_Ns_per_m=nan must be finite"),
        ({"duration_s": 0.0}, r"duration_s=0 s is outside the allowed range \(0, 3600\]"),
        ({"inputs": {"pf_mean_bar": 0.5, "pf_amp_bar": 0.9}}, r"pf_amp_bar=0.9 bar is outside"),
        ({"inputs": {"mode": 7}}, r"inputs.mode=7 must be one of \[1, 2, 3\]"),
        ({"inputs": {"stiffness": "kmed"}}, r"inputs.stiffness='kmed' must be 'kmax' or 'kmin'"),
        ({"inputs": {"mode": 1, "stiffness": "kmax"}}, r"at most one of"),
        ({"initial_state": {"x_m": 2.0, "v_mps": 0.0}}, r"initial_state.x_m=2 m is outside"),
        ({"initial_state": {"x_m": 0.8}}, r"missing required key\(s\) \['v_mps'\]"),
        ({"reference": {"x0_m": 0.8, "amp_m": 0.2}}, r"outside the allowed range"),
        ({"disturbances": [{"type": "kick", "t_s": 1, "force_N": 1, "duration_s": 0.1}]},
         r"disturbances\[0\].type='kick': allowed types are \['impulse', 'static'\]"),
        ({"disturbances": [{"type": "impulse", "t_s": 9, "force_N": 1, "duration_s": 0.1}]},
         r"disturbances\[0\].t_s=9 s is outside the allowed range \[0, 6\]"),
        ({"disturbances": {"type": "impulse"}}, r"disturbances must be a list"),
    ],
)
def test_malformed_scenario_names_key_value_and_range(patch, match):
    with pytest.raises(ScenarioError, match=match):
        load_scenario({**BASE, **patch})


def test_missing_duration_and_bad_files(tmp_path):
    with pytest.raises(ScenarioError, match=r"missing required key\(s\) \['duration_s'\]"):
        load_scenario({"name": "x"})
    bad = tmp_path / "bad.yaml"
    bad.write_text("duration_s: [1, 2\n")
    with pytest.raises(ScenarioError, match="is not valid YAML"):
        load_scenario(bad)
    with pytest.raises(ScenarioError, match=r"list\.yaml' must be a mapping"):
        (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
        load_scenario(tmp_path / "list.yaml")
    with pytest.raises(ScenarioError, match=r"neither a file nor one of the named scenarios"):
        load_scenario("no_such_scenario")
    good = tmp_path / "custom.yaml"
    good.write_text(yaml.safe_dump({**BASE, "plant": {"extra_mass_kg": 0.5}}))
    assert load_scenario(good).plant.extra_mass_kg == 0.5


def test_leaving_the_model_domain_raises_and_keeps_the_partial_run():
    # A -2 kN push throws the hip below the knee's reach: a clear error, not NaN results.
    sc = {**BASE, "disturbances": [{"type": "impulse", "t_s": 1.0, "force_N": -2000.0,
                                    "duration_s": 0.5}]}
    with pytest.raises(SimulationError, match=r"left the model's domain at t = ") as e:
        simulate(sc)
    part = e.value.partial
    assert part is not None and part.t.size > 0 and np.all(np.isfinite(part.x))
    assert part.t[-1] >= 1.0


# ------------------------------------------------------------ the dataclasses check themselves
@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: Plant(mass_kg=-1), r"plant.mass_kg=-1 kg is outside the allowed range"),
        (lambda: Plant(pressure_lag_s="slow"), r"plant.pressure_lag_s='slow' must be a number"),
        (lambda: Plant(C1_Pa=float("nan")), r"plant.C1_Pa=nan must be finite"),
        (lambda: Inputs(pf_mean_bar=0.5, pf_amp_bar=0.9), r"inputs.pf_amp_bar=0.9 bar is outside"),
        (lambda: Inputs(mode=[1]), r"inputs.mode=\[1\] must be one of \[1, 2, 3\]"),
        (lambda: Inputs(mode=True), r"inputs.mode=True must be one of"),
        (lambda: Inputs(stiffness="kmed"), r"inputs.stiffness='kmed' must be 'kmax' or 'kmin'"),
        (lambda: Inputs(mode=1, stiffness_const_N_per_m=5e3), r"at most one of"),
        (lambda: Inputs(p_max_bar=0.0), r"inputs.p_max_bar=0 bar is outside the allowed range"),
        (lambda: Randomization((("mass_kg", 5.0, 4.0),)), r"randomize.mass_kg=\[5, 4\]: low"),
        (lambda: Randomization((("encoder_resolution_m", 0.0, 1e-4),)),
         r"randomize: unknown key\(s\) \['encoder_resolution_m'\]"),
        (lambda: Randomization((("mass_kg", -1.0, 4.0),)), r"randomize.mass_kg=-1 kg is outside"),
        (lambda: Randomization.from_dict({"mass_kg": 4.0}), r"must be a \[low, high\] pair"),
        (lambda: Randomization.from_dict({"mass_kg": {"range": [3, 4], "p_off": 1.5}}),
         r"randomize.mass_kg.p_off=1.5 is outside the allowed range \[0, 1\]"),
        (lambda: Randomization.from_dict({"mass_kg": {"range": [3, 4], "p_of": 0.5}}),
         r"randomize.mass_kg=.* must be \{range: \[low, high\], p_off: p\}"),
        (lambda: Randomization((("mass_kg", 3.0, 4.0),), (("C1_Pa", 0.5),)),
         r"randomize.C1_Pa.p_off: 'C1_Pa' has no range to draw from"),
    ],
)
def test_the_scenario_dataclasses_validate_themselves(make, match):
    with pytest.raises(ScenarioError, match=match):
        make()


def test_every_plant_field_has_a_range_and_values_become_floats():
    assert {f.name for f in dataclasses.fields(Plant)} == set(PLANT_RANGES)
    p = Plant(mass_kg=4, extra_mass_kg=np.float32(0.5))
    assert type(p.mass_kg) is float and type(p.extra_mass_kg) is float
    assert Randomization((("mass_kg", 3, 4),)).ranges == (("mass_kg", 3.0, 4.0),)


def test_p_off_leaves_a_field_at_the_plants_value_that_often_and_keeps_the_other_draws():
    """A field with p_off is absent from a fraction p_off of the draws (binomial: 4000 draws at
    p = 0.3 have a standard deviation of 0.0072, the bound is 5 of them); the fields without one
    draw the values they draw without any p_off from the same seed."""
    plain = Randomization.from_dict({"mass_kg": [3.5, 4.2], "pressure_dead_time_s": [0.0, 0.03],
                                     "extra_mass_kg": [0.0, 1.0]})
    off = Randomization.from_dict({"mass_kg": [3.5, 4.2],
                                   "pressure_dead_time_s": {"range": [0.0, 0.03], "p_off": 0.3},
                                   "extra_mass_kg": [0.0, 1.0]})
    assert Randomization.from_dict(off.as_dict()) == off
    # the reports' one-line form (a run's "trained on"): every range, and p_off where set
    assert off.describe() == ("mass_kg 3.5–4.2, pressure_dead_time_s 0–0.03 (off 0.3), "
                              "extra_mass_kg 0–1")
    assert Randomization().describe() == "none"
    n, absent = 4000, 0
    for i in range(n):
        a, b = plain.sample(np.random.default_rng(i)), off.sample(np.random.default_rng(i))
        assert b["mass_kg"] == a["mass_kg"] and b["extra_mass_kg"] == a["extra_mass_kg"]
        absent += "pressure_dead_time_s" not in b
    assert abs(absent / n - 0.3) < 5 * 0.0072
    # the episode then keeps the scenario's value: off by default, the nominal for a model field
    sc = load_scenario({"name": "s", "duration_s": 1.0, "randomize": {
        "pressure_dead_time_s": {"range": [0.01, 0.03], "p_off": 1.0},
        "mass_kg": {"range": [3.9, 4.2], "p_off": 0.5}}})
    assert sc.randomize.sample(np.random.default_rng(0)).get("pressure_dead_time_s") is None
    assert sc.randomize.span(sc.plant) == {"pressure_dead_time_s": (0.0, 0.03),
                                           "mass_kg": (DEFAULT_PARAMS.leg.m, 4.2)}


def test_one_design_builder_serves_scenarios_plans_and_the_cli(capsys):
    """Inputs.design is what a scenario, a plan's stiffness target and the CLI flags build."""
    import json

    from mpa_gym.agents.cli import main
    from mpa_gym.task.plan import stiffness_design

    sc = load_scenario("nominal")
    t = np.linspace(0.0, 3.0, 31)
    for stiffness, inputs in (("kmax", Inputs(stiffness="kmax")),
                              (4000.0, Inputs(stiffness_const_N_per_m=4000.0))):
        a = stiffness_design(sc, stiffness, DEFAULT_PARAMS).pressures(t)
        b = inputs.design(sc.reference).pressures(t)
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sc.design().pressures(t),
                                  Inputs().design(Reference()).pressures(t))
    assert main(["design", "--mode", "2", "--samples", "31", "--json"]) == 0
    o = json.loads(capsys.readouterr().out)
    pe, pf = Inputs(mode=2).design(Reference()).pressures(np.asarray(o["t"])).T / 1e5
    np.testing.assert_allclose(o["pe_bar"], pe, rtol=0, atol=1e-12)  # the same floats, via JSON
    np.testing.assert_allclose(o["pf_bar"], pf, rtol=0, atol=1e-12)
