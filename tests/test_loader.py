"""The loader (``mpa_gym.agents.load_policy``) and how a loaded policy can be called: the state
kept when the caller drops it, per row of a batch, restarted by ``reset`` / ``episode_start``;
an observation that is not the run's env's own refused by name; the numbers the evaluation
reports reproduced by a plain gymnasium loop over the loaded policy.

The references are not the code under test: a row of a batch against the same row run alone in
a policy of its own, the stateless loop against the explicit-state loop that the evaluation and
the rig run (and against a policy that forgets its state, which must differ), the evaluation's
metrics against an episode of a single gymnasium env stepped by hand, the features the training
wrappers compute, and what SB3 itself does with ``model.zip``."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from conftest import tiny_config

import mpa_gym  # noqa: F401
from mpa_gym.agents.controllers.supervisor import Supervised
from mpa_gym.agents.evaluation.episodes import eval_task
from mpa_gym.agents.learned.config import EVAL_SEED
from mpa_gym.agents.learned.policies import load_run
from mpa_gym.agents.learned.wrappers import ForceStiffnessAction, TrackingErrorObservation
from mpa_gym.agents.training.train import train
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.analysis.simulate import metric_window


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A run of the default config (its supervisor and front-end included), trained for a few
    hundred steps: its weights and statistics are real, their quality does not matter here."""
    tmp = tmp_path_factory.mktemp("loader")
    return train(tiny_config(tmp), tmp / "run", progress=False)


def _episode(policy, env, how, seed=0, steps=None):
    """The actions of one episode of ``policy`` on ``env``: ``how`` = "explicit" (the state
    passed back, episode_start at the first step: the evaluation's and the rig's loop),
    "stateless" (``predict(obs)`` after ``reset()``) or "forgetful" (every step a new
    episode: what dropping the state did before the policy kept it)."""
    obs, _ = env.reset(seed=seed)
    policy.reset()
    state, start, out, done = None, np.array([True]), [], False
    while not done and (steps is None or len(out) < steps):
        if how == "explicit":
            a, state = policy.predict(obs, state, start)
        elif how == "stateless":
            a, _ = policy.predict(obs)
        else:
            a, _ = policy.predict(obs, None, np.array([True]))
        start = np.array([False])
        out.append(np.array(a, dtype=np.float64))
        obs, _, term, trunc, _ = env.step(a)
        done = term or trunc
    return np.array(out)


def test_the_package_exports_the_one_loader():
    # importing mpa_gym.agents stays light (the CLI imports it): the loader comes on first use
    code = ("import sys, mpa_gym.agents as a; assert 'torch' not in sys.modules; "
            "assert 'mpa_gym.agents.learned.policies' not in sys.modules; "
            "from mpa_gym.agents.learned.policies import load_policy; "
            "assert a.load_policy is load_policy; assert 'load_policy' in a.__all__")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("supervised,deployed", [(True, False), (False, False), (False, True),
                                                 (True, True)])
def test_a_stateless_loop_acts_as_the_explicit_state_loop(run, supervised, deployed):
    from mpa_gym.agents import load_policy

    policy, env_id, cfg = load_policy(run, deployed=deployed, supervised=supervised)
    assert isinstance(policy, Supervised) == supervised  # the reports' took_over sees it
    env = gym.make(env_id, scenario="load_1kg", task={**eval_task(cfg), "episode_s": 2.0})
    explicit = _episode(policy, env, "explicit")
    stateless = _episode(policy, env, "stateless")
    np.testing.assert_array_equal(stateless, explicit)  # bit for bit: the same computation
    # the check can fail: a policy that forgets its state each step acts otherwise
    forgetful = _episode(policy, env, "forgetful")
    assert np.max(np.abs(forgetful - explicit)) > 1e-3
    # a second episode after reset() is a first one again, not the last one continued
    again = _episode(policy, env, "stateless")
    np.testing.assert_array_equal(again, explicit)


def test_without_reset_the_state_carries_over_and_episode_start_restarts_it(run):
    from mpa_gym.agents import load_policy

    policy, env_id, cfg = load_policy(run, supervised=False)
    env = gym.make(env_id, scenario="load_1kg", task={**eval_task(cfg), "episode_s": 1.0})
    first = _episode(policy, env, "stateless")
    obs, _ = env.reset(seed=0)  # a new episode, the policy not told
    carried, _ = policy.predict(obs)
    assert np.max(np.abs(carried - first[0])) > 1e-6  # its integrals went on
    obs, _ = env.reset(seed=0)
    restarted, _ = policy.predict(obs, episode_start=np.array([True]))
    np.testing.assert_array_equal(restarted, first[0])


