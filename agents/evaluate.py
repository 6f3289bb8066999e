"""Evaluation harness: every controller on the paper's scenarios and on held-out plants, one
report (JSON + Markdown + PNG plots).

Metrics per (scenario, controller), over the last three reference periods of the episode (the
window `mpa-gym simulate` uses) unless said otherwise:

- ``position_rmse_mm``, ``position_max_mm``: X − X̂;
- ``stiffness_rmse_pct``: (k − k̂)/k̂, k the plant's true Eq. (23) stiffness at the applied
  pressures;
- ``saturation_pct``: share of all steps whose command the safety layer clipped to [0, p_max];
- ``recovery_s``: after the first impulse ends, the time until |X − X̂| stays below 1 mm
  (``None`` without an impulse, ``inf`` if it never does);
- ``return``: the episode's summed reward; ``terminated``: whether the leg left its bounds;
- ``fallback_s``: for a run under a ``supervisor`` (``agents.supervisor``), the time its
  fallback took over (``None``: it never did, or the controller has no supervisor);
  ``last_resort_s`` the time its last resort did.

With ``robustness=True`` the report also holds the robustness sweep of ``agents.robustness``
(grids of real-rig effects, easy / medium / hard levels) with its heatmaps. On a machine with a
second core the sweep runs in a second process while the report's batch runs in this one (both
are single-threaded and independent; the numbers are the same either way).
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import mpa_gym  # noqa: F401
from agents.baselines import BASELINES, Policy, stack
from agents.config import EVAL_SEED
from agents.policies import load_policy
from agents.seeds import group_runs, require_stats
from agents.supervisor import take_over_times, took_over
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.files import atomic_write_text
from mpa_gym.task.contract import SAFETY_CLIPPED

PAPER_SCENARIOS = ["nominal", "initial_error", "impulse", "gamma_mismatch", "mass_mismatch",
                   "load_1kg", "kmax", "kmin"]
HELDOUT_SCENARIOS = ["heldout_a", "heldout_b", "heldout_c", "heldout_bladder"]
RECOVERY_BAND_M = 1e-3


@dataclass
class Trace:
    """One evaluated episode, per step (after each step)."""

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


def run_episode(env: gym.Env, policy: Policy, seed: int, options: dict[str, Any] | None = None
                ) -> Trace:
    """Roll ``policy`` out for one episode of ``env`` (deterministic actions)."""
    obs, info = env.reset(seed=seed, options=options)
    state, start = None, np.array([True])
    rows: list[tuple[Any, ...]] = []
    rewards = []
    fallback: list[int] = []
    terminated = False
    while True:
        action, state = policy.predict(obs, state, start, deterministic=True)
        if (flags := took_over(policy, state)) is not None:
            fallback.append(int(flags[0]))
        start = np.array([False])
        obs, r, terminated, truncated, info = env.step(action)
        rows.append((info["t_s"], info["x_m"], info["x_ref_m"], info["k_N_per_m"],
                     info["k_ref_N_per_m"], info["pressure_bar"].copy(),
                     info["pressure_cmd_bar"].copy(), bool(info["safety"] & SAFETY_CLIPPED)))
        rewards.append(r)
        if terminated or truncated:
            break
    cols = list(zip(*rows, strict=True))
    return Trace(np.array(cols[0]), np.array(cols[1]), np.array(cols[2]), np.array(cols[3]),
                 np.array(cols[4]), np.array(cols[5]), np.array(cols[6]), np.array(cols[7]),
                 np.array(rewards), bool(terminated), np.array(fallback) if fallback else None)


@dataclass
class Job:
    """One evaluation episode: ``policy`` on ``scenario`` in env ``env_id`` with ``task``."""

    scenario: Any  # a loaded Scenario
    policy: Policy
    env_id: str
    task: dict[str, Any]


def run_batch(jobs: list[Job], seed: int) -> list[Trace]:
    """Every job's episode at once, each exactly as :func:`run_episode` runs it alone.

    Jobs of one (scenario, env, task) share a native vector env, one row each, every row reset
    with the same episode seed (so row i is the single env reset with ``seed``); all the vector
    envs step together, and each policy is called once per step with the observations of all
    its rows (a learned policy evaluated on every scenario of a report is one batched forward
    pass per step). A row is recorded until its episode ends; its autoreset is ignored.
    """
    groups: dict[tuple[int, str, str], list[int]] = {}
    for i, j in enumerate(jobs):
        key = (id(j.scenario), j.env_id, json.dumps(j.task, sort_keys=True, default=str))
        groups.setdefault(key, []).append(i)
    envs, rows_of = [], []  # per group: vector env, job indices
    obs_of: list[np.ndarray] = []
    for (_, env_id, _), idx in groups.items():
        j0 = jobs[idx[0]]
        venv = gym.make_vec(env_id, num_envs=len(idx), vectorization_mode="vector_entry_point",
                            scenario=j0.scenario, task=j0.task)
        obs, _ = venv.reset(seed=[seed] * len(idx))
        envs.append(venv)
        rows_of.append(idx)
        obs_of.append(obs)
    # where each job sits: (group, row); each policy object's jobs, in a fixed order
    where = {i: (g, r) for g, idx in enumerate(rows_of) for r, i in enumerate(idx)}
    by_policy: dict[int, list[int]] = {}
    for i, j in enumerate(jobs):
        by_policy.setdefault(id(j.policy), []).append(i)
    states: dict[int, Any] = dict.fromkeys(by_policy)
    n = len(jobs)
    act_dim = envs[0].single_action_space.shape[0]
    actions = [np.zeros((len(idx), act_dim), dtype=np.float32) for idx in rows_of]
    live = np.ones(n, dtype=bool)
    cols: list[list[Any]] = [[] for _ in range(n)]
    rewards: list[list[float]] = [[] for _ in range(n)]
    fallback: list[list[int]] = [[] for _ in range(n)]
    terminated = np.zeros(n, dtype=bool)
    first = True
    while live.any():
        for pid, idx in by_policy.items():
            batch = np.stack([obs_of[where[i][0]][where[i][1]] for i in idx])
            start = np.full(len(idx), first)
            a, states[pid] = jobs[idx[0]].policy.predict(batch, states[pid], start,
                                                         deterministic=True)
            flags = took_over(jobs[idx[0]].policy, states[pid])
            for k, i in enumerate(idx):
                g, r = where[i]
                actions[g][r] = a[k]
                if flags is not None and live[i]:
                    fallback[i].append(int(flags[k]))
        first = False
        for g, venv in enumerate(envs):
            obs, rew, term, trunc, info = venv.step(actions[g])
            obs_of[g] = obs
            done = term | trunc
            last = info.get("final_info", info)
            for r, i in enumerate(rows_of[g]):
                if not live[i]:
                    continue
                src = last if done[r] else info
                cols[i].append((src["t_s"][r], src["x_m"][r], src["x_ref_m"][r],
                                src["k_N_per_m"][r], src["k_ref_N_per_m"][r],
                                src["pressure_bar"][r].copy(), src["pressure_cmd_bar"][r].copy(),
                                bool(src["safety"][r] & SAFETY_CLIPPED)))
                rewards[i].append(rew[r])
                if done[r]:
                    live[i] = False
                    terminated[i] = bool(term[r])
    for venv in envs:
        venv.close()
    out = []
    for i in range(n):
        c = list(zip(*cols[i], strict=True))
        out.append(Trace(np.array(c[0]), np.array(c[1]), np.array(c[2]), np.array(c[3]),
                         np.array(c[4]), np.array(c[5]), np.array(c[6]), np.array(c[7]),
                         np.array(rewards[i]), bool(terminated[i]),
                         np.array(fallback[i]) if fallback[i] else None))
    return out


def metrics(trace: Trace, period_s: float, impulse_end_s: float | None) -> dict[str, Any]:
    w = trace.t >= trace.t[-1] - 3 * period_s - 1e-9
    e = trace.x - trace.x_ref
    ek = (trace.k - trace.k_ref) / trace.k_ref
    recovery: float | None = None
    if impulse_end_s is not None:
        after = trace.t >= impulse_end_s - 1e-9
        outside = np.flatnonzero(np.abs(e[after]) >= RECOVERY_BAND_M)
        if outside.size == 0:
            recovery = 0.0
        elif outside[-1] == after.sum() - 1:
            recovery = math.inf
        else:
            recovery = float(trace.t[after][outside[-1] + 1] - impulse_end_s)
    return {
        "position_rmse_mm": float(np.sqrt(np.mean(e[w] ** 2)) * 1e3),
        "position_max_mm": float(np.max(np.abs(e[w])) * 1e3),
        "stiffness_rmse_pct": float(np.sqrt(np.mean(ek[w] ** 2)) * 100),
        "saturation_pct": float(np.mean(trace.clipped) * 100),
        "recovery_s": recovery,
        "return": float(trace.rewards.sum()),
        "terminated": trace.terminated,
        **take_over_times(trace.t, trace.fallback),
    }


def eval_task(run_cfg: Any = None) -> dict[str, Any]:
    """The task settings a controller is evaluated with: a learned policy's own (control
    period, limits, residual scale) if it has a run config; the scenario's duration rules."""
    task = (run_cfg.env_kwargs.get("task") if run_cfg is not None else None) or {}
    return {k: v for k, v in task.items() if k != "episode_s"}


