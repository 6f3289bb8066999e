"""Agents: baselines through the policy interface, PPO train/save/load/resume, configs, report."""

from __future__ import annotations

import dataclasses
import json
import os

import gymnasium as gym
import numpy as np
import pytest
import yaml

import mpa_gym  # noqa: F401
from mpa_gym.agents.controllers.baselines import make_baseline
from mpa_gym.agents.evaluation.episodes import metrics, run_episode
from mpa_gym.agents.evaluation.evaluate import evaluate, write_report
from mpa_gym.agents.learned.config import DEFAULT_CONFIG, ConfigError, load_config, parse_config
from mpa_gym.agents.learned.policies import load_run
from mpa_gym.agents.learned.wrappers import (
    FeatureSpec,
    ForceStiffnessAction,
    TrackingErrorObservation,
    TrackingErrorVectorObservation,
)
from mpa_gym.agents.training.train import train
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.task.contract import OBS_V as OV
from mpa_gym.task.contract import OBS_VREF as OVR
from mpa_gym.task.contract import OBS_X as OX
from mpa_gym.task.contract import OBS_XREF as OXR

SHORT = {"name": "short", "duration_s": 6.0, "plant": {"extra_mass_kg": 1.0}}
LOADED = {"name": "loaded", "duration_s": 18.0, "plant": {"extra_mass_kg": 1.0}}


@pytest.mark.parametrize("name", ["ff", "pid", "mbfb", "afc", "rc"])
def test_baselines_drive_the_env_through_the_policy_interface(name):
    # 18 s: the integrators settle in the first 9 s, the metrics use the last three periods
    env = gym.make("MPALegResidual-v0", scenario=LOADED)
    policy = make_baseline(name, LOADED)
    tr = run_episode(env, policy, seed=3)
    m = metrics(tr, 3.0, None)
    assert not tr.terminated and len(tr.t) == 1800
    if name == "ff":  # the expert sags under the unknown load …
        assert m["position_rmse_mm"] > 10
    elif name == "afc":  # … the slow adaptation removes the sag: its averaged law leaves
        # exp(−t / 6 s) of it, 22 % at 9 s to 5 % at 18 s, an RMS of 12 % over the window
        # (0.2 leaves room for the nonlinearity's coupling of mean and harmonic) …
        ff = metrics(run_episode(env, make_baseline("ff", LOADED), seed=3), 3.0, None)
        assert m["position_rmse_mm"] < 0.2 * ff["position_rmse_mm"]
    else:  # … the feedback baselines hold the reference
        assert m["position_rmse_mm"] < 1.0
    # batched observations give the same actions as single ones (state per row)
    obs = np.stack([env.reset(seed=s)[0] for s in range(3)])
    obs[:, 0] += [0.004, -0.003, 0.0]  # off the reference, so the feedback acts
    obs[:, 4:6] = [[0.0, 1.0], [1.0, 0.0], [0.0, -1.0]]  # three phases
    a_batch, _ = policy.predict(obs, None, np.ones(3, dtype=bool))
    for i in range(3):
        a_one, _ = policy.predict(obs[i], None, np.ones(1, dtype=bool))
        np.testing.assert_allclose(a_batch[i], a_one, rtol=1e-6, atol=1e-7)
        assert np.all(np.abs(a_one) <= 1.0)


def _per_period_rmse_mm(tr, period_s=3.0, dt=0.01):
    e = (tr.x - tr.x_ref).reshape(-1, round(period_s / dt))
    return np.sqrt(np.mean(e**2, axis=1)) * 1e3


