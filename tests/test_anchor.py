"""The rest-anchored residual policy (agents/learned/anchor.py): zero mean action at zero
features."""

from __future__ import annotations

import copy

import gymnasium as gym
import numpy as np
import pytest
import yaml

import mpa_gym  # noqa: F401
from mpa_gym.agents.evaluation.episodes import Job, run_episodes
from mpa_gym.agents.learned.anchor import RestAnchoredPolicy, set_rest
from mpa_gym.agents.learned.config import ConfigError, parse_config
from mpa_gym.agents.learned.inference import DeployedPolicy
from mpa_gym.agents.learned.policies import LearnedPolicy, load_policy, load_run
from mpa_gym.agents.learned.wrappers import (
    ActionSpec,
    FeatureSpec,
    ForceStiffnessAction,
    TrackingErrorObservation,
)
from mpa_gym.agents.training.train import train
from mpa_gym.analysis.scenario import load_scenario

FEATURES = {"errors_only": True, "harmonics": 1, "remodulate": True, "previous_action": True}
# SB3 runs the network in float32, the deployed path in float64 (tests/test_inference.py)
ATOL = 1e-6


def _policy(anchored: bool, seed: int = 0) -> LearnedPolicy:
    """A LearnedPolicy of the default wrappers around a fresh PPO (random weights, torch's
    default init so the action layer is not scaled to ~0) and made-up normaliser statistics
    (the zero features then map to a point far from the origin of the network's input)."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    def make():
        env = TrackingErrorObservation(gym.make("MPALegResidual-v0", task={"episode_s": 3.0}),
                                       **FEATURES)
        return ForceStiffnessAction(env, force_N=20.0, stiffness_rel=0.3)

    norm = VecNormalize(DummyVecEnv([make]), norm_reward=False, clip_obs=10.0)
    rng = np.random.default_rng(seed)
    d = norm.observation_space.shape[0]
    norm.obs_rms.mean = rng.normal(0.0, 0.5, d)
    norm.obs_rms.var = rng.uniform(0.01, 2.0, d)
    norm.training = False
    model = PPO(RestAnchoredPolicy if anchored else "MlpPolicy", norm, seed=seed, device="cpu",
                policy_kwargs={"net_arch": [64, 64], "ortho_init": False})
    set_rest(model)
    return LearnedPolicy(model, norm, FeatureSpec(**FEATURES), 0.01,
                         ActionSpec(force_N=20.0, stiffness_rel=0.3), 1.5)


def _at_rest(x_ref: float = 0.8, v_ref: float = 0.05) -> np.ndarray:
    """An env observation with X = X̂, V = V̂ (pressures and phase arbitrary; the phase a unit
    vector, as a loaded run checks)."""
    return np.array([x_ref, v_ref, x_ref, v_ref, 0.6, 0.8, 2.1, 0.4, 1.3], dtype=np.float32)


def test_anchored_mean_is_zero_at_rest_and_only_there():
    anchored, plain = _policy(True), _policy(False)
    start = np.array([True])
    a, _ = anchored.predict(_at_rest(), episode_start=start)
    assert np.array_equal(a, np.zeros(2))  # exactly: f(o_rest) − f(o_rest)
    # SB3's own path (model.predict on the normalised zero features) agrees
    zero = anchored.normalizer.normalize_obs(np.zeros((1, anchored.model.observation_space
                                                       .shape[0]), dtype=np.float32))
    assert np.array_equal(anchored.model.predict(zero, deterministic=True)[0], np.zeros((1, 2)))
    # the same weights without the anchor are not zero there (so the check above can fail)
    b, _ = plain.predict(_at_rest(), episode_start=start)
    assert np.max(np.abs(b)) > 1e-2
    # and the anchored policy does act on an error
    off = _at_rest()
    off[0] -= 0.2  # far below the reference (the made-up spreads are O(1))
    c, _ = anchored.predict(off, episode_start=start)
    assert np.max(np.abs(c)) > 1e-3


def test_anchor_follows_every_change_of_the_weights_and_the_rest_point():
    # rollouts reuse f(o_rest) while the weights stay; an optimiser step (in place, as Adam's)
    # or a new normaliser must be seen at once, or the mean would not be zero at rest
    import torch as th

    policy = _policy(True, seed=1)
    pol, start = policy.model.policy, np.array([True])
    assert np.array_equal(policy.predict(_at_rest(), episode_start=start)[0], np.zeros(2))
    with th.no_grad():
        for q in pol.mlp_extractor.policy_net.parameters():
            q.add_(0.3 * th.randn_like(q))
    assert np.array_equal(policy.predict(_at_rest(), episode_start=start)[0], np.zeros(2))
    policy.normalizer.obs_rms.mean = policy.normalizer.obs_rms.mean + 0.7
    set_rest(policy.model)
    assert np.array_equal(policy.predict(_at_rest(), episode_start=start)[0], np.zeros(2))
    # a weight or the rest point assigned anew (not changed in place): its tensor is another
    pol.action_net.bias = th.nn.Parameter(pol.action_net.bias.detach() + 0.5)
    assert np.array_equal(policy.predict(_at_rest(), episode_start=start)[0], np.zeros(2))
    pol.rest_obs = pol.rest_obs.clone()
    policy.normalizer.obs_rms.mean = policy.normalizer.obs_rms.mean - 0.4
    set_rest(policy.model)
    assert np.array_equal(policy.predict(_at_rest(), episode_start=start)[0], np.zeros(2))
    # a submodule assigned anew, and a move or cast (torch swaps the tensors in unregistered)
    replaced = copy.deepcopy(pol.action_net)
    with th.no_grad():
        replaced.bias.add_(0.3)
    pol.action_net = replaced
    assert np.array_equal(policy.predict(_at_rest(), episode_start=start)[0], np.zeros(2))
    pol._apply(lambda t: t.clone())
    policy.normalizer.obs_rms.mean = policy.normalizer.obs_rms.mean + 0.4
    set_rest(policy.model)
    assert np.array_equal(policy.predict(_at_rest(), episode_start=start)[0], np.zeros(2))
    off = _at_rest()
    off[0] -= 0.2
    assert np.max(np.abs(policy.predict(off, episode_start=start)[0])) > 1e-3


def test_deployed_anchored_policy_equals_sb3_and_is_zero_at_rest():
    sb3 = _policy(True, seed=4)
    deployed = DeployedPolicy.from_learned(sb3, 9)
    assert np.max(np.abs(deployed.act(_at_rest(), True))) < ATOL
    env = gym.make("MPALegResidual-v0", scenario="load_1kg", task={"episode_s": 3.0})
    obs, _ = env.reset(seed=0)
    state, start, err, moved = None, np.array([True]), 0.0, 0.0
    for _ in range(200):
        a, state = sb3.predict(obs, state, start)
        b = deployed.act(obs, bool(start[0]))
        err = max(err, float(np.max(np.abs(a - b))))
        moved = max(moved, float(np.max(np.abs(a))))
        obs, _, term, trunc, _ = env.step(a)
        start = np.array([bool(term or trunc)])
        if term or trunc:
            obs, _ = env.reset()
    assert moved > 1e-2 and err < ATOL, (moved, err)


def test_anchored_policy_keeps_the_feedforward_where_it_is_exact():
    # On the nominal plant the feedforward tracks X̂ to a few µm (the start and the integrator),
    # so the anchored policy — random weights, a made-up normaliser — sees features far inside
    # their spread and stays within 1 µm of ff's own trajectory (a tenth of the 10 µm nominal
    # target; it measured 0.44 µm). The plain policy with the same weights drives the leg off
    # by its rest output, more than 100 µm.
    sc = load_scenario("nominal")
    task = {"episode_s": 3.0}
    ff = load_policy("ff")[0]
    jobs = [Job(sc, p, "MPALegResidual-v0", task)
            for p in (ff, _policy(True, 2), _policy(False, 2))]
    ff_trace, anchored, plain = run_episodes(jobs, seed=0)
    assert np.max(np.abs(anchored.x - ff_trace.x)) < 1e-6
    assert np.max(np.abs(plain.x - ff_trace.x)) > 1e-4


def _config(**harness):
    raw = yaml.safe_load(open("configs/ppo_residual.yaml"))
    raw["mpa_gym"].update(harness)
    return raw


def test_anchor_config_errors_name_the_field():
    with pytest.raises(ConfigError, match=r"mpa_gym.anchor_at_rest='yes' must be true or false"):
        parse_config(_config(anchor_at_rest="yes"))
    raw = _config(anchor_at_rest=True)
    wrappers = raw["MPALegResidual-v0"]["env_wrapper"]
    wrappers[0]["mpa_gym.agents.learned.wrappers.TrackingErrorObservation"]["errors_only"] = False
    with pytest.raises(ConfigError, match=r"anchor_at_rest=true needs .*errors_only: true"):
        parse_config(raw)
    assert parse_config(_config()).anchor_at_rest is True  # the default config's
    raw = _config()
    del raw["mpa_gym"]["anchor_at_rest"]
    assert parse_config(raw).anchor_at_rest is False  # off unless a config opts in


def test_a_trained_anchored_run_is_anchored_at_its_saved_normaliser(tmp_path):
    raw = _config(anchor_at_rest=True, eval_scenarios=[], eval_freq=10_000,
                  checkpoint_freq=10_000)
    hp = raw["MPALegResidual-v0"]
    hp.update(n_envs=4, n_timesteps=512, n_steps=64, batch_size=128, n_epochs=2)
    hp["env_kwargs"]["task"]["episode_s"] = 0.5
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(raw))
    run = train(path, tmp_path / "run", progress=False)
    policy, _ = load_run(run)
    pol = policy.model.policy
    assert isinstance(pol, RestAnchoredPolicy)
    zero = np.zeros((1, pol.rest_obs.numel()), dtype=np.float32)
    expected = policy.normalizer.normalize_obs(zero).astype(np.float32).reshape(-1)
    assert np.array_equal(pol.rest_obs.numpy(), expected)  # the saved normaliser's zero
    assert np.max(np.abs(expected)) > 0.0  # training moved the statistics off zero
    a, _ = policy.predict(_at_rest(), episode_start=np.array([True]))
    assert np.array_equal(a, np.zeros(2))