def test_a_batch_keeps_a_state_per_row(run):
    # four legs on four scenarios in one batch, stateless, one restarting mid-way: each row
    # acts as the same leg run alone by a policy of its own
    from mpa_gym.agents import load_policy

    scenarios = ["nominal", "load_1kg", "heldout_a", "mass_mismatch"]
    batch_policy, env_id, cfg = load_policy(run, supervised=False)
    task = {**eval_task(cfg), "episode_s": 1.0}
    envs = [gym.make(env_id, scenario=s, task=task) for s in scenarios]
    obs = np.stack([e.reset(seed=i)[0] for i, e in enumerate(envs)])
    restart_row, restart_at, steps = 2, 40, 90
    batched = []
    for k in range(steps):
        start = np.zeros(len(envs), dtype=bool)
        if k == restart_at:  # row 2's env resets; the policy is told by episode_start only
            obs[restart_row] = envs[restart_row].reset(seed=7)[0]
            start[restart_row] = True
        a, _ = batch_policy.predict(obs, episode_start=start if start.any() else None)
        batched.append(a.astype(np.float64))
        obs = np.stack([e.step(a[i])[0] for i, e in enumerate(envs)])
    batched = np.array(batched)
    for i, sc in enumerate(scenarios):
        alone, _, _ = load_policy(run, supervised=False)
        env = gym.make(env_id, scenario=sc, task=task)
        if i != restart_row:
            ref = _episode(alone, env, "explicit", seed=i, steps=steps)
        else:
            ref = np.concatenate([_episode(alone, env, "explicit", seed=i, steps=restart_at),
                                  _episode(alone, env, "explicit", seed=7,
                                           steps=steps - restart_at)])
        # rows of one torch matmul against a matmul of one row: float32 summation order
        np.testing.assert_allclose(batched[:, i], ref, rtol=0, atol=1e-6)
    assert np.max(np.abs(np.diff(batched, axis=1))) > 1e-3  # the rows do differ


def test_a_stateless_batch_of_another_size_is_refused_unless_it_starts(run):
    from mpa_gym.agents import load_policy

    policy, env_id, _ = load_policy(run, supervised=False)
    env = gym.make(env_id, scenario="nominal")
    obs = np.stack([env.reset(seed=s)[0] for s in range(3)])
    policy.predict(obs)
    with pytest.raises(ValueError, match=r"batch of 2 observations.*3 rows.*policy\.reset\(\)"):
        policy.predict(obs[:2])
    policy.predict(obs[:2], episode_start=np.ones(2, dtype=bool))  # a new episode: accepted
    policy.reset()
    policy.predict(obs[:1])


def test_loaded_policies_keep_separate_states(run):
    # the SB3 model is read once per process and shared; the episode state is each load's own:
    # a's episode, interleaved with b's calls on other observations, acts as c's alone
    a, _ = load_run(run)
    b, _ = load_run(run)
    c, _ = load_run(run)
    assert a is not b and a.model is b.model
    env = gym.make("MPALegResidual-v0", scenario="load_1kg")
    other, _ = gym.make("MPALegResidual-v0", scenario="heldout_a").reset(seed=3)
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        x, _ = a.predict(obs)
        b.predict(other)
        y, _ = c.predict(obs)
        np.testing.assert_array_equal(x, y)
        obs, *_ = env.step(x)


def _wrapped(cfg, scenario="load_1kg", steps=30):
    """The features the run's training wrappers give the network after ``steps`` steps of zero
    action, and the same normalised as in training."""
    env = gym.make(cfg.env_id, scenario=scenario, task=eval_task(cfg))
    env = ForceStiffnessAction(TrackingErrorObservation(env, **cfg.observation_wrapper),
                               **cfg.action_wrapper)
    feat, _ = env.reset(seed=0)
    for _ in range(steps):
        feat, *_ = env.step(np.zeros(2, dtype=np.float32))
    return feat


