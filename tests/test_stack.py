"""Stacks (``baselines.stack``): controllers built per scenario, cell or rig run as one object,
one call per step, each row its own controller's."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
from conftest import tiny_config

import mpa_gym  # noqa: F401
from mpa_gym.agents.controllers.baselines import make_baseline, stack, stacked
from mpa_gym.agents.controllers.supervisor import (
    FALLBACK,
    LAST_RESORT,
    POLICY,
    Divergence,
    Stage,
    Supervised,
    SupervisorSpec,
)
from mpa_gym.agents.evaluation.episodes import Job, eval_task, run_episodes, stack_jobs
from mpa_gym.agents.evaluation.robustness import plant_jobs
from mpa_gym.agents.learned.policies import ALONE, LearnedPolicy, load_for_plant
from mpa_gym.agents.training.train import train
from mpa_gym.analysis.scenario import load_scenario

INF = float("inf")
DT = 0.01
SLOW = {"pressure_dead_time_s": 0.03, "pressure_lag_s": 0.04, "extra_mass_kg": 0.7}
# the regulator delays a policy is told, one pair per plant: none of the code's defaults
TOLD = [{"pressure_dead_time_s": 0.0, "pressure_lag_s": 0.0},
        {"pressure_dead_time_s": 0.02, "pressure_lag_s": 0.03},
        {"pressure_dead_time_s": 0.045, "pressure_lag_s": 0.01}]


class Wobbly:
    """A stateless stand-in residual that stacks (a user's class may: ``stack_rows``)."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        o = np.atleast_2d(observation)
        return (0.3 * np.tanh(o[:, :2] * 7.0)).astype(np.float32), state

    @classmethod
    def stack_rows(cls, policies):
        return policies[0]  # no state, nothing of its own per row


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny trained run of the default config (told the rig's delays, supervised)."""
    tmp = tmp_path_factory.mktemp("stack")
    return train(tiny_config(tmp, n_envs=2, n_timesteps=64, n_steps=32, batch_size=64,
                             n_epochs=1), tmp / "run", progress=False)


def test_a_stack_of_supervisors_runs_each_row_as_its_own_supervisor():
    # Three supervisors of one spec, each built for a scenario of its own (other loads: other
    # plans for rc and pid), started at the policy (with a monitor that hands it over a few
    # steps in on this slow, loaded rig), at rc and at pid (chosen), as one stack in one
    # batch: every row's episode is its own supervisor's run alone, bit for bit (Wobbly has
    # no state, and rc and pid stack bit for bit), with its own start and stages.
    spec = SupervisorSpec((Divergence(2.0, 0.5, None, 0),),
                          (Stage("policy", ("divergence",)), Stage("rc", ("divergence",)),
                           Stage("pid")))
    scenarios = [load_scenario(n) for n in ("nominal", "load_1kg", "mass_mismatch")]
    figures = [[0.4, 0.39, 0.5], [INF, 0.3, 0.5], [INF, INF, 0.3]]

    def build():
        sups = [Supervised(Wobbly(), make_baseline("rc", sc), DT, sc.reference.period, spec,
                           make_baseline("pid", sc)) for sc in scenarios]
        for s, f in zip(sups, figures, strict=True):
            s.choose(f, [5.0] * 3)
        return sups

    sups = build()
    assert [s.start for s in sups] == [POLICY, FALLBACK, LAST_RESORT]
    one = stack(sups)
    together = run_episodes([Job(sc, one, "MPALegResidual-v0", {}, plant=SLOW, seed=11)
                             for sc in scenarios], 11)
    alone = run_episodes([Job(sc, s, "MPALegResidual-v0", {}, plant=SLOW, seed=11)
                          for sc, s in zip(scenarios, build(), strict=True)], 11)
    for a, b in zip(together, alone, strict=True):
        assert a.start == b.start
        np.testing.assert_array_equal(a.fallback, b.fallback)
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.pressure_cmd_bar, b.pressure_cmd_bar)
    # the policy's row was handed to rc a few steps in and rc's on to pid: the stack's
    # monitors judged that row, stage by stage
    took = np.flatnonzero(together[0].fallback)
    assert 0 < took[0] < 50 and set(together[0].fallback) == {POLICY, FALLBACK, LAST_RESORT}
    assert [t.start for t in together] == [POLICY, FALLBACK, LAST_RESORT]


def test_a_stack_of_learned_policies_acts_on_each_row_as_its_own_policy(run):
    # Three loads of a run, each told the delays of a rig of its own, stacked: on the same
    # observations, each row's action is its own policy's to float32 rounding (torch's product
    # over a batch of rows need not round the last bit as over one row: ε ≈ 6e-8 per
    # operation, a few hundred of them through two layers of 64 and the action map, well
    # under 1e-6), step after step of the features' integrals and the estimator's state. The
    # delays reach the rows: told none, the rows' actions differ.
    sc = load_scenario("heldout_a")
    members = [load_for_plant(str(run) + ALONE, sc, plant)[0] for plant in TOLD]
    one = stack(members)
    assert isinstance(one, LearnedPolicy)
    env = gym.make("MPALegResidual-v0", scenario=sc, task=eval_task(load_for_plant(
        str(run) + ALONE, sc, None)[2]))
    obs, _ = env.reset(seed=5)
    rng = np.random.default_rng(7)
    untold = stack([load_for_plant(str(run) + ALONE, sc, TOLD[0])[0]] * len(TOLD))
    differ = 0.0
    for _ in range(200):
        batch = np.repeat(obs[None], len(TOLD), axis=0)
        got, _ = one.predict(batch)
        want = np.stack([m.predict(obs)[0] for m in members])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
        differ = max(differ, float(np.abs(got - untold.predict(batch)[0]).max()))
        obs, *_ = env.step(np.clip(want[0] + rng.normal(0, 0.05, 2), -1, 1).astype(np.float32))
    env.close()
    assert differ > 1e-3


def test_what_does_not_stack_is_refused_by_name(run):
    sc = load_scenario("nominal")
    learned = load_for_plant(str(run) + ALONE, sc, TOLD[1])[0]
    with pytest.raises(ValueError, match=r"controllers of one kind only"):
        stack([learned, make_baseline("pid", sc)])
    with pytest.raises(ValueError, match=r"object does not stack \(no stack_rows\)"):
        stack([object(), object()])
    assert stacked([object(), object()]) is None and stacked([]) is None
    other = LearnedPolicy(learned.model, None, learned.features, learned.dt, learned.action,
                          learned.residual_scale_bar)
    with pytest.raises(ValueError, match=r"one model, normaliser, features and action map"):
        stack([learned, other])
    # the estimator's regressions and the harmonic force correction are part of the action map
    action = learned.action
    for changed in (
            dataclasses.replace(action,
                                stiffness_adapt_velocity=not action.stiffness_adapt_velocity),
            dataclasses.replace(action,
                                stiffness_adapt_relative=not action.stiffness_adapt_relative),
            dataclasses.replace(action, harmonic_force_N=(0.5 if action.harmonic_force_N is None
                                                          else None))):
        mapped = LearnedPolicy(learned.model, learned.normalizer, learned.features, learned.dt,
                               changed, learned.residual_scale_bar)
        with pytest.raises(ValueError, match=r"one model, normaliser, features and action map"):
            stack([learned, mapped])
    one = stack([learned, learned, learned])
    with pytest.raises(ValueError, match=r"stack of learned policies does not stack again"):
        stack([one, one])
    env = gym.make("MPALegResidual-v0", scenario=sc)
    obs, _ = env.reset(seed=0)
    env.close()
    with pytest.raises(ValueError, match=r"a stack of 3 policies got a batch of 2 observations"):
        one.predict(np.repeat(obs[None], 2, axis=0))
    spec = SupervisorSpec()
    sups = [Supervised(Wobbly(), make_baseline("rc", sc), DT, period, spec,
                       make_baseline("pid", sc)) for period in (3.0, 2.0)]
    with pytest.raises(ValueError, match=r"one spec, control period and reference period"):
        stack(sups)
    both = stack([sups[0], sups[0], sups[0]])
    with pytest.raises(ValueError, match=r"a stack of 3 supervisors got a batch of 2"):
        both.predict(np.repeat(obs[None], 2, axis=0))


def test_a_sweeps_plants_told_their_delays_make_one_network_call_per_step(run, monkeypatch):
    # plant_jobs loads a policy that observes delays once per pair of delays told (three
    # here); stacked, the batch makes one network call per step, not three.
    calls = []
    mean_action = LearnedPolicy._mean_action

    def counted(self, obs):
        calls.append(len(obs))
        return mean_action(self, obs)

    monkeypatch.setattr(LearnedPolicy, "_mean_action", counted)
    sc = load_scenario({"name": "short", "duration_s": 2.0})
    jobs = plant_jobs(str(run) + ALONE, sc, TOLD, seed=3)
    assert len({id(j.policy) for j in jobs}) == 1
    traces = run_episodes(jobs, 3)
    assert len(calls) == max(len(tr.t) for tr in traces) == 200 and set(calls) == {3}


def test_every_evaluation_path_calls_a_runs_network_once_per_step_for_all_its_plants(
        run, monkeypatch):
    # Three plants of other delays: the report's scenarios (the policy alone, the supervised
    # loop and the start's prediction on each model), the random rigs, the model predictions
    # of several loads and training's held-out evaluation each give the network all three
    # rows in one call, never a row at a time.
    from mpa_gym.agents.evaluation.evaluate import evaluate
    from mpa_gym.agents.evaluation.rigs import random_rigs
    from mpa_gym.agents.evaluation.select import predict
    from mpa_gym.agents.learned.policies import load_policy, load_run
    from mpa_gym.agents.training.callbacks import held_out_metrics

    rows: list[int] = []
    mean_action = LearnedPolicy._mean_action

    def counted(self, obs):
        rows.append(len(obs))
        return mean_action(self, obs)

    monkeypatch.setattr(LearnedPolicy, "_mean_action", counted)
    scenarios = [load_scenario({"name": f"p{i}", "duration_s": 2.0, "plant": plant})
                 for i, plant in enumerate(TOLD)]
    evaluate([str(run)], scenarios)
    assert rows and set(rows) == {3}, sorted(set(rows))
    rows.clear()
    random_rigs([str(run) + ALONE], 3, 11, 0)
    assert rows and set(rows) == {3}, sorted(set(rows))
    rows.clear()
    predict([load_policy(str(run), {"scenario": sc}) for sc in scenarios], scenarios,
            [None] * 3)
    assert rows and set(rows) == {3}, sorted(set(rows))
    rows.clear()
    policy, cfg = load_run(run)
    held_out_metrics(cfg, scenarios, policy.model, policy.normalizer)
    assert rows and set(rows) == {3}, sorted(set(rows))


def test_a_stack_is_made_once_and_of_whole_groups():
    sc = load_scenario("nominal")
    spec = SupervisorSpec()
    sups = [Supervised(Wobbly(), make_baseline("rc", sc), DT, 3.0, spec,
                       make_baseline("pid", sc)) for _ in range(2)]
    one = stack(sups)
    with pytest.raises(ValueError, match=r"stack of supervisors does not stack again"):
        stack([one, one])
    with pytest.raises(ValueError, match=r"choose on each before stacking"):
        one.choose([0.5, 0.4, 0.3])
    pids = stack([make_baseline("pid", sc), make_baseline("pid", load_scenario("load_1kg"))])
    with pytest.raises(ValueError, match=r"stack of controllers does not stack again"):
        stack([pids, pids])

    class Mine(type(make_baseline("ff"))):
        """A subclass of ZeroResidual: it may act per row, so it does not stack as zero."""

    assert stacked([Mine(), Mine()]) is None
    jobs = [Job(sc, make_baseline("pid", sc), "MPALegResidual-v0", {}) for _ in range(3)]
    with pytest.raises(ValueError, match=r"job\(s\) \[1\] in two groups"):
        stack_jobs(jobs, [[0, 1], [1, 2]])
