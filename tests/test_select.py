"""The supervisor's start, chosen on the model (``Selection``, agents/evaluation/select.py)."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from conftest import REALTIME, tiny_config

import mpa_gym  # noqa: F401
import mpa_gym.agents.evaluation.robustness as robustness_module
import mpa_gym.agents.rig.rollout as rollout_module
from mpa_gym.agents.cli import show_rollout
from mpa_gym.agents.controllers.baselines import make_baseline
from mpa_gym.agents.controllers.supervisor import (
    FALLBACK,
    LAST_RESORT,
    NOISE_FLOOR_MM,
    POLICY,
    Divergence,
    Selection,
    Stage,
    Supervised,
    SupervisorSpec,
    hand_overs,
    handed_over,
)
from mpa_gym.agents.evaluation.episodes import (
    Job,
    eval_task,
    run_episode,
    run_episodes,
    score_mm,
    score_stiffness_pct,
    trace_metrics,
)
from mpa_gym.agents.evaluation.rigs import random_rigs
from mpa_gym.agents.evaluation.robustness import (
    Grid,
    _cell,
    _scenario,
    cell_metrics,
    plant_jobs,
    robustness,
    run_batches,
)
from mpa_gym.agents.evaluation.select import MODEL_SEED, choose_starts, model_of, predict
from mpa_gym.agents.learned.policies import ALONE, load_policy
from mpa_gym.agents.rig.rollout import read_log, rollout
from mpa_gym.agents.training.train import train
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.hardware.emulator import EmulatorProcess

INF = math.inf
DT = 0.01
# a rig none of the code's defaults describe: long regulator delays and a load
SLOW = {"pressure_dead_time_s": 0.03, "pressure_lag_s": 0.04, "extra_mass_kg": 0.7}


@pytest.mark.parametrize("predicted, start", [
    ([0.50, 0.45, 0.90], POLICY),  # the fallback better, but within the ratio
    ([1.20, 1.00], POLICY),  # exactly the ratio: not better by more than it
    ([0.50, 0.41, 0.90], FALLBACK),  # 0.50 > 1.2 x 0.41
    ([0.50, 0.41, 0.30], LAST_RESORT),  # the best of the later stages
    ([0.50, 0.30, 0.30], FALLBACK),  # equals: the earlier
    ([INF, INF, 2.0], LAST_RESORT),  # the policy and the fallback unstable on the model
    ([INF, 3.0], FALLBACK),
    ([INF, INF, INF], POLICY),  # nothing known better: the monitors judge the policy
    # below the noise floor figures are alike: 0.001 vs 0.0001 is no reason
    ([0.001, 0.0001, 0.002], POLICY),
    ([0.045, 0.034], POLICY),
    ([1.3 * NOISE_FLOOR_MM, 0.01], FALLBACK),  # over 1.2 x the floor
    ([1.1 * NOISE_FLOOR_MM, 0.01], POLICY),  # under it
])
def test_the_policy_starts_unless_a_later_stage_is_predicted_better_by_the_ratio(
        predicted, start):
    assert Selection(1.2, stiffness_ratio=None).start(predicted) == start
    # stiffness figures that block nothing (every stage's alike) change no start
    assert Selection(1.2, 1.0).start(predicted, [2.0] * len(predicted)) == start


@pytest.mark.parametrize("mm, pct, start", [
    ([0.75, 0.48], [8.1, 14.1], POLICY),  # rc better on position, 1.7x worse on stiffness
    ([0.75, 0.48], [8.1, 8.9], FALLBACK),  # 8.9 <= 1.1 x 8.1
    ([0.75, 0.48], [8.1, 8.92], POLICY),  # 8.92 > 1.1 x 8.1 = 8.91
    ([0.75, 0.48], [8.1, 5.0], FALLBACK),  # better on both
    # the fallback blocked on stiffness, the last resort not: the best stage that passes both
    ([0.75, 0.40, 0.60], [8.1, 14.0, 8.0], LAST_RESORT),
    ([0.75, 0.40, 0.50], [8.1, 8.0, 8.0], FALLBACK),  # both pass: the better on position
    ([INF, 3.0], [INF, 30.0], FALLBACK),  # the policy unstable: it tracks no stiffness either
    ([INF, INF, 2.0], [INF, INF, 30.0], LAST_RESORT),
    ([0.75, 0.75], [8.1, 1.0], POLICY),  # better stiffness alone is no reason
])
def test_with_a_stiffness_ratio_a_later_stage_starts_only_if_not_worse_on_stiffness(
        mm, pct, start):
    # The residual task tracks position and stiffness (Eq. 23): a stage predicted better on
    # position but more than stiffness_ratio x worse on stiffness is no improvement to start
    # at. (The first two rows are offnominal.yaml's figures, CHANGELOG issue 36.)
    assert Selection(1.1, 1.1).start(mm, pct) == start


def test_the_default_start_is_chosen_on_position_alone():
    # The shipped spec (SupervisorSpec's defaults, the default config's section) starts the
    # stage predicted better on position by over the ratio whatever its stiffness: the
    # audit's 1.2x on position holds only if a policy 1.3-3.2x worse than rc is not kept for
    # its stiffness (CHANGELOG, issue 36). The figures are the rows above that a
    # stiffness_ratio of 1.1 keeps the policy on.
    default = SupervisorSpec().select
    assert default.stiffness_ratio is None
    assert default.start([0.75, 0.48], [8.1, 14.1]) == FALLBACK
    assert default.start([0.75, 0.40, 0.60], [8.1, 14.0, 8.0]) == FALLBACK
    assert default.start([0.75, 0.70], [8.1, 1.0]) == POLICY  # within the ratio on position
    assert default.start([0.75, 0.48]) == FALLBACK  # no stiffness figures needed


def test_a_start_needs_a_figure_per_stage():
    with pytest.raises(ValueError, match=r"one figure per stage, at least two stages"):
        Selection().start([0.5])
    with pytest.raises(ValueError, match=r"supervisor.select.stiffness_ratio=1.1 needs one "
                                         r"figure per stage \(2\)"):
        Selection(1.1, 1.1).start([0.5, 0.4])
    with pytest.raises(ValueError, match=r"supervisor.select.stiffness_ratio.*0.9.*\[1"):
        Selection(1.1, 0.9)
    sup = Supervised(Wobbly(), make_baseline("rc"), DT, 3.0, SupervisorSpec(),
                     make_baseline("pid"))
    with pytest.raises(ValueError, match=r"one figure per stage \(3\)"):
        sup.choose([0.5, 0.4])
    with pytest.raises(ValueError, match=r"predicted_stiffness_pct=\[1.0\]: one figure per "
                                         r"stage \(3\)"):
        sup.choose([0.5, 0.4, 0.3], [1.0])


class Wobbly:
    """A stand-in residual whose actions would show in the trace if it drove."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        o = np.atleast_2d(observation)
        return (0.3 * np.tanh(o[:, :2] * 7.0)).astype(np.float32), state


