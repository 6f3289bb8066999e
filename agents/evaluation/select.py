"""The supervisor's start, chosen on the model (``SupervisorSpec.select``,
``mpa_gym.agents.controllers.supervisor.Selection``).

A supervisor whose monitors fire only on instability keeps a policy that tracks stably but
worse than its fallback would (a light leg with a long regulator lag, where rc tracks 1.2-2x
better), and hands over too late where the policy is unstable from the start (a fallback
handed an oscillating loop in the middle of an episode still settles when the report scores
it). What the fallback is expected to do is known before the episode, on the model: each
stage's controller alone runs one episode on the scenario with the plant the supervised
policy was loaded for (a report's scenario, a sweep cell, a random rig; on a rig, the
scenario ``mpa-gym identify --out`` wrote, whose plant is the estimate), without the
scenario's disturbances (the model does not know the kicks to come) and its randomisation,
its sensor noise drawn from ``MODEL_SEED`` (no report's episode seed). Each is scored as the
sweep scores a cell (``cell_metrics``: position RMSE over the last three reference periods; an
unstable or terminated loop is infinitely bad) and ``Supervised.choose`` sets the stage every
episode starts at. The episodes of every policy given run as one batch.

What was chosen is never hidden: each report row says ``chosen`` (``who_drove``) and its
``policy_share``, and a run's ``predicted_mm`` are kept on the policy object.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from mpa_gym.agents.controllers.baselines import stacked
from mpa_gym.agents.controllers.supervisor import Supervised
from mpa_gym.agents.evaluation.episodes import Job, eval_task, run_episodes, score_mm, trace_metrics
from mpa_gym.agents.learned.config import EVAL_SEED
from mpa_gym.analysis.scenario import Randomization, Scenario, load_scenario

MODEL_SEED = 4 * EVAL_SEED  # the model episodes' noise: beyond training, evaluation and rigs


def model_of(scenario: Any) -> Scenario:
    """The model a start is chosen on: ``scenario`` without its disturbances and its
    randomisation (its plant, noise and reference kept)."""
    sc = load_scenario(scenario)
    return dataclasses.replace(sc, name=f"{sc.name} (model)", disturbances=(),
                               randomize=Randomization())


def predict(loaded: list[tuple[Any, str, Any]], scenarios: list[Any],
            plants: list[dict[str, Any] | None]) -> list[list[float] | None]:
    """For each ``loaded[i]`` (``load_policy``'s (policy, env id, run config)) to run on
    ``scenarios[i]`` with ``plants[i]``'s fields: if it is a supervised policy whose spec
    selects (``spec.select``), each of its stages' controller alone on the model of that
    scenario and plant, scored [mm] (inf: unstable or terminated), in cascade order; None for
    any other policy. A policy object given for several plants (one told the delays they
    share) runs them as rows of one batch, as its controllers do."""
    if not len(loaded) == len(scenarios) == len(plants):
        raise ValueError(f"{len(loaded)} policies, {len(scenarios)} scenarios and "
                         f"{len(plants)} plants: one of each per policy")
    models: dict[int, Scenario] = {}  # id(scenario) -> its model (one env per scenario)
    jobs, owners, period = [], [], {}
    later: dict[int, list[int]] = {}  # a later stage -> its jobs, in the order of ``loaded``
    for i, ((policy, env_id, cfg), sc, plant) in enumerate(zip(loaded, scenarios, plants,
                                                              strict=True)):
        if not isinstance(policy, Supervised) or policy.spec.select is None:
            continue
        if id(sc) not in models:
            models[id(sc)] = model_of(sc)
        model = models[id(sc)]
        period[i] = model.reference.period
        task = eval_task(cfg)
        for s, (ctrl, eid) in enumerate([(policy.policy, env_id)] + [
                (c, "MPALegResidual-v0") for c in policy.controllers]):
            if s:
                later.setdefault(s, []).append(len(jobs))
            jobs.append(Job(model, ctrl, eid, task, plant=plant, seed=MODEL_SEED))
            owners.append(i)
    # each later stage's controllers as one batch where they stack (one kind, gains and task
    # config; each row its own plan, with the numbers its own controller gives): one call per
    # step for the fallbacks of every scenario, cell or rig, not one per policy loaded
    for idx in later.values():
        if (one := stacked([jobs[j].policy for j in idx])) is not None:
            for j in idx:
                jobs[j] = dataclasses.replace(jobs[j], policy=one)
    out: list[list[float] | None] = [None] * len(loaded)
    if jobs:
        for i, tr in zip(owners, run_episodes(jobs, MODEL_SEED), strict=True):
            out[i] = (out[i] or []) + [score_mm(trace_metrics(tr, period[i]))]
    return out


def choose_starts(loaded: list[tuple[Any, str, Any]], scenarios: list[Any],
                  plants: list[dict[str, Any] | None]) -> list[list[float] | None]:
    """:func:`predict`, and each supervised policy that selects starts where its figures say
    (``Supervised.choose``); returns the figures. Each policy object must be given once (one
    loaded for each scenario and plant: its start is its own)."""
    if len({id(p) for p, _, _ in loaded}) != len(loaded):
        raise ValueError("choose_starts: a policy object given twice; load one for each "
                         "scenario and plant (its start is its own)")
    predicted = predict(loaded, scenarios, plants)
    for (policy, _, _), figures in zip(loaded, predicted, strict=True):
        if figures is not None:
            policy.choose(figures)
    return predicted