def test_repetitive_control_learns_the_periodic_error_period_by_period():
    # A plant the nominal model does not know (heavier, a slow regulator with dead time, a
    # 1 kg load; no sensor noise): the feedforward's error repeats every period, which is what
    # the delay line learns. Period by period rc's error falls (from the fourth period on,
    # each within 2 % of, or below, the one before: the memory contracts, by ~0.7 a period
    # here), and over the last three of 15 periods it is far below ff's (the internal model
    # cancels the repeating error: < 1 % of it) and below a tenth of pid's, the same PID
    # without the memory, whose error repeats unchanged.
    sc = {"name": "mismatch", "duration_s": 45.0,
          "plant": {"mass_kg": 4.1, "extra_mass_kg": 1.0, "pressure_lag_s": 0.03,
                    "pressure_dead_time_s": 0.01}}
    env = gym.make("MPALegResidual-v0", scenario=sc)
    per = {n: _per_period_rmse_mm(run_episode(env, make_baseline(n, sc), seed=0))
           for n in ("ff", "pid", "rc")}
    rc = per["rc"]
    assert np.all(rc[4:] <= 1.02 * rc[3:-1]), rc
    assert rc[-3:].mean() < 0.01 * per["ff"][-3:].mean(), (rc, per["ff"])
    assert rc[-3:].mean() < 0.1 * per["pid"][-3:].mean(), (rc, per["pid"])


def test_repetitive_control_does_nothing_where_the_feedforward_is_exact():
    # The nominal plant without noise: the feedforward is exact (X within 4 µm of X̂: a
    # design held over each control period), so the residual rc adds stays under 1e-4 bar
    # (1/70000 of the pressure range; what 18 µm of error would command through pid's
    # proportional gain) and its error stays within a micrometre of ff's: the memory has
    # nothing to learn.
    env = gym.make("MPALegResidual-v0", scenario={"name": "n", "duration_s": 9.0})
    rc = make_baseline("rc")
    tr, ff = (run_episode(env, p, seed=0) for p in (rc, make_baseline("ff")))
    assert np.abs(tr.x - tr.x_ref).max() <= np.abs(ff.x - ff.x_ref).max() + 1e-6
    residual_bar = np.abs(tr.pressure_cmd_bar - ff.pressure_cmd_bar).max()
    assert residual_bar < 1e-4, residual_bar


