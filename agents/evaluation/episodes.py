"""The episode runner and the metric window: one for evaluation reports, the robustness sweep,
held-out evaluations during training, baseline tuning and single episodes.

:func:`run_episodes` runs a list of :class:`Job` s (a controller on a scenario, with an optional
plant of its own and an episode seed) at once. Jobs of one (scenario, env id, task) share a
native vector env, one row each, every row reset with its job's seed (so row i is the single
env reset with that seed) and, where a job has a plant, with it (``reset(options={"plant":
[dict per row]})``). All the vector envs step together, and each controller object is called
once per step with the observations of all its rows (a learned policy evaluated on every
scenario of a report is one batched forward pass per step). A row is recorded until its episode
ends; its autoreset is ignored. :func:`run_episode` runs one episode of a given single env
through the same loop (the env as a batch of one row), so a single episode and a batch row are
the same code path, and the check that they agree tests the vector env against the single one.

Metrics are taken over the last three reference periods of an episode
(``mpa_gym.analysis.simulate.metric_window``, the window of every report).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from mpa_gym.agents.controllers.baselines import Policy, stacked
from mpa_gym.agents.controllers.supervisor import took_over, who_drove
from mpa_gym.analysis.simulate import METRIC_PERIODS, metric_window, whole_periods
from mpa_gym.task.contract import OBS_X, OBS_XREF, SAFETY_CLIPPED

RECOVERY_BAND_M = 1e-3  # [m] recovered: |X − X̂| stays below this
# [mm] a loop is unstable when the RMS of its error less the error's mean period over the
# metric window passes this (5 % of the reference's 20 mm amplitude; cell_metrics)
UNSTABLE_APERIODIC_MM = 1.0
# the per-step info fields a Trace keeps: Trace field -> info key
_RECORDED = {"t": "t_s", "x": "x_m", "x_ref": "x_ref_m", "k": "k_N_per_m",
             "k_ref": "k_ref_N_per_m", "pressure_bar": "pressure_bar",
             "pressure_cmd_bar": "pressure_cmd_bar", "safety": "safety"}


def eval_task(run_cfg: Any = None) -> dict[str, Any]:
    """The task settings a controller is evaluated with: a learned policy's own (control
    period, limits, residual scale) if it has a run config; the scenario's duration rules."""
    task = (run_cfg.env_kwargs.get("task") if run_cfg is not None else None) or {}
    return {k: v for k, v in task.items() if k != "episode_s"}


def recovery_s(t: np.ndarray, err: np.ndarray, t_end: float, band_m: float = RECOVERY_BAND_M
               ) -> float:
    """[s] after ``t_end`` (a disturbance's end), until |``err``| stays below ``band_m``
    (inf: it never does)."""
    after = t >= t_end - 1e-9
    outside = np.flatnonzero(np.abs(err[after]) >= band_m)
    if outside.size == 0:
        return 0.0
    if outside[-1] == after.sum() - 1:
        return math.inf
    return float(t[after][outside[-1] + 1] - t_end)


@dataclass
class Trace:
    """One episode, per step (after each step)."""

    t: np.ndarray  # [s]
    x: np.ndarray  # [m]
    x_ref: np.ndarray  # [m]
    k: np.ndarray  # [N/m]
    k_ref: np.ndarray  # [N/m]
    pressure_bar: np.ndarray  # (n, 2)
    pressure_cmd_bar: np.ndarray  # (n, 2)
    clipped: np.ndarray  # bool
    rewards: np.ndarray
    terminated: bool
    fallback: np.ndarray | None = None  # per step, a supervisor's stage (``took_over``)
    start: int = 0  # the stage a supervisor started at (``Supervised.start``: chosen on a model)
    # [m] per step, the error X̂ − X the controller observed before it (its observation's)
    observed_error: np.ndarray | None = None


@dataclass
class Job:
    """One episode: ``policy`` on ``scenario`` in env ``env_id`` with ``task``; ``plant``: plant
    fields of this episode's own (``reset(options={"plant": ...})``); ``seed``: its episode
    seed (None: the batch's)."""

    scenario: Any  # a loaded Scenario
    policy: Policy
    env_id: str
    task: dict[str, Any]
    plant: dict[str, Any] | None = None
    seed: int | None = None