@pytest.mark.parametrize("start, alone", [(FALLBACK, "rc"), (LAST_RESORT, "pid")])
def test_a_loop_started_at_a_fallback_drives_exactly_as_that_fallback_alone(start, alone):
    # Identity: from the first step the chosen stage's controller drives from its rest
    # state, so the supervised episode is the fallback's own episode, bit for bit, on a
    # plant with dead time, lag and a load; the report says it was chosen, not handed over.
    sc = load_scenario("nominal")
    predicted = [INF, 0.3, 0.5] if start == FALLBACK else [INF, INF, 0.3]
    sup = Supervised(Wobbly(), make_baseline("rc", sc), DT, sc.reference.period,
                     SupervisorSpec(), make_baseline("pid", sc))
    assert sup.choose(predicted, [INF if v == INF else 5.0 for v in predicted]) == start
    ref = make_baseline(alone, sc)
    got, want = run_episodes([Job(sc, sup, "MPALegResidual-v0", {}, plant=SLOW, seed=11),
                              Job(sc, ref, "MPALegResidual-v0", {}, plant=SLOW, seed=11)], 11)
    np.testing.assert_array_equal(got.x, want.x)
    np.testing.assert_array_equal(got.pressure_cmd_bar, want.pressure_cmd_bar)
    assert got.start == start and np.all(got.fallback == start)
    m = trace_metrics(got, sc.reference.period)
    key = "fallback" if start == FALLBACK else "last_resort"
    assert m["chosen"] == key and m["policy_share"] == 0.0 and not handed_over(m)
    assert m[f"{key}_s"] == pytest.approx(got.t[0])
    said = f"{alone} chosen on the model; policy 0 % of steps"
    assert hand_overs(m, ["policy", "rc", "pid"]) == said
    assert _cell(m).endswith("chosen (policy 0 %)")