def test_repetitive_control_stacked_over_scenarios_is_each_row_alone():
    # rc on two scenarios of different reference periods (3 s and 2 s: delay lines of 300 and
    # 200 steps) as one stack in one batch gives every step of each scenario's episode exactly
    # as the scenario's own controller run alone does.
    scenarios = [{"name": "a", "duration_s": 7.0, "plant": {"extra_mass_kg": 1.0}},
                 {"name": "b", "duration_s": 7.0, "plant": {"extra_mass_kg": 0.5},
                  "reference": {"x0_m": 0.8, "amp_m": 0.02, "period_s": 2.0}}]
    batched = evaluate(["rc"], scenarios)
    alone = evaluate(["rc"], scenarios, batched=False)
    for sc in ("a", "b"):
        a, b = batched["traces"][sc]["rc"], alone["traces"][sc]["rc"]
        for f in ("x", "pressure_cmd_bar"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    # and the memory acted: rc's commands are not pid's
    pid = evaluate(["pid"], scenarios[:1])["traces"]["a"]["pid"]
    assert np.abs(batched["traces"]["a"]["rc"].pressure_cmd_bar - pid.pressure_cmd_bar).max() > 0.01


def test_repetitive_design_refuses_what_it_cannot_hold():
    with pytest.raises(ValueError, match=r"rc\.learn=2\.5 is outside the allowed range"):
        make_baseline("rc", gains={"learn": 2.5})
    with pytest.raises(ValueError, match=r"not a whole number \(>= 8\) of control periods"):
        make_baseline("rc", task={"dt_s": 0.007})


def test_stiffness_feedback_keeps_k_at_k_hat_under_load():
    # With only the mass off, the plant's MPAs are the nominal model's, so solving
    # k(X, V, P') = k̂ at the measured state holds the true stiffness on target; the feedforward
    # alone lets it drift with the sag.
    sc = load_scenario("load_1kg")
    ff = metrics(run_episode(gym.make("MPALegResidual-v0", scenario=sc),
                             make_baseline("ff", sc), 0), 3.0, None)
    mb = metrics(run_episode(gym.make("MPALegResidual-v0", scenario=sc),
                             make_baseline("mbfb", sc), 0), 3.0, None)
    assert ff["stiffness_rmse_pct"] > 10
    assert mb["stiffness_rmse_pct"] < 1.0  # ZOH of the command over 10 ms: < 1 %
    assert mb["position_rmse_mm"] < ff["position_rmse_mm"] / 10


def test_integral_wrappers_agree_single_and_vector():
    single = TrackingErrorObservation(gym.make("MPALegResidual-v0", scenario=SHORT,
                                               task={"episode_s": 0.3}))
    vec = TrackingErrorVectorObservation(gym.make_vec(
        "MPALegResidual-v0", num_envs=2, vectorization_mode="vector_entry_point",
        scenario=SHORT, task={"episode_s": 0.3}))
    so, _ = single.reset(seed=4)
    vo, _ = vec.reset(seed=4)
    assert so.shape == (12,) and vo.shape == (2, 12)
    np.testing.assert_array_equal(so, vo[0])
    rng = np.random.default_rng(1)
    for _ in range(45):  # crosses the 30-step episode end (same-step autoreset)
        a = rng.uniform(-1, 1, (2, 2))
        so, _, te, tr, _ = single.step(a[0])
        vo, _, _, _, vinfo = vec.step(a)
        if te or tr:
            np.testing.assert_array_equal(so, vinfo["final_obs"][0])
            so, _ = single.reset()
        np.testing.assert_array_equal(so, vo[0])
    assert np.any(vo[:, -1] != 0.0)  # the integral moves


def tiny_config(tmp_path, **over):
    cfg = yaml.safe_load(open("configs/ppo_residual.yaml"))
    hp = cfg["MPALegResidual-v0"]
    hp.update(n_envs=4, n_timesteps=256, n_steps=32, batch_size=64, n_epochs=1)
    hp["env_kwargs"]["task"]["episode_s"] = 0.5
    cfg["mpa_gym"].update(eval_scenarios=[{"name": "ev", "duration_s": 3.0}], eval_freq=128,
                          checkpoint_freq=256)
    for k, v in over.items():
        hp[k] = v
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_ppo_trains_saves_loads_and_evaluates_to_the_same_numbers(tmp_path):
    run = train(tiny_config(tmp_path), tmp_path / "run", progress=False)
    for f in ("config.yaml", "model.zip", "vecnormalize.pkl", "eval/evaluations.npz",
              "eval/evaluations.json", "best/best_model.zip"):
        assert (run / f).is_file(), f
    assert list((run / "tb").glob("PPO_*/events.out.tfevents.*"))
    assert list((run / "checkpoints").glob("ppo_*_steps.zip"))
    hist = json.loads((run / "eval" / "evaluations.json").read_text())
    assert hist and {"position_rmse_mm", "stiffness_rmse_pct"} <= set(hist[-1]["scenarios"]["ev"])
    # the loaded policy (model + normaliser) evaluates to the same numbers twice, and to what
    # the model and the saved normaliser give directly
    policy, cfg = load_run(run)
    assert policy.features == FeatureSpec(**cfg.observation_wrapper)
    # loaded once while the run's files are unchanged (each caller its own episode state
    # around the one model); a run written again is loaded again
    again = load_run(run)[0]
    assert again is not policy and again.model is policy.model
    st = (run / "model.zip").stat()
    os.utime(run / "model.zip", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert load_run(run)[0].model is not policy.model
    assert policy.action is not None
    sc = {"name": "ev", "duration_s": 3.0}
    r1 = evaluate([str(run)], [sc])["results"]["ev"]["run"]
    r2 = evaluate([str(run)], [sc])["results"]["ev"]["run"]
    assert r1 == r2
    # step by step, the loaded policy (raw observations in, its own state) acts as the model on
    # the training wrappers' observations, mapped to the env's residual action as the training
    # wrapper maps it (with its stiffness estimator, which the default config has)
    assert cfg.observation_wrapper is not None and cfg.action_wrapper is not None
    task = {k: v for k, v in cfg.env_kwargs["task"].items() if k != "episode_s"}
    raw = _LastObservation(gym.make("MPALegResidual-v0", scenario=SHORT, task=task))
    env = ForceStiffnessAction(TrackingErrorObservation(raw, **cfg.observation_wrapper),
                               **cfg.action_wrapper)
    obs, _ = env.reset(seed=0)
    state, start = None, np.array([True])
    for _ in range(60):
        direct, _ = policy.model.predict(policy.normalizer.normalize_obs(obs[None]),
                                         deterministic=True)
        via, state = policy.predict(raw.last, state, start)
        start = np.array([False])
        obs, *_ = env.step(direct[0])
        np.testing.assert_array_equal(via, env.env.state["prev"][0][0])  # what the env was given
    # the model saw the tracking-error features alone (the env's X, X̂, pressures… left out):
    # errors, integrals, the remodulated pairs, the actions in flight and the rig's delays
    f = policy.features
    assert f.errors_only and obs.shape == (2 + f.n_integrals + 2 * f.harmonics * f.remodulate
                                           + 2 * f.n_actions + 2 * f.delay_observation,)


class _LastObservation(gym.Wrapper):
    """Keeps the env's own last observation (what a deployed policy is given)."""

    def reset(self, **kwargs):
        self.last, info = self.env.reset(**kwargs)
        return self.last, info

    def step(self, action):
        self.last, *rest = self.env.step(action)
        return self.last, *rest


def test_resume_continues_the_step_count(tmp_path):
    run = train(tiny_config(tmp_path), tmp_path / "run", progress=False)
    from stable_baselines3 import PPO

    first = PPO.load(run / "model.zip").num_timesteps
    with pytest.raises(ConfigError, match="already reached n_timesteps"):
        train(resume=run, progress=False)
    train(resume=run, n_timesteps=128, progress=False)
    assert PPO.load(run / "model.zip").num_timesteps == first + 128
    assert len(json.loads((run / "eval" / "evaluations.json").read_text())) >= 3
    with pytest.raises(ConfigError, match="already holds a model; use --resume"):
        train(tiny_config(tmp_path), run, progress=False)


@pytest.mark.parametrize(
    ("patch", "match"),
    [({"learning_rat": 1e-3}, r"unknown key\(s\) \['learning_rat'\]"),
     ({"n_envs": 0}, r"n_envs=0 must be a whole number in \[1, 4096\]"),
     ({"policy": "CnnPolicy"}, r"policy='CnnPolicy': allowed \['MlpPolicy'\]"),
     ({"policy_kwargs": "dict(net_arch=__import__('os'))"}, r"only literals"),
     ({"batch_size": 10_000}, r"batch_size=10000 must be <= n_steps \* n_envs"),
     ({"env_wrapper": "os.system"}, r"env_wrapper='os.system': allowed"),
     ({"env_wrapper": [{"mpa_gym.agents.learned.wrappers.TrackingErrorObservation":
                        {"harmonic": 1}}]},
      r"TrackingErrorObservation: unknown key\(s\) \['harmonic'\]"),
     ({"env_wrapper": [{"mpa_gym.agents.learned.wrappers.TrackingErrorObservation":
                        {"harmonics": 9}}]},
      r"harmonics=9 must be a whole number in \[0, 5\]"),
     ({"env_wrapper": [{"mpa_gym.agents.learned.wrappers.ForceStiffnessAction": {"force_N": 0}}]},
      r"ForceStiffnessAction: force_N=0 must be a number in \(0, 200\]"),
     ({"env_wrapper": [{"mpa_gym.agents.learned.wrappers.ForceStiffnessAction":
                        {"rate_penalty": "big"}}]},
      r"ForceStiffnessAction: rate_penalty='big' must be a number in \[0, 100\]"),
     ({"env_wrapper": ["mpa_gym.agents.learned.wrappers.ForceStiffnessAction",
                       "mpa_gym.agents.learned.wrappers.ForceStiffnessAction"]}, "given twice"),
     ({"learning_rate": "fast"}, r"learning_rate='fast' must be a number or 'lin_<number>'"),
     ({"env_kwargs": {"scenery": 1}}, r"env_kwargs=.*allowed keys are \['scenario'")],
)
def test_malformed_config_names_the_bad_key(tmp_path, patch, match):
    with pytest.raises(ConfigError, match=match):
        load_config(tiny_config(tmp_path, **patch))


def test_config_structure_errors():
    with pytest.raises(ConfigError, match=r"unknown top-level key\(s\) \['CartPole-v1'\]"):
        parse_config({"CartPole-v1": {}})
    with pytest.raises(ConfigError, match="missing required key 'n_timesteps'"):
        parse_config({"MPALeg-v0": {"policy": "MlpPolicy"}})
    with pytest.raises(ConfigError, match=r"mpa_gym: unknown key\(s\) \['sed'\]"):
        parse_config({"MPALeg-v0": {"policy": "MlpPolicy", "n_timesteps": 10},
                      "mpa_gym": {"sed": 1}})
    cfg = load_config("configs/ppo_scratch.yaml")
    assert cfg.env_id == "MPALeg-v0" and cfg.policy_kwargs["net_arch"] == [64, 64]
    with pytest.raises(ConfigError, match="ForceStiffnessAction needs MPALegResidual-v0"):
        parse_config({"MPALeg-v0": {"policy": "MlpPolicy", "n_timesteps": 10,
                                    "env_wrapper":
                                        "mpa_gym.agents.learned.wrappers.ForceStiffnessAction"}})


def test_report_files(tmp_path):
    rep = evaluate(["ff", "pid"], [{"name": "a", "duration_s": 3.0,
                                    "disturbances": [{"type": "impulse", "t_s": 1.0,
                                                      "force_N": 20.0, "duration_s": 0.05}]}])
    paths = write_report(rep, tmp_path)
    data = json.loads(paths["json"].read_text())
    row = data["results"]["a"]
    assert set(row) == {"ff", "pid"}
    assert row["pid"]["recovery_s"] is not None and row["pid"]["recovery_s"] != "never"
    md = paths["markdown"].read_text()
    assert "| a |" in md and "position RMSE [mm]" in md
    # what each controller was tuned on, in both forms of the report
    from mpa_gym.agents.controllers.baselines import TUNED_ON

    assert data["controllers"] == {"ff": TUNED_ON["ff"], "pid": TUNED_ON["pid"]}
    assert f"| pid | {TUNED_ON['pid']} |" in md
    assert (tmp_path / "plots" / "a.png").stat().st_size > 10_000


def _obs_with_error(e_x, e_v, n=1):
    """Residual-env observations on the reference at phase 0, then moved by (e_x, e_v)."""
    env = gym.make("MPALegResidual-v0")
    obs = np.tile(env.reset(seed=0)[0], (n, 1)).astype(np.float64)
    obs[:, OXR] = obs[:, OX] + e_x  # e = X̂ − X
    obs[:, OVR] = obs[:, OV] + e_v
    return obs


def test_pid_derivative_is_low_pass_filtered():
    # A step of the velocity error from 0 to 0.1 m/s: the D term follows the discrete
    # first-order filter d_k = d_{k−1} + α (ė − d_{k−1}), α = dt / (tf + dt), i.e.
    # Kd ė (1 − (1 − α)^k); with tf = 0 it is Kd ė at once.
    from mpa_gym.agents.controllers.baselines import PIDResidual

    for tf in (0.0, 0.02):
        pid = dataclasses.replace(make_baseline("pid"), kp_bar_per_m=0.0, ki_bar_per_m_s=0.0,
                                  kd_bar_s_per_m=2.0, tf_s=tf)
        assert isinstance(pid, PIDResidual)
        _, st = pid.predict(_obs_with_error(0.0, 0.0), None, np.ones(1, bool))
        alpha = 0.01 / (tf + 0.01)
        for k in range(1, 6):
            a, st = pid.predict(_obs_with_error(0.0, 0.1), st, np.zeros(1, bool))
            want = 2.0 * 0.1 * (1.0 - (1.0 - alpha) ** k) / pid.cfg.residual_scale_bar
            np.testing.assert_allclose(a[0], [want, -want], rtol=1e-6)


@pytest.mark.parametrize("name", ["pid", "mbfb"])
def test_integrators_do_not_wind_up_while_the_output_saturates(name):
    # A 5 cm error saturates either controller's output at a stiff proportional gain (5 bar,
    # 250 N: beyond the ±1.5 bar residual): the integral takes the first step (nothing was
    # saturated before it) and then holds while the error pushes the same way; an error of the
    # other sign integrates again at once.
    stiff = {"pid": {"kp_bar_per_m": 100.0}, "mbfb": {"kp_N_per_m": 5000.0}}[name]
    ctrl = dataclasses.replace(make_baseline(name), **stiff)
    _, st = ctrl.predict(_obs_with_error(0.05, 0.0), None, np.ones(1, bool))
    first = st[0, 0]
    assert first == pytest.approx(0.05 * 0.01) and st[0, 2] != 0.0
    for _ in range(20):
        _, st = ctrl.predict(_obs_with_error(0.05, 0.0), st, np.zeros(1, bool))
    assert st[0, 0] == first
    _, st = ctrl.predict(_obs_with_error(-0.001, 0.0), st, np.zeros(1, bool))
    assert st[0, 0] == pytest.approx(first - 0.001 * 0.01)


def test_adaptive_feedforward_follows_its_averaged_law():
    # A synthetic loop e = d − G u (the plant's gain G [m/bar] from u to X, in phase at ω₀)
    # at a fixed X̂ = 0.8 m, V̂ = 0, k̂ = 545 N/m, where the controller's G is a constant, with
    # a periodic error d = 4 mm + 3 mm · sin(ω₀t + 0.7): averaged over a period, each
    # coefficient obeys dθ/dt = (d̄ / G − θ) / τ, so the error's mean and first harmonic decay
    # as exp(−t / τ), τ = adapt_periods · T. Measured over whole periods ending at t: the
    # averaging's ripple (the products at 2ω₀, of relative size T / (2π τ) = 8 %) bounds the
    # agreement at 15 %.
    from mpa_gym.agents.controllers.baselines import AdaptiveFeedforward
    from mpa_gym.task.contract import OBS_COS, OBS_KREF, OBS_KREF_SCALE, OBS_SIN

    afc = make_baseline("afc")
    assert isinstance(afc, AdaptiveFeedforward)
    T, dt = afc.plan.design.reference.period, afc.cfg.dt_s
    tau = afc.adapt_periods * T
    obs = _obs_with_error(0.0, 0.0)
    obs[0, OXR], obs[0, OVR], obs[0, OBS_KREF] = 0.8, 0.0, 545.0 / OBS_KREF_SCALE
    G = float(afc.gain(obs)[0])
    n = round(T / dt)
    t = dt * np.arange(6 * round(tau / dt))
    w = 2 * np.pi * t / T
    d = 0.004 + 0.003 * np.sin(w + 0.7)
    e, u, st = np.empty_like(t), 0.0, None
    for j in range(len(t)):
        e[j] = d[j] - G * u
        obs[0, OX], obs[0, OBS_SIN], obs[0, OBS_COS] = 0.8 - e[j], np.sin(w[j]), np.cos(w[j])
        a, st = afc.predict(obs, st, np.array([j == 0]))
        u = float(a[0, 0]) * afc.cfg.residual_scale_bar

    def parts(j):  # (mean, first-harmonic amplitude) of e over the period ending at step j
        win, ww = e[j - n:j], w[j - n:j]
        return abs(win.mean()), np.hypot(2 * np.mean(win * np.sin(ww)),
                                          2 * np.mean(win * np.cos(ww)))

    for m in (1, 2, 4):
        j = round(m * tau / dt)
        want = np.exp(-t[j - n // 2] / tau)  # at the window's centre
        mean, harm = parts(j)
        assert mean / 0.004 == pytest.approx(want, rel=0.15)
        assert harm / 0.003 == pytest.approx(want, rel=0.15)


def test_adaptive_feedforward_gain_is_the_simulated_legs():
    # The gain G that normalises the adaptation, taken on the nominal model along the
    # reference (dF/du over k̂), against the simulated leg: a constant antagonistic u = 0.05 bar
    # over the feedforward shifts X by ⟨G⟩ u on average over a period (the period is far below
    # the leg's natural frequency, so the shift is quasi-static). 3 %: the plant's gain varies
    # ~2× along the cycle and the shift is not exactly linear in it at second order.
    from mpa_gym.agents.controllers.baselines import AdaptiveFeedforward

    afc = make_baseline("afc", SHORT | {"plant": {}})
    assert isinstance(afc, AdaptiveFeedforward)
    u = 0.05
    runs = []
    for du in (0.0, u):
        env = gym.make("MPALegResidual-v0", scenario=SHORT | {"plant": {}})
        obs, _ = env.reset(seed=0)
        xs, gains = [], []
        a = np.array([du, -du], dtype=np.float32) / afc.cfg.residual_scale_bar
        for _ in range(600):
            gains.append(float(afc.gain(obs[None])[0]))
            obs, *_ = env.step(a)
            xs.append(obs[OX])
        runs.append((np.array(xs[-300:]), np.array(gains[-300:])))
    shift = np.mean(runs[1][0] - runs[0][0])
    assert shift / u == pytest.approx(np.mean(runs[0][1]), rel=0.03)


def test_tuning_runs_on_the_training_plants_and_says_so():
    # Two trials on two plants (a smoke run of the budgeted tuning): the first trial is the
    # current defaults, the best is no worse, and the result names the plants' source.
    from mpa_gym.agents.training.tune_baselines import score, training_plants, tune

    r = tune("pid", n_trials=2, n_plants=2, episode_s=9.0)
    assert r["mean_position_rmse_mm"] <= r["default_mean_position_rmse_mm"]
    assert set(r["gains"]) == {"kp_bar_per_m", "ki_bar_per_m_s", "kd_bar_s_per_m", "tf_s"}
    # the ranges are the training config's, every effect on (its p_off left out)
    ranges = {k: [lo, hi] for k, lo, hi in load_scenario(
        load_config(DEFAULT_CONFIG).env_kwargs["scenario"]).randomize.ranges}
    assert r["tuned_on"]["randomize"]["pressure_dead_time_s"] == ranges["pressure_dead_time_s"]
    assert not {"kick_force_N", "kick_t_s", "kick_duration_s"} & set(r["tuned_on"]["randomize"])
    sc, plants = training_plants(n_plants=2, episode_s=9.0)
    # two draws, then their undamped twins: the same plant, the leg's damping at the low end
    # of its range, friction and the regulator's rate limit off
    assert len(plants) == 4
    for draw, twin in zip(plants[:2], plants[2:], strict=True):
        assert twin == {**draw, "gamma_Ns_per_m": 20.0, "braid_friction_ratio": 0.0,
                        "slider_friction_N": 0.0, "slider_viscous_Ns_per_m": 0.0,
                        "pressure_slew_bar_per_s": 0.0}
        assert draw["braid_friction_ratio"] > 0.0 and draw["pressure_slew_bar_per_s"] >= 5.0
    assert score("pid", r["gains"], sc, plants) == pytest.approx(r["mean_position_rmse_mm"])
    with pytest.raises(ValueError, match=r"--n-trials=0 must be a whole number in \[1, "):
        tune("pid", n_trials=0)


def test_batched_evaluation_gives_the_one_at_a_time_numbers(tmp_path):
    """All scenarios of a report in one batch (vector envs, one policy call per step) against
    each episode alone in its own single env: the baselines bit for bit; a learned policy to
    float32 rounding, because torch's matrix product over a batch of rows need not round the
    last bit as it does for one row (ε_32 ≈ 6e-8; the closed loop is stable, so the metrics
    stay within 1e-6 relative)."""
    run = train(tiny_config(tmp_path), tmp_path / "run", progress=False)
    noisy = {"position_noise_m": 2e-5, "velocity_noise_mps": 1e-3, "pressure_noise_bar": 0.005}
    scenarios = [
        {"name": "imp", "duration_s": 3.0, "disturbances": [
            {"type": "impulse", "t_s": 1.0, "force_N": 20.0, "duration_s": 0.05}]},
        {"name": "kmax_load", "duration_s": 3.0, "inputs": {"stiffness": "kmax"},
         "plant": {"extra_mass_kg": 1.0}},
        {"name": "noisy_lag", "duration_s": 2.0, "initial_state": {"x_m": 0.81, "v_mps": 0.0},
         "plant": {"mass_kg": 4.1, "pressure_lag_s": 0.03, **noisy}},
    ]
    policies = ["ff", "pid", "mbfb", str(run)]
    batched = evaluate(policies, scenarios)
    alone = evaluate(policies, scenarios, batched=False)
    for sc in ("imp", "kmax_load", "noisy_lag"):
        for p in ("ff", "pid", "mbfb"):
            assert batched["results"][sc][p] == alone["results"][sc][p], (sc, p)
            a, b = batched["traces"][sc][p], alone["traces"][sc][p]
            for f in ("t", "x", "k", "pressure_bar", "pressure_cmd_bar", "rewards"):
                np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        a, b = batched["results"][sc]["run"], alone["results"][sc]["run"]
        assert a["terminated"] == b["terminated"]
        for k in ("position_rmse_mm", "stiffness_rmse_pct", "return"):
            np.testing.assert_allclose(a[k], b[k], rtol=1e-6)
    assert len(batched["traces"]["noisy_lag"]["ff"].t) == 200  # its own 2 s episode


def test_train_on_a_scenario_file_keeps_its_plants_in_the_run(tmp_path):
    # `train --scenario FILE` (identify's --out) trains on that file's plant and randomize
    # ranges instead of the config's, and the run's config.yaml holds the file's content, so
    # the run folder alone says what it was trained on; a built-in name stays a name.
    from mpa_gym.agents.cli import main
    from mpa_gym.agents.evaluation.robustness import training_ranges

    ident = {"name": "identified", "duration_s": 3.0,
             "plant": {"mass_kg": 4.34, "pressure_dead_time_s": 0.021, "slider_friction_N": 1.5},
             "randomize": {"C1_Pa": [172000.0, 174000.0], "pressure_lag_s": [0.029, 0.031]}}
    f = tmp_path / "identified.yaml"
    f.write_text(yaml.safe_dump(ident))
    cfg = tiny_config(tmp_path)
    assert main(["train", "--config", str(cfg), "--scenario", str(f), "--run-dir",
                 str(tmp_path / "run"), "--no-progress"]) == 0
    saved = load_config(tmp_path / "run" / "config.yaml")
    assert saved.env_kwargs["scenario"] == ident
    ranges = training_ranges(str(tmp_path / "run"))
    assert ranges["C1_Pa"] == (172000.0, 174000.0) and ranges["pressure_lag_s"] == (0.029, 0.031)
    assert ranges["mass_kg"] == (4.34, 4.34) and ranges["pressure_dead_time_s"] == (0.021, 0.021)
    drawn = {k for k, (lo, hi) in ranges.items() if lo != hi}
    assert drawn == {"C1_Pa", "pressure_lag_s"}  # none of the config's own ranges
    named = train(cfg, tmp_path / "run2", progress=False, n_timesteps=128, scenario="heldout_a")
    assert load_config(named / "config.yaml").env_kwargs["scenario"] == "heldout_a"
    # bad input: exit 2 and nothing trained
    assert main(["train", "--config", str(cfg), "--scenario", str(tmp_path / "nope.yaml"),
                 "--run-dir", str(tmp_path / "run3")]) == 2
    assert not (tmp_path / "run3").exists()
    assert main(["train", "--resume", str(tmp_path / "run"), "--scenario", "heldout_a"]) == 2