class _OneRow:
    """A single env as a vector env of one row (the runner's view of :func:`run_episode`)."""

    def __init__(self, env: gym.Env, options: dict[str, Any] | None) -> None:
        self.env, self.options = env, options

    def reset(self, seed: list[int], options: Any = None) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed[0], options=self.options)
        return obs[None], info

    def step(self, actions: np.ndarray) -> tuple[Any, ...]:
        obs, r, term, trunc, info = self.env.step(actions[0])
        return (obs[None], np.array([r]), np.array([term]), np.array([trunc]),
                {k: np.asarray([v]) for k, v in info.items()})

    def close(self) -> None:
        """The caller's env stays open."""


def stack_jobs(jobs: list[Job], groups: list[list[int]]) -> list[Job]:
    """``jobs`` with the controllers of each group of job indices (disjoint groups) replaced by
    their stack (``baselines.stack``), where they stack and are more than one object: one call
    per step for the group, row i its i-th job's controller in job order (its plan, delays
    told, start), the order in which :func:`run_episodes` gives a controller its rows."""
    seen: set[int] = set()
    for idx in groups:
        if seen & set(idx):
            raise ValueError(f"stack_jobs: job(s) {sorted(seen & set(idx))} in two groups")
        seen |= set(idx)
    out = list(jobs)
    for idx in map(sorted, groups):
        if len({id(jobs[j].policy) for j in idx}) < 2:
            continue
        if (one := stacked([jobs[j].policy for j in idx])) is not None:
            for j in idx:
                out[j] = dataclasses.replace(jobs[j], policy=one)
    return out


def run_episodes(jobs: list[Job], seed: int) -> list[Trace]:
    """Every job's episode at once (module docstring); ``seed`` for jobs without their own."""
    groups: dict[tuple[int, str, str], list[int]] = {}
    for i, j in enumerate(jobs):
        key = (id(j.scenario), j.env_id, json.dumps(j.task, sort_keys=True, default=str))
        groups.setdefault(key, []).append(i)
    envs = []
    for (_, env_id, _), idx in groups.items():
        j0 = jobs[idx[0]]
        envs.append(gym.make_vec(env_id, num_envs=len(idx), vectorization_mode="vector_entry_point",
                                 scenario=j0.scenario, task=j0.task))
    return _run(jobs, list(groups.values()), envs, seed)


def run_episode(env: gym.Env, policy: Policy, seed: int, options: dict[str, Any] | None = None
                ) -> Trace:
    """One episode of ``policy`` on the single env ``env`` (deterministic actions), through
    :func:`run_episodes`' loop."""
    job = Job(None, policy, "", {})
    return _run([job], [[0]], [_OneRow(env, options)], seed)[0]