def test_a_monitor_tripping_on_the_first_step_is_a_hand_over_not_a_choice():
    # The policy starts (its figure within the ratio) and a hair-trigger monitor hands its
    # loop to rc on the very first step (the leg starts off the reference): the stages are
    # then those of a start at rc, and only the start tells the two apart. The report says
    # hand-over, from the first step's time.
    sc = load_scenario("initial_error")
    spec = SupervisorSpec((Divergence(1e-3, 0.5, None, 0),),
                          (Stage("policy", ("divergence",)), Stage("rc")))
    sup = Supervised(Wobbly(), make_baseline("rc", sc), DT, sc.reference.period, spec)
    assert sup.choose([0.4, 0.39], [3.0, 3.0]) == POLICY
    (tr,) = run_episodes([Job(sc, sup, "MPALegResidual-v0", {}, plant=SLOW, seed=3)], 3)
    assert tr.start == POLICY and np.all(tr.fallback == FALLBACK)
    m = trace_metrics(tr, sc.reference.period)
    assert m["chosen"] is None and handed_over(m) and m["fallback_s"] == pytest.approx(tr.t[0])
    assert hand_overs(m, ["policy", "rc"]) == f"rc from {tr.t[0]:.1f} s; policy 0 % of steps"


@pytest.mark.parametrize("level_mm", [0.3, 2.0, 5.0, 100.0])
def test_a_policy_its_monitors_hand_over_on_the_model_is_predicted_to_fail(level_mm):
    # The supervisor's monitors replayed over the policy's episode alone (first_trips, from
    # the errors the policy observed) hand over at the very step the live supervised loop,
    # started at the policy, does (levels whose trips fall 5-20 steps in, and one that never
    # trips): up to a hand-over that loop is the policy's own, action for action. A policy
    # handed over on the model scores inf on both figures and a fallback predicted finite is
    # chosen; one never handed over scores its own episode's figures.
    sc = load_scenario("nominal")
    spec = SupervisorSpec((Divergence(level_mm, 0.5, None, 0),),
                          (Stage("policy", ("divergence",)), Stage("rc")))
    sup = Supervised(Wobbly(), make_baseline("rc", sc), DT, sc.reference.period, spec)
    ((mm, pct),) = predict([(sup, "MPALegResidual-v0", None)], [sc], [SLOW])
    assert sup.start == POLICY  # predicting chooses nothing
    env = gym.make("MPALegResidual-v0", scenario=model_of(sc))
    alone = run_episode(env, Wobbly(), MODEL_SEED, options={"plant": SLOW})
    watched = run_episode(env, sup, MODEL_SEED, options={"plant": SLOW})
    env.close()
    took = np.flatnonzero(watched.fallback)
    (step,) = sup.first_trips(alone.observed_error[:, None])
    assert step == (took[0] if took.size else -1)
    upto = took[0] if took.size else len(alone.x)
    np.testing.assert_array_equal(watched.x[:upto], alone.x[:upto])
    if took.size:
        assert mm[0] == pct[0] == INF and math.isfinite(mm[1])
        assert sup.choose(mm, pct) == FALLBACK
    else:
        assert level_mm == 100.0  # the others trip (the replay's step is checked above)
        m = trace_metrics(alone, sc.reference.period)
        assert mm[0] == pytest.approx(score_mm(m), rel=1e-12)
        assert pct[0] == pytest.approx(score_stiffness_pct(m), rel=1e-12)