def make_env(env_id: str, scenario: Any, run_cfg: Any = None) -> gym.Env:
    """The single env a controller is evaluated in (:func:`eval_task`)."""
    return gym.make(env_id, scenario=scenario, task=eval_task(run_cfg))


def evaluate(policies: list[str], scenarios: list[Any], seed: int = EVAL_SEED,
             robustness: bool = False, batched: bool = True,
             plots_dir: str | Path | None = None) -> dict[str, Any]:
    """Metrics and traces of each controller on each scenario (episode seed ``seed``), and
    the robustness sweep if ``robustness``.

    All episodes run as one batch (:func:`run_batch`); ``batched=False`` runs them one after
    another (:func:`run_episode`), with the same numbers. ``plots_dir``: the scenario plots
    (:func:`plot`) are drawn there while the sweep's worker finishes, rather than by
    :func:`write_report` after it (``report["plots"]``)."""
    loaded = [load_scenario(s) for s in scenarios]  # every input checked before any episode
    groups = group_runs(policies)  # several runs of one config: checked before any episode
    if groups:
        require_stats()
    learned = {spec: load_policy(spec) for spec in policies if spec not in BASELINES}
    # a baseline is built for its scenario's plan; batched, one stack of them per baseline
    own = {spec: [load_policy(spec, {"scenario": sc})[0] for sc in loaded]
           for spec in policies if spec in BASELINES}
    stacked = {spec: stack(ps) for spec, ps in own.items()} if batched else {}
    swept = sweep_in_background(policies, seed=seed) if robustness else None
    try:
        report = _scenario_report(policies, loaded, learned, own, stacked, groups, seed,
                                  batched)
    except BaseException:  # an error or Ctrl-C here: the sweep's worker is not waited for
        if swept:
            swept.cancel()
        raise
    if swept and plots_dir is not None:
        try:
            Path(plots_dir).mkdir(parents=True, exist_ok=True)
            report["plots"] = plot(report, Path(plots_dir))
        except BaseException:
            swept.cancel()
            raise
    if robustness:
        from agents.robustness import robustness as sweep

        report["robustness"] = swept.result() if swept else sweep(policies, seed=seed)
    from agents.robustness import no_harm

    report["no_harm"] = no_harm(report["results"], report.get("robustness"),
                                [_label(p) for p in policies if p not in BASELINES])
    return report


