"""Agents: baselines through the policy interface, PPO train/save/load/resume, configs, report."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import yaml

import mpa_gym  # noqa: F401
from agents.baselines import make_baseline
from agents.config import ConfigError, load_config, parse_config
from agents.evaluate import evaluate, metrics, run_episode, write_report
from agents.policies import load_run
from agents.train import train
from agents.wrappers import (
    FeatureSpec,
    ForceStiffnessAction,
    TrackingErrorObservation,
    TrackingErrorVectorObservation,
    force_stiffness_to_residual,
)
from mpa_gym.analysis.scenario import load_scenario

SHORT = {"name": "short", "duration_s": 6.0, "plant": {"extra_mass_kg": 1.0}}
LOADED = {"name": "loaded", "duration_s": 18.0, "plant": {"extra_mass_kg": 1.0}}


@pytest.mark.parametrize("name", ["ff", "pid", "mbfb"])
def test_baselines_drive_the_env_through_the_policy_interface(name):
    # 18 s: the integrators settle in the first 9 s, the metrics use the last three periods
    env = gym.make("MPALegResidual-v0", scenario=LOADED)
    policy = make_baseline(name, LOADED)
    tr = run_episode(env, policy, seed=3)
    m = metrics(tr, 3.0, None)
    assert not tr.terminated and len(tr.t) == 1800
    if name == "ff":  # the expert sags under the unknown load …
        assert m["position_rmse_mm"] > 10
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
    assert policy.force_stiffness is not None
    sc = {"name": "ev", "duration_s": 3.0}
    r1 = evaluate([str(run)], [sc])["results"]["ev"]["run"]
    r2 = evaluate([str(run)], [sc])["results"]["ev"]["run"]
    assert r1 == r2
    # step by step, the loaded policy (raw observations in, its own state) acts as the model on
    # the training wrappers' observations, mapped to the env's residual action
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
        np.testing.assert_array_equal(
            via, force_stiffness_to_residual(direct, raw.last[None], env.force_N,
                                             env.stiffness_rel, env.scale_bar)[0])
        obs, *_ = env.step(direct[0])
    # the model saw the tracking-error features alone (the env's X, X̂, pressures… left out)
    assert policy.features.errors_only and obs.shape == (2 + policy.features.n_integrals + 2,)


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
     ({"env_wrapper": [{"agents.wrappers.TrackingErrorObservation": {"harmonic": 1}}]},
      r"TrackingErrorObservation: unknown key\(s\) \['harmonic'\]"),
     ({"env_wrapper": [{"agents.wrappers.TrackingErrorObservation": {"harmonics": 9}}]},
      r"harmonics=9 must be a whole number in \[0, 5\]"),
     ({"env_wrapper": [{"agents.wrappers.ForceStiffnessAction": {"force_N": 0}}]},
      r"ForceStiffnessAction: force_N=0 must be a number in \(0, 200\]"),
     ({"env_wrapper": [{"agents.wrappers.ForceStiffnessAction": {"rate_penalty": "big"}}]},
      r"ForceStiffnessAction: rate_penalty='big' must be a number in \[0, 100\]"),
     ({"env_wrapper": ["agents.wrappers.ForceStiffnessAction",
                       "agents.wrappers.ForceStiffnessAction"]}, "given twice"),
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
                                    "env_wrapper": "agents.wrappers.ForceStiffnessAction"}})


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
    assert (tmp_path / "plots" / "a.png").stat().st_size > 10_000