def test_episodes_replayed_together_hand_over_as_each_replayed_alone():
    # _handed_over replays the episodes of supervisors that judge alike as one batch, the
    # shorter ones padded. A 4 mm error that repeats with the reference never trips the
    # limit-cycle monitor; 30 s of it beside 40 s episodes must not trip on the padding
    # (zeros after its end make the one-period change −e). An error at another period trips,
    # alone and in the batch.
    from types import SimpleNamespace

    from mpa_gym.agents.controllers.supervisor import LimitCycle
    from mpa_gym.agents.evaluation.select import _handed_over

    sc = load_scenario("nominal")
    period = sc.reference.period
    spec = SupervisorSpec((LimitCycle(2.0, 3.0, None, 2),),
                          (Stage("policy", ("limit_cycle",)), Stage("rc")))
    sups = [Supervised(Wobbly(), make_baseline("rc", sc), DT, period, spec) for _ in range(3)]
    t = np.arange(4000) * DT
    errors = [4e-3 * np.sin(2 * np.pi * t[:3000] / period),  # 30 s, periodic
              4e-3 * np.sin(2 * np.pi * t / period),  # 40 s, periodic
              4e-3 * np.sin(2 * np.pi * t / (0.57 * period))]  # 40 s, another period
    alone = [sups[0].first_trips(e[:, None])[0] for e in errors]
    assert alone[0] == alone[1] == -1 and 0 < alone[2] < 4000
    traces = [SimpleNamespace(observed_error=e) for e in errors]
    handed = _handed_over({id(s): s for s in sups}, {id(s): [j] for j, s in enumerate(sups)},
                          traces)
    assert handed == {2}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny trained run of the default config (its supervisor chooses its start)."""
    tmp = tmp_path_factory.mktemp("select")
    return train(tiny_config(tmp, n_envs=2, n_timesteps=64, n_steps=32, batch_size=64,
                             n_epochs=1), tmp / "run", progress=False)


def test_the_prediction_is_each_stage_alone_on_the_model_through_the_single_env(run):
    # What choose_starts predicts (one batch of the vector env) is what each stage's
    # controller scores alone on the scenario's model through a single env of its own, the
    # kick the scenario holds left out (position, and the stiffness RMSE recomputed here from
    # the trace's last three periods); the start follows from those figures.
    sc = load_scenario("impulse")
    assert sc.disturbances and model_of(sc).disturbances == ()
    loaded = load_policy(str(run), {"scenario": sc})
    (predicted,) = choose_starts([loaded], [sc], [SLOW])
    sup, _, cfg = loaded
    mm, pct = predicted
    assert sup.start == sup.spec.select.start(mm, pct)
    assert sup.predicted_mm == mm and sup.predicted_stiffness_pct == pct
    alone = load_policy(str(run) + ALONE, {"scenario": sc})[0]
    # the later stages as the supervisor builds them: the run's task settings, its gains
    task = cfg.env_kwargs.get("task")
    controllers = [alone] + [make_baseline(s.controller, sc, None, task,
                                           gains=sup.spec.gains.get(s.controller))
                             for s in sup.spec.stages[1:]]
    # the policy is predicted under its monitors: failing (inf) where they hand it over
    env = gym.make("MPALegResidual-v0", scenario=model_of(sc), task=eval_task(cfg))
    watched = run_episode(env, load_policy(str(run), {"scenario": sc})[0], MODEL_SEED,
                          options={"plant": SLOW})
    env.close()
    if watched.fallback.any():
        assert mm[0] == pct[0] == INF
        controllers, mm, pct = controllers[1:], mm[1:], pct[1:]
    for ctrl, want_mm, want_pct in zip(controllers, mm, pct, strict=True):
        env = gym.make("MPALegResidual-v0", scenario=model_of(sc), task=eval_task(cfg))
        tr = run_episode(env, ctrl, MODEL_SEED, options={"plant": SLOW})
        env.close()
        assert score_mm(trace_metrics(tr, sc.reference.period)) == pytest.approx(
            want_mm, rel=1e-9)
        n = 3 * round(sc.reference.period / DT)  # the last three periods' samples
        ek = (tr.k[-n:] - tr.k_ref[-n:]) / tr.k_ref[-n:]
        assert want_pct == pytest.approx(100 * np.sqrt(np.mean(ek**2)), rel=1e-12)
    # a policy without a supervisor, or whose supervisor does not select, chooses nothing
    assert choose_starts([load_policy(str(run) + ALONE, {"scenario": sc})], [sc], [None]) == [None]
    with pytest.raises(ValueError, match=r"1 policies, 2 scenarios and 1 plants"):
        choose_starts([loaded], [sc, sc], [None])


def test_predicting_many_at_once_is_predicting_each_alone(run):
    # predict runs each stage's controllers of every policy given as one stacked batch: the
    # figures must be those of each policy predicted on its own, on scenarios of other
    # reference periods (rc's delay line is a period long) and plants of their own: the
    # fallbacks' bit for bit, the policy's to float32 rounding (its stack's rows are told
    # their own delays, and torch's product over a batch of rows need not round the last bit
    # as over one row: within 1e-6 relative, or 1e-6 mm at the noise floor)
    import dataclasses

    heldout = load_scenario("heldout_a")
    fast = dataclasses.replace(heldout, name="fast", reference=dataclasses.replace(
        heldout.reference, period=2.0))
    cases = [(load_scenario("impulse"), SLOW), (heldout, None),
             (fast, {"pressure_dead_time_s": 0.02, "extra_mass_kg": 1.5})]
    together = predict([load_policy(str(run), {"scenario": sc}) for sc, _ in cases],
                        [sc for sc, _ in cases], [p for _, p in cases])
    for (sc, plant), figures in zip(cases, together, strict=True):
        (alone,) = predict([load_policy(str(run), {"scenario": sc})], [sc], [plant])
        assert len(figures[0]) == len(figures[1]) == 3, (sc.name, figures)
        assert [f[1:] for f in figures] == [f[1:] for f in alone], (sc.name, figures, alone)
        assert figures[0][0] == pytest.approx(alone[0][0], rel=1e-6, abs=1e-6)
        assert figures[1][0] == pytest.approx(alone[1][0], rel=1e-6)
    assert len({tuple(f[0]) for f in together}) == len(cases)  # three plants, three figures


@REALTIME
def test_a_rollout_chooses_its_start_on_the_scenario_and_says_so(run, tmp_path):
    # The emulator in its own process plays a slow, loaded rig; the rollout is given that
    # rig as its scenario (what identify --out writes), chooses the start on it before the
    # rig is touched, logs the choice and its figures, and every step and the summary agree.
    rig = {"name": "slow_rig", "duration_s": 6.0, "plant": SLOW}
    log = tmp_path / "r.jsonl"
    with EmulatorProcess(rig) as emu:
        out = rollout(str(run), emu.url, log, scenario=rig, episode_s=6.0)
    stages = out["stages"]
    assert list(out["predicted_mm"]) == stages == ["policy", "rc", "pid"]
    assert list(out["predicted_stiffness_pct"]) == stages
    start = SupervisorSpec().select.start(*([INF if v is None else v for v in f.values()]
                                            for f in (out["predicted_mm"],
                                                      out["predicted_stiffness_pct"])))
    (event,) = [r for r in read_log(log) if r.get("event") == "chosen"]
    assert event["start"] == stages[start] and event["predicted_mm"] == out["predicted_mm"]
    assert event["predicted_stiffness_pct"] == out["predicted_stiffness_pct"]
    steps = [r for r in read_log(log) if "reward" in r]
    assert steps[0]["fallback"] == start
    ep = out["episodes"][0]
    assert ep["chosen"] == (None if start == POLICY else
                            "fallback" if start == FALLBACK else "last_resort")
    text = show_rollout(out)
    assert "predicted on the model (scenario 'slow_rig''s plant)" in text
    assert ("chosen on the model" in text) == (start != POLICY)


def test_reports_keep_a_start_chosen_on_the_model_apart_from_a_hand_over(run):
    # Each sweep cell and random rig gets a supervised policy of its own whose start is
    # chosen on that plant: a cell says which stage was chosen exactly where choose_starts,
    # run again on a fresh load for that plant, chooses a later stage; the grid's and the
    # audit's counts keep the choices apart from the monitors' hand-overs.
    grid = Grid("delay", "pressure_dead_time_s", (0.0, 0.04), "pressure_lag_s", (0.0, 0.06),
                base={"extra_mass_kg": 1.0})
    rob = robustness([str(run)], grids=(grid,), levels={}, kicks={})
    g = rob["grids"]["delay"]
    cells = [c for row in g["controllers"][run.name] for c in row]
    sc = _scenario(load_scenario("nominal"), "delay", {})
    for cell, plant in zip(cells, grid.cells(), strict=True):
        fresh = load_policy(str(run), {"scenario": sc})
        choose_starts([fresh], [sc], [plant])
        assert cell["chosen"] == (None if fresh[0].start == POLICY else
                                  "fallback" if fresh[0].start == FALLBACK else "last_resort")
        assert (cell["policy_share"] == 0.0) if cell["chosen"] else True
    assert g["chosen"][run.name] == sum(c["chosen"] is not None for c in cells)
    assert g["hand_overs"][run.name] == sum(map(handed_over, cells))
    rr = random_rigs([str(run)], 6)
    audit = rr["audit"][run.name]
    rows = {r["rig"]: r["controllers"][run.name] for r in rr["rigs"]}
    assert audit["chosen"] == [i for i, m in rows.items() if m["chosen"] is not None]
    assert audit["hand_overs"] == [i for i, m in rows.items() if handed_over(m)]
    assert not set(audit["chosen"]) & set(audit["hand_overs"])


def test_the_sweep_starts_each_cell_where_its_figures_say(run, monkeypatch):
    # Figures forced in place of the model's: the cells start at the stages they say, each
    # told its own delays, as the rows of one stacked supervised object (one call per step),
    # and the sweep's cells report who was chosen.
    slow = [{**SLOW, "extra_mass_kg": m} for m in (0.0, 0.5, 1.0)]
    quick = [{"pressure_dead_time_s": 0.0, "pressure_lag_s": 0.0, "extra_mass_kg": m}
             for m in (0.0, 0.5)]
    plants = [slow[0], slow[1], quick[0], quick[1], slow[2]]
    forced = [[0.1, 0.2, 0.3], [INF, 0.2, 0.3], [0.5, 0.4, 0.1], [0.5, 0.1, 0.4],
              [0.2, 0.3, 0.3]]
    monkeypatch.setattr(robustness_module, "predict",
                        lambda loaded, scenarios, plants: [(list(f), [5.0] * 3) for f in forced])
    sc = _scenario(load_scenario("nominal"), "cells", {})
    jobs = plant_jobs(str(run), sc, plants, 5)
    (one,) = {id(j.policy): j.policy for j in jobs}.values()
    assert list(one.start) == [POLICY, FALLBACK, LAST_RESORT, FALLBACK, POLICY]
    assert [tuple(d) for d in one.policy.frontend.known_delay_s] == [
        (0.03, 0.04), (0.03, 0.04), (0.0, 0.0), (0.0, 0.0), (0.03, 0.04)]
    (batch,) = run_batches([str(run)], sc, plants, 5)
    cells = cell_metrics(batch, sc.reference.period, DT)
    assert [c["chosen"] for c in cells] == [None, "fallback", "last_resort", "fallback", None]
    assert [c["policy_share"] for c in cells[1:4]] == [0.0, 0.0, 0.0]
    assert not any(handed_over(c) for c in cells[1:4])


@REALTIME
def test_a_rollout_started_at_its_fallback_says_so_at_every_step(run, tmp_path, monkeypatch):
    # The model's figures forced (the policy unstable on it): on an emulator in its own
    # process playing a slow, loaded rig, rc drives every step from its rest state, the log
    # says so before the first step, and the summary never calls it a hand-over.
    monkeypatch.setattr(rollout_module, "choose_starts",
                        lambda loaded, scenarios, plants: [([INF, 0.3, 0.5], [INF, 9.0, 9.0])])
    rig = {"name": "slow_rig", "duration_s": 4.0, "plant": SLOW}
    log = tmp_path / "r.jsonl"
    with EmulatorProcess(rig) as emu:
        out = rollout(str(run), emu.url, log, scenario=rig, episode_s=4.0)
    assert out["predicted_mm"] == {"policy": None, "rc": 0.3, "pid": 0.5}
    assert out["predicted_stiffness_pct"] == {"policy": None, "rc": 9.0, "pid": 9.0}
    records = read_log(log)
    (event,) = [r for r in records if r.get("event") == "chosen"]
    assert event["start"] == "rc" and event["predicted_mm"] == out["predicted_mm"]
    assert not [r for r in records if r.get("event") in ("fallback", "last_resort")]
    assert {r["fallback"] for r in records if "reward" in r} == {FALLBACK}
    ep = out["episodes"][0]
    assert ep["chosen"] == "fallback" and ep["policy_share"] == 0.0
    assert ep["hand_overs"] == "rc chosen on the model; policy 0 % of steps"
    text = show_rollout(out)
    assert ("position RMSE [mm] / stiffness RMSE [%]: policy unstable, rc 0.300 / 9.00, "
            "pid 0.500 / 9.00") in text
    assert "hand-over: rc chosen on the model" in text