@pytest.mark.parametrize("deployed", [False, True])
def test_an_observation_of_another_wrapper_chain_or_env_is_refused_by_name(run, deployed):
    from mpa_gym.agents import load_policy

    policy, env_id, cfg = load_policy(run, deployed=deployed)
    feat = _wrapped(cfg)
    sb3, _ = load_run(run)
    normalised = sb3.normalizer.normalize_obs(feat[None])[0]
    other, _ = gym.make("MPALeg-v0", scenario="load_1kg").reset(seed=0)
    for wrong in (feat, normalised, other):
        with pytest.raises(ValueError, match=rf"{env_id} itself, shape \(9,\)"):
            policy.predict(wrong)
    with pytest.raises(ValueError, match=r"MPALeg-v0's width"):
        policy.predict(other)
    good, _ = gym.make(env_id, scenario="load_1kg").reset(seed=0)
    policy.predict(good)  # the env's own observation is taken


def test_model_zip_alone_takes_features_and_the_run_folder_says_so(run):
    # what SB3 does with the bare model file (the reason for README.txt): predict checks the
    # shape only, so any array of the features' width is taken without a word (the env's own
    # observation too, where the widths coincide: 9 and 9 with one previous action) and the
    # default's raw observation (9 wide; its features 33) is refused for its shape alone;
    # load with the env checks the spaces and refuses
    from stable_baselines3 import PPO

    model = PPO.load(run / "model.zip", device="cpu")
    obs, _ = gym.make("MPALegResidual-v0", scenario="load_1kg").reset(seed=0)
    assert model.observation_space.shape != obs.shape
    with pytest.raises(ValueError, match="Unexpected observation shape"):
        model.predict(obs, deterministic=True)
    unnormalised = np.full(model.observation_space.shape, 5.0, dtype=np.float32)
    model.predict(unnormalised, deterministic=True)  # not features, and not normalised: taken
    with pytest.raises(ValueError, match="Observation spaces do not match"):
        PPO.load(run / "model.zip", env=gym.make("MPALegResidual-v0"), device="cpu")
    text = (run / "README.txt").read_text()
    assert "MPALegResidual-v0" in text and f"shape {model.observation_space.shape}" in text
    # its example runs as written, from the folder the run was trained from (through episode
    # ends: the tiny run's episodes are 0.5 s)
    code = "\n".join(line[4:] for line in text.splitlines() if line.startswith("    "))
    subprocess.run([sys.executable, "-c", code], cwd=run.parent, check=True, timeout=300)


def test_the_loaded_policy_reproduces_the_evaluation(run):
    # evaluate's numbers (batched vector envs, explicit state) from a plain gymnasium loop
    # over the loaded policy, stateless, supervised and alone
    from mpa_gym.agents import load_policy
    from mpa_gym.agents.evaluation.evaluate import evaluate
    from mpa_gym.agents.evaluation.select import choose_starts

    sc = load_scenario("load_1kg")
    report = evaluate([str(run)], [sc.name])["results"][sc.name]
    for supervised, label in ((True, run.name), (False, f"{run.name} (alone)")):
        policy, env_id, cfg = load_policy(run, {"scenario": sc.name}, supervised=supervised)
        if supervised:  # its start chosen on the scenario's model, as evaluate chooses it
            choose_starts([(policy, env_id, cfg)], [sc], [None])
        env = gym.make(env_id, scenario=sc.name, task=eval_task(cfg))
        obs, info = env.reset(seed=EVAL_SEED)
        policy.reset()
        t, e, done = [], [], False
        while not done:
            action, _ = policy.predict(obs)
            obs, _, term, trunc, info = env.step(action)
            t.append(info["t_s"])
            e.append(info["x_m"] - info["x_ref_m"])
            done = term or trunc
        w = metric_window(np.array(t), sc.reference.period)
        rmse_mm = float(np.sqrt(np.mean(np.array(e)[w] ** 2)) * 1e3)
        # the vector env steps each leg as the single env does (tests/test_vector.py)
        assert rmse_mm == pytest.approx(report[label]["position_rmse_mm"], rel=1e-9), label


def test_the_loader_names_what_it_cannot_load(run):
    from mpa_gym.agents import load_policy

    with pytest.raises(ValueError, match=r"which='last' must be one of \['best', 'final'\]"):
        load_policy(run, which="last")
    with pytest.raises(FileNotFoundError, match=r"best_model\.zip not found"):
        load_policy(run, which="best")  # the tiny run evaluated nothing, so has no best/
