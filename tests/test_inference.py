"""The deployed (compiled) inference path against SB3's deterministic action.

Both paths call the same front-end kernels (``mpa_gym.agents.learned.frontend``: features, action
map, episode record; tested against independent references in ``tests/test_wrappers.py``), so what
they can disagree on is their own part, the normaliser and the network: that is checked option by
option. One trained run checks the whole path end to end (the front-end wired in the same
order around the network)."""

from __future__ import annotations

import base64
import dataclasses
import json
import shutil
import zipfile

import gymnasium as gym
import numpy as np
import pytest
import yaml
from conftest import tiny_config
from stable_baselines3.common.save_util import load_from_zip_file

import mpa_gym  # noqa: F401
from mpa_gym.agents.learned.frontend import ActionSpec
from mpa_gym.agents.learned.inference import DeployedPolicy
from mpa_gym.agents.learned.policies import LearnedPolicy, load_policy, load_run
from mpa_gym.agents.training.train import train

# SB3 runs the normaliser's output and the network in float32, the deployed path in float64:
# the actions differ by float32 rounding through the 64-wide layers (~1e-7 of O(1) values), far
# inside 1e-6.
ATOL = 1e-6


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A run of the default config, trained for a few hundred steps (the weights and the
    normaliser's statistics are the trained ones; their quality does not matter here)."""
    tmp = tmp_path_factory.mktemp("inference")
    return train(tiny_config(tmp), tmp / "run", progress=False)


def compare(sb3, deployed, env, n=250, restart_at=120, seed=0):
    """Largest |a_sb3 − a_deployed| over ``n`` steps of the env's own observations (SB3's action
    driving it), with a restart (episode_start) in the middle and wherever an episode ends."""
    obs, _ = env.reset(seed=seed)
    state, dstate, start = None, None, np.array([True])
    err, moved = 0.0, 0.0
    for i in range(n):
        a, state = sb3.predict(obs, state, start, deterministic=True)
        b, dstate = deployed.predict(obs, dstate, start)
        err = max(err, float(np.max(np.abs(np.asarray(a, float) - b))))
        moved = max(moved, float(np.max(np.abs(a))))
        obs, _, term, trunc, _ = env.step(np.clip(a, -1, 1))
        if term or trunc:
            obs, _ = env.reset()
        start = np.array([i + 1 == restart_at or term or trunc])
    return err, moved


def test_deployed_run_equals_sb3_deterministic_action(tiny_run):
    sb3, cfg = load_run(tiny_run)
    deployed, _ = load_run(tiny_run, deployed=True)
    assert isinstance(deployed, DeployedPolicy) and deployed.features == sb3.features
    # one front-end: the same settings record, read by the same kernels
    assert deployed.frontend.settings.tobytes() == sb3.frontend.settings.tobytes()
    assert deployed.frontend.settings[0]["adapt"]  # the default config's estimator included
    task = {k: v for k, v in cfg.env_kwargs["task"].items() if k != "episode_s"}
    env = gym.make("MPALegResidual-v0", scenario="load_1kg", task={**task, "episode_s": 5.0})
    err, moved = compare(sb3, deployed, env)
    assert moved > 1e-3  # the actions are not trivially zero
    assert err < ATOL, err
    # the estimator's regressions (on X̂ and V̂; in proportion to k̂) and the harmonic force
    # correction, each on or off, reach both paths alike
    action = sb3.action
    for field, setting, changed in (
            ("adapt_velocity", not action.stiffness_adapt_velocity,
             {"stiffness_adapt_velocity": not action.stiffness_adapt_velocity}),
            ("adapt_relative", not action.stiffness_adapt_relative,
             {"stiffness_adapt_relative": not action.stiffness_adapt_relative}),
            ("harmonic", action.harmonic_force_N is None,
             {"harmonic_force_N": 0.5 if action.harmonic_force_N is None else None})):
        sb3_c = LearnedPolicy(sb3.model, sb3.normalizer, sb3.features, sb3.dt,
                              dataclasses.replace(action, **changed), sb3.residual_scale_bar,
                              sb3.check)
        deployed_c = DeployedPolicy.from_learned(sb3_c, env.observation_space.shape[0])
        assert deployed_c.frontend.settings[0][field] == setting
        err, moved = compare(sb3_c, deployed_c, env)
        assert moved > 1e-3 and err < ATOL, (field, err)


def _untrained(env_id, policy_kwargs, normalize=True, seed=0):
    """A LearnedPolicy around a freshly initialised PPO (random weights) and a normaliser with
    made-up statistics, on the env's observation itself (no front-end): its action is the
    normaliser and the network alone."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    venv = DummyVecEnv([lambda: gym.make(env_id, task={"episode_s": 3.0})])
    norm = None
    if normalize:
        norm = VecNormalize(venv, norm_reward=False, clip_obs=5.0)
        rng = np.random.default_rng(seed)
        d = venv.observation_space.shape[0]
        norm.obs_rms.mean = rng.normal(0, 0.1, d)
        norm.obs_rms.var = rng.uniform(0.01, 2.0, d)
        norm.training = False
    # ortho_init=False: torch's default init, whose action layer is not scaled down to ~0.01
    model = PPO("MlpPolicy", venv, policy_kwargs={**policy_kwargs, "ortho_init": False},
                seed=seed, device="cpu")
    return LearnedPolicy(model, norm, None, 0.01)


@pytest.mark.parametrize("env_id,policy_kwargs,normalize", [
    ("MPALeg-v0", {"net_arch": [32, 32, 16]}, True),
    ("MPALeg-v0", {"net_arch": [64, 64], "activation_fn": __import__("torch").nn.ReLU}, False),
    ("MPALegResidual-v0", {"net_arch": [16]}, True),
    ("MPALegResidual-v0", {"net_arch": [64, 64], "activation_fn": __import__("torch").nn.ELU},
     True),
    ("MPALegResidual-v0", {"net_arch": [32], "activation_fn":
                           __import__("torch").nn.LeakyReLU}, True),
])
def test_deployed_normaliser_and_network_equal_sb3(env_id, policy_kwargs, normalize):
    # every layer and activation option, with and without the normaliser, on observations
    # spread over and beyond the normaliser's clip (±5 after scaling) and the action bounds
    sb3 = _untrained(env_id, policy_kwargs, normalize)
    dim = 9 if env_id == "MPALegResidual-v0" else 8
    deployed = DeployedPolicy.from_learned(sb3, dim)
    obs = np.random.default_rng(7).normal(0.0, 3.0, (300, dim)).astype(np.float32)
    ours = np.array([deployed.act(o, True).copy() for o in obs])
    theirs, _ = sb3.predict(obs)
    assert np.max(np.abs(theirs)) > 1e-2  # the actions are not trivially zero
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=ATOL)
    if normalize:  # the check can fail: the normaliser's statistics matter
        sb3.normalizer.obs_rms.mean = sb3.normalizer.obs_rms.mean + 0.5
        assert np.max(np.abs(sb3.predict(obs)[0] - ours)) > 1e-3


def test_deployed_policy_refuses_a_wrong_observation(tiny_run):
    deployed, _ = load_run(tiny_run, deployed=True)
    with pytest.raises(ValueError, match=r"observation has shape \(8,\).*\(9,\)"):
        deployed.predict(np.zeros(8))


def test_learned_policy_action_is_sb3_predicts_bit_for_bit(tiny_run):
    # LearnedPolicy computes the deterministic action by SB3's own torch operations without
    # model.predict's per-call overhead: it must be model.predict's action exactly, for one
    # observation and batches, float32 and float64 inputs, and beyond the action bounds (clip).
    policy, _ = load_run(tiny_run)
    rng = np.random.default_rng(3)
    dim = policy.model.observation_space.shape[0]
    for n, dtype in ((1, np.float32), (16, np.float64), (257, np.float32)):
        obs = rng.normal(0.0, 4.0, (n, dim)).astype(dtype)
        ours = policy._mean_action(obs)
        theirs, _ = policy.model.predict(obs, deterministic=True)
        assert ours.dtype == theirs.dtype and np.array_equal(ours, theirs)
    big = np.full((2, dim), 50.0)  # far outside the normalised range
    a = policy._mean_action(big)
    assert np.array_equal(a, policy.model.predict(big, deterministic=True)[0])
    assert np.all(np.abs(a) <= 1.0)


def test_saved_model_acts_as_the_algorithm_ppo_load_rebuilds(tiny_run):
    # evaluation loads the network alone (SavedModel, no optimiser, no rollout buffer): its
    # weights, rest point and actions must be those of SB3's PPO.load of the same file, bit for
    # bit, deterministic and sampled (same torch seed)
    import torch
    from stable_baselines3 import PPO

    from mpa_gym.agents.learned.policies import SavedModel

    ours = SavedModel.load(tiny_run / "model.zip")
    theirs = PPO.load(tiny_run / "model.zip", device="cpu")
    assert type(ours.policy) is type(theirs.policy)
    assert ours.num_timesteps == theirs.num_timesteps > 0
    mine, ref = ours.policy.state_dict(), theirs.policy.state_dict()
    assert mine.keys() == ref.keys() and "rest_obs" in mine
    assert all(torch.equal(mine[k], ref[k]) for k in ref)
    obs = np.random.default_rng(5).normal(0.0, 3.0, (64, ours.observation_space.shape[0]))
    assert np.array_equal(ours.predict(obs, deterministic=True)[0],
                          theirs.predict(obs, deterministic=True)[0])
    torch.manual_seed(0)
    sampled = ours.predict(obs)[0]
    torch.manual_seed(0)
    assert np.array_equal(sampled, theirs.predict(obs)[0])
    assert not np.array_equal(sampled, ours.predict(obs, deterministic=True)[0])


def test_both_policies_check_the_estimator_setting():
    # LearnedPolicy and DeployedPolicy are public; a bad time constant is refused by name, as
    # the training wrapper refuses it (one check:
    # mpa_gym.agents.learned.frontend.adapt_time_constant)
    layers = [(np.zeros((2, 9)), np.zeros(2))]  # the env's 9 observations → (a_F, a_k)
    makers = (lambda tau: LearnedPolicy(None, None, None, 0.01,
                                        ActionSpec(stiffness_adapt_s=tau), 1.0),
              lambda tau: DeployedPolicy(layers, "Tanh", 9, action=ActionSpec(
                  stiffness_adapt_s=tau), residual_scale_bar=1.0))
    for make in makers:
        for bad in (0, -1.0, 61.0, float("nan")):
            with pytest.raises(ValueError, match=r"stiffness_adapt_s=.*allowed range "
                                                 r"\(0, 60\] s"):
                make(bad)
        make(3.0)
    # the action map needs the residual env's scale
    with pytest.raises(ValueError, match="needs residual_scale_bar"):
        LearnedPolicy(None, None, None, 0.01, ActionSpec(stiffness_adapt_s=3.0))


def _as_written_before_0_2(model_zip):
    """Rewrite ``model_zip``'s policy class as a model file of 0.1.0 names it: by its module
    then, ``agents.anchor`` (a pickle of STACK_GLOBAL 'agents.anchor' 'RestAnchoredPolicy')."""
    with zipfile.ZipFile(model_zip) as z:
        files = {name: z.read(name) for name in z.namelist()}
    data = json.loads(files["data"])
    assert b"RestAnchoredPolicy" in base64.b64decode(data["policy_class"][":serialized:"])
    module, name = b"agents.anchor", b"RestAnchoredPolicy"
    legacy = (b"\x80\x04\x8c" + bytes([len(module)]) + module + b"\x8c" + bytes([len(name)])
              + name + b"\x93.")
    data["policy_class"][":serialized:"] = base64.b64encode(legacy).decode()
    files["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(model_zip, "w") as z:
        for name, content in files.items():
            z.writestr(name, content)


def test_a_run_folder_written_before_0_2_loads_and_acts_the_same(tiny_run, tmp_path):
    # run folders written before the app moved into mpa_gym.agents name the wrappers
    # agents.wrappers.…, their model file the policy class agents.anchor.RestAnchoredPolicy,
    # and give the supervisor in its flat form (the default config's levels then); such a folder
    # loads, supervised and not, and acts exactly as today's folder declaring that cascade
    flat = {"fallback": "pid", "aperiodic_mm": 0.4, "aperiodic_clip_mm": 0.5,
            "persistent_mm": 2.0, "persistent_clip_mm": 3.0, "last_resort": "afc"}
    declared = {  # written out by hand: what the flat form meant (error_mm 15 over 0.5 s, the
        # aperiodic window shared by both, armed after 2 periods, the fallback given 1 to settle)
        "monitors": {
            "divergence": {"level_mm": 15.0, "window_s": 0.5, "clip_mm": None, "arm_periods": 0},
            "limit_cycle": {"level_mm": 0.4, "window_s": 3.0, "clip_mm": 0.5, "arm_periods": 2},
            "persistent": {"level_mm": 2.0, "window_s": 3.0, "clip_mm": 3.0, "arm_periods": 2}},
        "stages": [{"controller": "policy",
                    "monitors": ["divergence", "limit_cycle", "persistent"]},
                   {"controller": "pid", "monitors": ["divergence"], "grace_periods": 1},
                   {"controller": "afc"}],
        "select": None}  # the flat form always started the policy
    today = tmp_path / "today_run"
    shutil.copytree(tiny_run, today)
    cfg = yaml.safe_load((today / "config.yaml").read_text())
    cfg["mpa_gym"]["supervisor"] = declared
    (today / "config.yaml").write_text(yaml.safe_dump(cfg))
    old = tmp_path / "old_run"
    shutil.copytree(tiny_run, old)
    cfg = yaml.safe_load((old / "config.yaml").read_text())
    text = yaml.safe_dump(cfg).replace("mpa_gym.agents.learned.wrappers.", "agents.wrappers.")
    cfg = yaml.safe_load(text)
    cfg["mpa_gym"]["supervisor"] = flat
    (old / "config.yaml").write_text(yaml.safe_dump(cfg))
    _as_written_before_0_2(old / "model.zip")
    with pytest.raises(ModuleNotFoundError, match="agents"):  # what SB3 alone makes of it
        load_from_zip_file(old / "model.zip", device="cpu")
    assert "agents.wrappers.TrackingErrorObservation" in (old / "config.yaml").read_text()
    env = gym.make("MPALegResidual-v0", scenario="heldout_a")
    obs = np.stack([env.reset(seed=s)[0] for s in range(6)])
    obs[:, 0] += np.linspace(-0.01, 0.01, 6)  # off the reference: the features are not zero
    now, _, cfg_now = load_policy(str(today))
    then, _, cfg_then = load_policy(str(old))
    assert cfg_now.observation_wrapper == cfg_then.observation_wrapper
    assert cfg_now.action_wrapper == cfg_then.action_wrapper
    assert cfg_now.supervisor == cfg_then.supervisor
    state_now = state_then = None
    for k in range(400):  # long enough for the supervisor's monitors to arm and trip
        start = np.full(6, k == 0)
        a, state_now = now.predict(obs, state_now, start)
        b, state_then = then.predict(obs, state_then, start)
        np.testing.assert_array_equal(a, b)