def _scenario_report(policies: list[str], loaded: list[Any], learned: dict[str, Any],
                     own: dict[str, list[Policy]], stacked: dict[str, Policy],
                     groups: list[list[str]], seed: int, batched: bool) -> dict[str, Any]:
    """``evaluate``'s report without the sweep: every controller's episode on every scenario."""
    results: dict[str, dict[str, Any]] = {}
    traces: dict[str, dict[str, Trace]] = {}
    jobs, keys = [], []
    for k, sc in enumerate(loaded):
        for spec in policies:
            if spec in learned:
                policy, env_id, run_cfg = learned[spec]
            else:
                policy, env_id, run_cfg = (stacked.get(spec) or own[spec][k],
                                           "MPALegResidual-v0", None)
            jobs.append(Job(sc, policy, env_id, eval_task(run_cfg)))
            keys.append((sc, _label(spec)))
    if batched:
        trs = run_batch(jobs, seed)
    else:
        trs = []
        for j in jobs:
            env = gym.make(j.env_id, scenario=j.scenario, task=j.task)
            trs.append(run_episode(env, j.policy, seed))
            env.close()
    for (sc, label), tr in zip(keys, trs, strict=True):
        impulses = [d for d in sc.disturbances if d.type == "impulse"]
        end = impulses[0].t_s + impulses[0].duration_s if impulses else None
        results.setdefault(sc.name, {})[label] = metrics(tr, sc.reference.period, end)
        traces.setdefault(sc.name, {})[label] = tr
    return {"results": results, "traces": traces, "seed": seed,
            "learning": learning_speed(policies, results),
            "controllers": {_label(p): tuned_on(p) for p in policies},
            "supervisors": {_label(p): cfg.supervisor.describe()
                            for p, (_, _, cfg) in learned.items() if cfg.supervisor},
            "groups": seed_groups(groups, results)}