def _run(jobs: list[Job], rows_of: list[list[int]], envs: list[Any], seed: int) -> list[Trace]:
    """The loop: ``envs[g]`` runs the jobs ``rows_of[g]``, one row each."""
    obs_of: list[np.ndarray] = []
    try:
        for venv, idx in zip(envs, rows_of, strict=True):
            plants = [jobs[i].plant for i in idx]
            options = ({"plant": [p or {} for p in plants]}
                       if any(p is not None for p in plants) else None)
            obs, _ = venv.reset(seed=[seed if jobs[i].seed is None else jobs[i].seed
                                      for i in idx], options=options)
            obs_of.append(obs)
        # where each job sits: (group, row); each policy object's jobs, in a fixed order
        where = {i: (g, r) for g, idx in enumerate(rows_of) for r, i in enumerate(idx)}
        by_policy: dict[int, list[int]] = {}
        for i, j in enumerate(jobs):
            by_policy.setdefault(id(j.policy), []).append(i)
        # each job's row in its policy's batch: a stack's row i is its i-th controller's
        row_of = {i: k for idx in by_policy.values() for k, i in enumerate(idx)}
        states: dict[int, Any] = dict.fromkeys(by_policy)
        n = len(jobs)
        actions = [np.zeros((len(idx), 2), dtype=np.float32) for idx in rows_of]
        live = np.ones(n, dtype=bool)
        length = np.zeros(n, dtype=np.int64)  # steps recorded per job
        terminated = np.zeros(n, dtype=bool)
        stage = np.zeros(n, dtype=np.int8)
        steps: list[list[dict[str, np.ndarray]]] = [[] for _ in envs]  # per group, per step
        rewards: list[list[np.ndarray]] = [[] for _ in envs]
        stages: list[np.ndarray] = []  # per step, every job's supervisor stage
        observed: list[list[np.ndarray]] = [[] for _ in envs]  # per group, per step: X̂ − X
        supervised = np.zeros(n, dtype=bool)
        first = True
        while live.any():
            for g, obs in enumerate(obs_of):
                o = np.asarray(obs, dtype=np.float64)  # as Supervised.predict takes it
                observed[g].append(o[:, OBS_XREF] - o[:, OBS_X])
            for pid, idx in by_policy.items():
                batch = np.stack([obs_of[where[i][0]][where[i][1]] for i in idx])
                start = np.full(len(idx), first)
                policy = jobs[idx[0]].policy
                a, states[pid] = policy.predict(batch, states[pid], start, deterministic=True)
                flags = took_over(policy, states[pid])
                for k, i in enumerate(idx):
                    g, r = where[i]
                    actions[g][r] = a[k]
                if flags is not None:
                    stage[idx] = flags
                    supervised[idx] = True
            stages.append(stage.copy())
            first = False
            for g, venv in enumerate(envs):
                obs, rew, term, trunc, info = venv.step(actions[g])
                obs_of[g] = obs
                done = term | trunc
                rec = {k: np.array(info[key]) for k, key in _RECORDED.items()}
                if "final_info" in info:  # a same-step autoreset: the finished step is there
                    f = info["_final_info"]
                    for k, key in _RECORDED.items():
                        rec[k][f] = info["final_info"][key][f]
                steps[g].append(rec)
                rewards[g].append(np.asarray(rew))
                idx = np.asarray(rows_of[g])
                on = live[idx]
                length[idx[on]] += 1
                ended = on & done
                terminated[idx[ended]] = term[ended]
                live[idx[ended]] = False
    finally:
        for venv in envs:
            venv.close()
    out: list[Trace] = [None] * len(jobs)  # type: ignore[list-item]
    all_stages = np.stack(stages)
    for g, idx in enumerate(rows_of):
        cols = {k: np.stack([s[k] for s in steps[g]]) for k in _RECORDED}
        rew = np.stack(rewards[g])
        seen = np.stack(observed[g])
        for r, i in enumerate(idx):
            m = length[i]
            c = {k: v[:m, r] for k, v in cols.items()}
            out[i] = Trace(c["t"].astype(float), c["x"].astype(float), c["x_ref"].astype(float),
                           c["k"].astype(float), c["k_ref"].astype(float), c["pressure_bar"],
                           c["pressure_cmd_bar"], (c["safety"] & SAFETY_CLIPPED) > 0,
                           rew[:m, r], bool(terminated[i]),
                           all_stages[:m, i].astype(np.int64) if supervised[i] else None,
                           _start(jobs[i].policy, row_of[i]) if supervised[i] else 0,
                           seen[:m, r].astype(float))
    return out


def _start(policy: Any, row: int) -> int:
    """The stage a supervised ``policy`` started row ``row`` of its batch at (a stack's start
    is each row's)."""
    start = getattr(policy, "start", 0)
    return int(start[row] if np.ndim(start) else start)


