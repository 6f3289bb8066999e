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
its sensor noise drawn from ``MODEL_SEED`` (no report's episode seed). The supervisor's
monitors are replayed over the policy's episode: a policy they would hand over on the model
counts as failing there, since starting at its fallback beats a hand-over late in the
episode. Each is scored as the sweep scores a cell (``cell_metrics``: position and stiffness
RMSE over the last three reference periods; an unstable or terminated loop, or a policy
handed over, is infinitely bad on both) and ``Supervised.choose`` sets the stage every
episode starts at. The episodes of every policy given run as one batch.

What was chosen is never hidden: each report row says ``chosen`` (``who_drove``) and its
``policy_share``, and a run's ``predicted_mm`` and ``predicted_stiffness_pct`` are kept on the
policy object.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from mpa_gym.agents.controllers.supervisor import Supervised
from mpa_gym.agents.evaluation.episodes import (
    Job,
    eval_task,
    run_episodes,
    score_mm,
    score_stiffness_pct,
    stack_jobs,
    trace_metrics,
)
from mpa_gym.agents.learned.config import EVAL_SEED
from mpa_gym.analysis.scenario import Randomization, Scenario, load_scenario

MODEL_SEED = 4 * EVAL_SEED  # the model episodes' noise: beyond training, evaluation and rigs
# each stage's predicted (position RMSE [mm], stiffness RMSE [%]), in cascade order
Figures = tuple[list[float], list[float]]


def model_of(scenario: Any) -> Scenario:
    """The model a start is chosen on: ``scenario`` without its disturbances and its
    randomisation (its plant, noise and reference kept)."""
    sc = load_scenario(scenario)
    return dataclasses.replace(sc, name=f"{sc.name} (model)", disturbances=(),
                               randomize=Randomization())


def predict(loaded: list[tuple[Any, str, Any]], scenarios: list[Any],
            plants: list[dict[str, Any] | None]) -> list[Figures | None]:
    """For each ``loaded[i]`` (``load_policy``'s (policy, env id, run config)) to run on
    ``scenarios[i]`` with ``plants[i]``'s fields: if it is a supervised policy whose spec
    selects (``spec.select``), each of its stages' controller alone on the model of that
    scenario and plant, scored (``Figures``: position [mm] and stiffness [%], inf where
    unstable or terminated), in cascade order; the policy scores inf where its monitors,
    replayed over its episode (``Supervised.first_trips``), would hand it over; None for any
    other policy. A policy object given for several plants (one told the delays they share)
    runs them as rows of one batch, as its controllers do."""
    if not len(loaded) == len(scenarios) == len(plants):
        raise ValueError(f"{len(loaded)} policies, {len(scenarios)} scenarios and "
                         f"{len(plants)} plants: one of each per policy")
    models: dict[int, Scenario] = {}  # id(scenario) -> its model (one env per scenario)
    jobs, owners, period = [], [], {}
    later: dict[int, list[int]] = {}  # a later stage -> its jobs, in the order of ``loaded``
    alone: dict[int, list[int]] = {}  # id(supervised policy) -> its policy-alone jobs
    models_of: dict[int, list[int]] = {}  # id(a policy's network) -> its policy-alone jobs
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
            else:
                alone.setdefault(id(policy), []).append(len(jobs))
                models_of.setdefault(id(getattr(ctrl, "model", ctrl)), []).append(len(jobs))
            jobs.append(Job(model, ctrl, eid, task, plant=plant, seed=MODEL_SEED))
            owners.append(i)
    # each stage's controllers as one batch where they stack (one kind, gains and task config;
    # each row its own plan or delays told, with the numbers its own controller gives): one
    # call per step for each run's policies (one network), and for the fallbacks, of every
    # scenario, cell or rig, not one per policy loaded
    jobs = stack_jobs(jobs, [*models_of.values(), *later.values()])
    out: list[Figures | None] = [None] * len(loaded)
    if not jobs:
        return out
    traces = run_episodes(jobs, MODEL_SEED)
    handed = _handed_over({id(p): p for p, _, _ in loaded}, alone, traces)
    for j, (i, tr) in enumerate(zip(owners, traces, strict=True)):
        m = trace_metrics(tr, period[i])
        if j in handed:  # the policy, which its monitors would hand over on the model
            m = {"position_rmse_mm": math.inf, "stiffness_rmse_pct": math.inf}
        mm, pct = out[i] or ([], [])
        out[i] = ([*mm, score_mm(m)], [*pct, score_stiffness_pct(m)])
    return out


def _handed_over(supervisors: dict[int, Supervised], alone: dict[int, list[int]],
                 traces: list[Any]) -> set[int]:
    """The jobs of the policy alone (``alone``: per supervised policy, by id) whose
    supervisor, started at the policy, would hand over in that episode: its monitors replayed
    over the errors the policy observed (``Supervised.first_trips``), the episodes of the
    supervisors that judge alike (spec, period and step equal) at once."""
    groups: list[tuple[Supervised, list[int]]] = []
    for key, js in alone.items():
        sup = supervisors[key]
        same = [g for g in groups if (g[0].spec, g[0].n_period, g[0].dt) ==
                (sup.spec, sup.n_period, sup.dt)]
        if same:
            same[0][1].extend(js)
        else:
            groups.append((sup, list(js)))
    out: set[int] = set()
    for sup, js in groups:
        seen = [traces[j].observed_error for j in js]
        errors = np.zeros((max(map(len, seen)), len(js)))  # a shorter one: 0 after its end,
        for c, e in enumerate(seen):
            errors[:len(e), c] = e
        # where its trips do not count (zeros are no neutral signal to the limit-cycle monitor)
        out |= {j for j, e, step in zip(js, seen, sup.first_trips(errors), strict=True)
                if 0 <= step < len(e)}
    return out


def choose_starts(loaded: list[tuple[Any, str, Any]], scenarios: list[Any],
                  plants: list[dict[str, Any] | None]) -> list[Figures | None]:
    """:func:`predict`, and each supervised policy that selects starts where its figures say
    (``Supervised.choose``); returns the figures. Each policy object must be given once (one
    loaded for each scenario and plant: its start is its own)."""
    if len({id(p) for p, _, _ in loaded}) != len(loaded):
        raise ValueError("choose_starts: a policy object given twice; load one for each "
                         "scenario and plant (its start is its own)")
    predicted = predict(loaded, scenarios, plants)
    for (policy, _, _), figures in zip(loaded, predicted, strict=True):
        if figures is not None:
            policy.choose(*figures)
    return predicted