class Background:
    """A function call running in a spawned worker process (``agents.worker.Worker``: it ignores
    Ctrl-C, exits with a SIGKILLed parent, and a dead one fails its call rather than hangs)."""

    def __init__(self, what: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        from agents.worker import Worker

        self._worker = Worker()
        self._what, self._fn, self._args, self._kwargs = what, fn, args, kwargs
        self._call = self._worker.submit(fn, *args, **kwargs)

    def result(self) -> Any:
        """Wait for the call, raise its error if it failed, and reap the worker. If the worker
        exited before it answered (it died, or could not start), the call runs in this process,
        and it is said. A Ctrl-C while waiting stops the worker."""
        from agents.worker import WorkerStopped

        try:
            return self._worker.result(self._call)
        except WorkerStopped as e:
            print(f"mpa-gym evaluate: the worker of {self._what} stopped ({e}); running "
                  f"{self._what} in this process", file=sys.stderr, flush=True)
        finally:
            self._worker.close()
        return self._fn(*self._args, **self._kwargs)

    def cancel(self) -> None:
        """Stop the worker now (the caller failed or was interrupted: nobody waits for it)."""
        self._worker.terminate()


def sweep_in_background(policies: list[str], **kwargs: Any) -> Background | None:
    """``agents.robustness.robustness(policies, **kwargs)`` started in a second process (a fresh
    interpreter: the policies load there from their specs), or None on a single core."""
    if len(os.sched_getaffinity(0)) < 2:
        return None
    from agents.robustness import robustness as sweep

    return Background("the robustness sweep", sweep, policies, **kwargs)


def seed_groups(groups: list[list[str]], results: dict[str, Any]) -> dict[str, Any]:
    """The groups of run folders of one config (``agents.seeds.group_runs``): per scenario the
    IQM of each metric and its 95 % stratified-bootstrap CI over the runs, and the aggregate
    learning curves (:mod:`agents.seeds`). A lone run of its config is in no group."""
    from agents.seeds import aggregate, group_label, learning_curves

    out: dict[str, Any] = {}
    for runs in groups:
        label = group_label(runs)
        out[label] = {"runs": [_label(r) for r in runs], "results": aggregate(results, runs),
                      "curves": learning_curves(runs)}
    return out


def learning_speed(policies: list[str], results: dict[str, Any], scenario: str = "heldout_b"
                   ) -> dict[str, Any]:
    """For each run folder: the env steps its held-out evaluations took to reach the
    feedforward's position RMSE on ``scenario`` (default ``heldout_b``, the held-out plant
    under an unknown 0.8 kg load; the feedforward is measured in this same report)."""
    from agents.train import read_eval_history

    ff = results.get(scenario, {}).get("ff")
    out: dict[str, Any] = {}
    for spec in policies:
        hist_path = Path(spec) / "eval" / "evaluations.json"
        if not hist_path.is_file():
            continue
        hist = read_eval_history(hist_path.parent)[0]
        curve = [(h["timesteps"], h["scenarios"][scenario]["position_rmse_mm"]) for h in hist
                 if scenario in h["scenarios"]]
        entry: dict[str, Any] = {"scenario": scenario, "curve": curve}
        if ff is not None and curve:
            target = ff["position_rmse_mm"]
            reached = [t for t, r in curve if r <= target]
            entry.update(ff_position_rmse_mm=target,
                         steps_to_ff_score=reached[0] if reached else None)
        out[_label(spec)] = entry
    return out


def tuned_on(spec: str) -> str:
    """What a controller was tuned or trained on, for the report."""
    from agents.baselines import TUNED_ON

    if spec in TUNED_ON:
        return TUNED_ON[spec]
    if Path(spec).is_dir():
        from agents.policies import load_policy

        policy, _, cfg = load_policy(spec)
        from mpa_gym.analysis.scenario import load_scenario

        rnd = load_scenario(cfg.env_kwargs.get("scenario", "nominal")).randomize
        steps = getattr(getattr(policy, "model", None), "num_timesteps", cfg.n_timesteps)
        return (f"PPO, {steps} env steps on the training scenario of its config "
                f"(randomize: {rnd.describe()})")
    return "–"


def _label(spec: str) -> str:
    return Path(spec).name if Path(spec).is_dir() else spec


COLUMNS = [("position_rmse_mm", "position RMSE [mm]"), ("position_max_mm", "max |X − X̂| [mm]"),
           ("stiffness_rmse_pct", "stiffness RMSE [% of k̂]"),
           ("saturation_pct", "pressure saturation [% of steps]"),
           ("recovery_s", "recovery after impulse [s]"), ("return", "return"),
           ("fallback_s", "supervisor's fallback took over at [s]"),
           ("last_resort_s", "supervisor's last resort took over at [s]")]


def markdown(report: dict[str, Any]) -> str:
    res = report["results"]
    groups = report.get("groups") or {}
    in_group = {r for g in groups.values() for r in g["runs"]}
    ctrls = [c for c in next(iter(res.values())) if c not in in_group]
    out = ["# Evaluation report", "",
           f"Episode seed {report['seed']}; metrics over the last three reference periods; "
           "saturation over the whole episode; recovery: time after the impulse until "
           f"|X − X̂| stays below {RECOVERY_BAND_M * 1e3:g} mm."]
    if groups:
        out.append("Several runs of one config are one column: the interquartile mean over "
                   "the runs and its 95 % stratified-bootstrap confidence interval [low, high] "
                   "(rliable); recovery is their median. " + "; ".join(
                       f"{g}: {len(v['runs'])} runs ({', '.join(v['runs'])})"
                       for g, v in groups.items()) + ".")
    if any(Path(c).name == c and c not in BASELINES for c in ctrls):
        out.append("A learned policy given as a single run has no interval (n = 1): train "
                   "several seeds (`mpa-gym train --seeds 0 1 2 3 4`) and pass all the runs.")
    out.append("")
    if report.get("controllers"):
        out += ["## Controllers", "", "| controller | tuned / trained on |", "|---|---|"]
        sup = report.get("supervisors") or {}
        out += [f"| {c} | {d}" + (f"; under a supervisor: {sup[c]}" if c in sup else "") + " |"
                for c, d in report["controllers"].items()] + [""]
    for key, title in COLUMNS:
        if key == "fallback_s" and not report.get("supervisors"):
            continue
        if key == "last_resort_s" and not any(m.get(key) is not None for row in res.values()
                                              for m in row.values()):
            continue
        names = ctrls + [f"{g} (IQM [95 % CI])" for g in groups]
        out += [f"## {title}", "", "| scenario | " + " | ".join(names) + " |",
                "|---|" + "---|" * len(names)]
        for sc, row in res.items():
            cells = []
            for c in ctrls:
                v = row[c][key]
                cell = "–" if v is None else ("never" if v == math.inf else f"{v:.3f}")
                cells.append(cell + (" (terminated)" if row[c]["terminated"] else ""))
            for g in groups.values():
                a = g["results"][sc]
                v = a.get(key)
                cell = "–" if v is None else ("never" if v == math.inf else f"{v:.3f}")
                if f"{key}_ci" in a:
                    lo, hi = a[f"{key}_ci"]
                    cell += f" [{lo:.3f}, {hi:.3f}]"
                if key in ("fallback_s", "last_resort_s"):
                    cell = f"in {a[key.removesuffix('_s') + '_runs']} of {a['n_runs']} runs"
                if a["terminated"]:
                    cell += f" ({a['terminated']} of {a['n_runs']} terminated)"
                cells.append(cell)
            out.append(f"| {sc} | " + " | ".join(cells) + " |")
        out.append("")
    if any(g["curves"] for g in groups.values()):
        out += ["## Learning curves", "", "IQM and 95 % CI of the held-out position RMSE over "
                "each group's runs at every evaluation during training: "
                "`plots/learning_curves.png`.", ""]
    learning = report.get("learning") or {}
    if learning:
        out += ["## Learning speed", "",
                "Env steps each run's held-out evaluations took to reach the feedforward's "
                "position RMSE on its scenario (from the run's `eval/evaluations.json`).", "",
                "| run | scenario | feedforward RMSE [mm] | steps to reach it "
                "| curve (steps: mm) |",
                "|---|---|---|---|---|"]
        for run, e in learning.items():
            curve = ", ".join(f"{t}: {r:.3f}" for t, r in e["curve"])
            steps = e.get("steps_to_ff_score")
            target = e.get("ff_position_rmse_mm")
            out.append(f"| {run} | {e['scenario']} | "
                       f"{'–' if target is None else f'{target:.3f}'} | "
                       f"{'not within the run' if steps is None else steps} | {curve} |")
        out.append("")
    if report.get("robustness"):
        from agents.robustness import markdown as robustness_markdown

        out += robustness_markdown(report["robustness"])
    if report.get("no_harm"):
        from agents.robustness import no_harm_markdown

        out += no_harm_markdown(report["no_harm"])
    return "\n".join(out)


def plot(report: dict[str, Any], out_dir: Path) -> list[Path]:
    """One PNG per scenario: X vs X̂, k vs k̂ and both pressures for every controller."""
    from matplotlib.figure import Figure

    paths = []
    for sc, per_ctrl in report["traces"].items():
        # fixed margins: a constrained layout measured every text box of the 14 figures of a
        # report again at each draw, half of the plotting time
        fig = Figure(figsize=(9, 8))
        fig.subplots_adjust(left=0.09, right=0.98, bottom=0.06, top=0.96, hspace=0.12)
        ax = fig.subplots(4, 1, sharex=True)
        first = next(iter(per_ctrl.values()))
        ax[0].plot(first.t, first.x_ref, "k--", lw=1, label="X̂")
        ax[1].plot(first.t, first.k_ref, "k--", lw=1, label="k̂")
        for i, (name, tr) in enumerate(per_ctrl.items()):
            c = f"C{i}"
            ax[0].plot(tr.t, tr.x, color=c, lw=1, label=name)
            ax[1].plot(tr.t, tr.k, color=c, lw=1, label=name)
            ax[2].plot(tr.t, tr.pressure_bar[:, 0], color=c, lw=1, label=name)
            ax[3].plot(tr.t, tr.pressure_bar[:, 1], color=c, lw=1, label=name)
        ax[0].set(ylabel="X [m]", title=f"scenario {sc}")
        ax[1].set(ylabel="k [N/m]")
        ax[2].set(ylabel="P'_e [bar]")
        ax[3].set(ylabel="P'_f [bar]", xlabel="time [s]")
        for a in ax:
            a.legend(loc="upper right", fontsize=7, ncol=4)
        path = out_dir / f"{sc}.png"
        fig.savefig(path, dpi=90)
        paths.append(path)
    return paths


def write_report(report: dict[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """report.json, report.md and plots/<scenario>.png in ``out_dir``."""
    out = Path(out_dir)
    (out / "plots").mkdir(parents=True, exist_ok=True)
    data = {"seed": report["seed"], "results": _finite(report["results"]),
            "learning": report.get("learning", {}),
            "controllers": report.get("controllers", {}),
            "supervisors": report.get("supervisors", {}),
            "groups": _finite(report.get("groups", {})), "no_harm": report.get("no_harm", {})}
    plots = list(report.get("plots") or plot(report, out / "plots"))
    if report.get("robustness"):
        from agents.robustness import plot as robustness_plot

        data["robustness"] = _finite(report["robustness"])
        plots += robustness_plot(report["robustness"], out / "plots")
    atomic_write_text(out / "report.json", json.dumps(data, indent=1, allow_nan=False))
    atomic_write_text(out / "report.md", markdown(report))
    curves = {g: v["curves"] for g, v in (report.get("groups") or {}).items() if v["curves"]}
    if curves:
        from agents.seeds import plot_curves

        plots.append(plot_curves(curves, out / "plots" / "learning_curves.png"))
    return {"json": out / "report.json", "markdown": out / "report.md",
            "plots": out / "plots", **{f"plot_{p.stem}": p for p in plots}}


def _finite(o: Any) -> Any:
    """JSON has no infinity: a recovery that never happens is written as "never"."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_finite(v) for v in o]
    if isinstance(o, float) and math.isinf(o):
        return "never"
    return o