def cell_metrics(run: dict[str, np.ndarray], period_s: float, dt: float) -> list[dict[str, Any]]:
    """The robustness sweep's metrics (``mpa_gym.agents.evaluation.robustness``' docstring) for
    each leg of ``run_batch``'s output: position and aperiodic RMSE over the last three
    reference periods, ``unstable``, ``terminated`` and who drove; where ``run`` has the
    stiffness and its reference (``k``, ``k_ref``), the stiffness RMSE [%] over that window
    (``stiffness_rmse_pct``, as :func:`metrics`)."""
    per = round(period_s / dt)
    e = run["x"] - run["x_ref"]
    out = []
    for i in range(e.shape[1]):
        n = int(run["steps"][i]) if "steps" in run else len(run["t"])  # the leg's own steps
        took = who_drove(run["t"][:n], run["fallback"][:n, i] if "fallback" in run else None,
                         int(run["start"][i]) if "start" in run else 0)
        stiffness = {"stiffness_rmse_pct": None} if "k" in run else {}
        if run["terminated"][i] or e.shape[0] < METRIC_PERIODS * per:
            out.append({"position_rmse_mm": None, "aperiodic_rmse_mm": None, "unstable": True,
                        "terminated": bool(run["terminated"][i]), **stiffness, **took})
            continue
        window = whole_periods(run["t"], period_s)
        w = e[window, i].reshape(METRIC_PERIODS, per)
        rem = w - w.mean(axis=0)
        ap = float(np.sqrt(np.mean(rem**2)) * 1e3)
        if stiffness:
            stiffness["stiffness_rmse_pct"] = stiffness_rmse_pct(run["k"][window, i],
                                                                 run["k_ref"][window, i])
        out.append({"position_rmse_mm": float(np.sqrt(np.mean(w**2)) * 1e3),
                    "aperiodic_rmse_mm": ap, "unstable": ap > UNSTABLE_APERIODIC_MM,
                    "terminated": False, **stiffness, **took})
    return out


def stiffness_rmse_pct(k: np.ndarray, k_ref: np.ndarray) -> float:
    """[%] the RMS of the relative stiffness error (k − k̂)/k̂ over the samples given."""
    return float(np.sqrt(np.mean(((k - k_ref) / k_ref) ** 2)) * 100)


def trace_metrics(tr: Trace, period_s: float) -> dict[str, Any]:
    """:func:`cell_metrics` of one episode's trace."""
    run = {"t": tr.t, "x": tr.x[:, None], "x_ref": tr.x_ref[:, None],
           "k": tr.k[:, None], "k_ref": tr.k_ref[:, None],
           "terminated": np.array([tr.terminated]), "steps": np.array([len(tr.t)]),
           "fallback": (np.zeros((len(tr.t), 1), dtype=np.int8) if tr.fallback is None
                        else tr.fallback[:, None]), "start": np.array([tr.start])}
    return cell_metrics(run, period_s, float(tr.t[0]))[0]


def score_mm(m: dict[str, Any]) -> float:
    """[mm] a cell's position RMSE; inf where the loop was unstable or terminated."""
    return _score(m, "position_rmse_mm")


def score_stiffness_pct(m: dict[str, Any]) -> float:
    """[%] a cell's stiffness RMSE (:func:`trace_metrics`); inf where the loop was unstable or
    terminated (it tracks no stiffness then)."""
    return _score(m, "stiffness_rmse_pct")


def _score(m: dict[str, Any], key: str) -> float:
    v = m.get(key)
    return math.inf if m.get("unstable") or m.get("terminated") or v is None else float(v)


def metrics(trace: Trace, period_s: float, impulse_end_s: float | None) -> dict[str, Any]:
    """An episode's figures (``mpa_gym.agents.evaluation.evaluate``'s module docstring)."""
    w = metric_window(trace.t, period_s)
    e = trace.x - trace.x_ref
    return {
        "position_rmse_mm": float(np.sqrt(np.mean(e[w] ** 2)) * 1e3),
        "position_max_mm": float(np.max(np.abs(e[w])) * 1e3),
        "stiffness_rmse_pct": stiffness_rmse_pct(trace.k[w], trace.k_ref[w]),
        "saturation_pct": float(np.mean(trace.clipped) * 100),
        "recovery_s": None if impulse_end_s is None else recovery_s(trace.t, e, impulse_end_s),
        "return": float(trace.rewards.sum()),
        "terminated": trace.terminated,
        **who_drove(trace.t, trace.fallback, trace.start),
    }
