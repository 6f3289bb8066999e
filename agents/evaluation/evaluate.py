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
- ``fallback_s``: for a run under a ``supervisor`` (``mpa_gym.agents.controllers.supervisor``), the
  time its fallback took over (``None``: it never did, or the controller has no supervisor);
  ``last_resort_s`` the time its last resort did;
- ``policy_share``: the share of the episode's steps the learned policy drove (its supervisor's
  stage was the policy's); 1.0 where nothing took over, so for every baseline and every
  unsupervised policy;
- ``chosen``: ``"fallback"`` or ``"last_resort"`` where the supervisor started the episode at
  that stage, chosen on the scenario's model before it (``supervisor.select``,
  ``mpa_gym.agents.evaluation.select``; its ``fallback_s`` is then the first step's time), None
  where the policy started.

Who produced a figure is always said. A run folder whose config has a supervisor is evaluated
twice (``mpa_gym.agents.learned.policies.with_alone``): as given, the supervised system (its
row keeps the run's name), and as ``RUN_DIR:alone``, the policy without its supervisor (row
``<run> (alone)``). Groups of runs, the no-harm audit and the sweep have both side by side; the
Markdown tables mark with ‡ every figure of an episode in which a fallback drove (who, from
when, the policy's share of steps), the groups say in how many runs a hand-over happened, and
the plots draw a line where each supervised controller's fallback and last resort took over.

With ``robustness=True`` the report also holds the robustness sweep of
``mpa_gym.agents.evaluation.robustness`` (grids of real-rig effects, easy / medium / hard levels)
with its heatmaps. On a machine with a second core the sweep runs in a second process while the
report's batch runs in this one (both are single-threaded and independent; the numbers are the same
either way).
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

import mpa_gym  # noqa: F401
from mpa_gym.agents.controllers.baselines import BASELINES, TUNED_ON, Policy
from mpa_gym.agents.controllers.gains import Gains
from mpa_gym.agents.controllers.supervisor import (
    CHOSEN,
    HAND_OVERS,
    LAST_RESORT,
    Supervised,
    hand_overs,
    take_over_times,
)
from mpa_gym.agents.evaluation import rigs
from mpa_gym.agents.evaluation.episodes import (
    RECOVERY_BAND_M,
    Job,
    Trace,
    eval_task,
    metrics,
    run_episode,
    run_episodes,
    stack_jobs,
)
from mpa_gym.agents.evaluation.rigs import RIGS_SEED
from mpa_gym.agents.evaluation.robustness import markdown as robustness_markdown
from mpa_gym.agents.evaluation.robustness import no_harm, no_harm_markdown
from mpa_gym.agents.evaluation.robustness import plot as robustness_plot
from mpa_gym.agents.evaluation.robustness import robustness as sweep
from mpa_gym.agents.evaluation.seeds import (
    aggregate,
    group_label,
    group_runs,
    iqm_ci,
    learning_curves,
    plot_curves,
    require_stats,
)
from mpa_gym.agents.evaluation.select import choose_starts
from mpa_gym.agents.learned.config import EVAL_SEED
from mpa_gym.agents.learned.policies import (
    ALONE_LABEL,
    builds_per_scenario,
    has_supervisor,
    is_user_spec,
    load_policy,
    loads_per_scenario,
    run_of,
    spec_label,
    with_alone,
)
from mpa_gym.agents.learned.runs import read_eval_history, run_files
from mpa_gym.agents.worker import Worker, WorkerStopped
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.files import atomic_write_text

if TYPE_CHECKING:
    from matplotlib.figure import Figure

PAPER_SCENARIOS = ["nominal", "initial_error", "impulse", "gamma_mismatch", "mass_mismatch",
                   "load_1kg", "kmax", "kmin"]
HELDOUT_SCENARIOS = ["heldout_a", "heldout_b", "heldout_c", "heldout_bladder"]


def evaluate(policies: list[str], scenarios: list[Any], seed: int = EVAL_SEED,
             robustness: bool = False, batched: bool = True,
             plots_dir: str | Path | None = None, gains: Gains | None = None,
             random_rigs: int = 0, rigs_seed: int = RIGS_SEED) -> dict[str, Any]:
    """Metrics and traces of each controller on each scenario (episode seed ``seed``), the
    robustness sweep if ``robustness``, and ``random_rigs`` random real-rig plants drawn with
    ``rigs_seed`` if any (``mpa_gym.agents.evaluation.rigs``).

    All episodes run as one batch (``mpa_gym.agents.evaluation.episodes.run_episodes``);
    ``batched=False`` runs them one after another
    (``mpa_gym.agents.evaluation.episodes.run_episode``), with the same numbers (a learned
    policy's to float32 rounding: torch's product over a batch of rows). ``plots_dir``: the
    scenario plots (:func:`plot`) are drawn there while the sweep's worker finishes, rather than by
    :func:`write_report` after it (``report["plots"]``). A supervised run folder is evaluated
    also alone (module docstring). ``gains``: the baselines' gains (``load_gains``'s) where
    not their defaults. The controllers built per scenario (the baselines; a run told each
    scenario's delays, or whose supervisor starts where each scenario's model says; your own
    ``module:Class``) run as one stack per controller, one call per step, when their class
    stacks (``baselines.stack``), else as one controller per scenario."""
    loaded = [load_scenario(s) for s in scenarios]  # every input checked before any episode
    _once("--scenarios", [sc.name for sc in loaded], scenarios)
    _once("--policy", [spec_label(p) for p in policies], policies)
    policies = with_alone(policies)
    learned = {spec: load_policy(spec) for spec in policies if not loads_per_scenario(spec)}
    groups = group_runs(policies)  # several runs of one config: checked before any episode
    if groups:
        require_stats()
    # a baseline (and a supervised run: its monitors and fallbacks) is built for its scenario's
    # plan; batched, one stack of them per spec (_scenario_report)
    own = {spec: [load_policy(spec, {"scenario": sc}, gains=gains) for sc in loaded]
           for spec in policies if loads_per_scenario(spec)}
    swept = sweep_in_background(policies, seed=seed, gains=gains) if robustness else None
    try:
        # a supervisor's start on each scenario, chosen on its model (select.choose_starts),
        # while the sweep's worker runs
        supervised = [spec for spec in own if has_supervisor(spec)]
        choose_starts([p for spec in supervised for p in own[spec]],
                      [sc for _ in supervised for sc in loaded],
                      [None] * len(supervised) * len(loaded))
        report = _scenario_report(policies, loaded, learned, own, groups, seed, batched)
        if random_rigs:
            report["random_rigs"] = rigs.random_rigs(policies, random_rigs, rigs_seed, seed,
                                                     gains)
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
        report["robustness"] = (swept.result() if swept
                                else sweep(policies, seed=seed, gains=gains))
    report["controllers"] = {spec_label(p): tuned_on(p, gains) for p in policies}

    report["no_harm"] = no_harm(report["results"], report.get("robustness"),
                                [spec_label(p) for p in policies if p not in BASELINES])
    report["summary"] = summary(report)
    return report


def _once(flag: str, labels: list[str], given: list[Any]) -> None:
    """Refuse two inputs that the report would show under one label (the same run or scenario
    given twice, or two of one name): a report row each, never a run counted twice."""
    seen: dict[str, Any] = {}
    for label, g in zip(labels, given, strict=True):
        if label in seen:
            raise ValueError(f"{flag}: {str(seen[label])!r} and {str(g)!r} are both reported as "
                             f"{label!r}; give each once (several runs of one config go in "
                             "folders of their own, e.g. name-s0 name-s1)")
        seen[label] = g


def _scenario_report(policies: list[str], loaded: list[Any], learned: dict[str, Any],
                     own: dict[str, list[tuple[Policy, str, Any]]],
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
                policy, env_id, run_cfg = own[spec][k]
            jobs.append(Job(sc, policy, env_id, eval_task(run_cfg)))
            keys.append((sc, spec_label(spec)))
    if batched:  # each spec's per-scenario controllers as one stack (its own plans, delays
        # told and starts chosen)
        trs = run_episodes(stack_jobs(jobs, [list(range(c, len(jobs), len(policies)))
                                             for c, spec in enumerate(policies) if spec in own]),
                           seed)
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
    # every controller as loaded (a per-scenario one as for the first scenario): what it is
    every = {**{spec: ps[0] for spec, ps in own.items()}, **learned}
    return {"results": results, "traces": traces, "seed": seed,
            "learning": learning_speed(policies, results),
            "supervisors": {spec_label(p): cfg.supervisor.describe()
                            for p, (pol, _, cfg) in every.items()
                            if isinstance(pol, Supervised)},
            "stages": {spec_label(p): [s.controller for s in cfg.supervisor.stages]
                       for p, (pol, _, cfg) in every.items() if isinstance(pol, Supervised)},
            "kinds": {spec_label(p): controller_kind(p, every) for p in policies},
            "groups": seed_groups(groups, results)}


class Background:
    """A function call running in a spawned worker process (``mpa_gym.agents.worker.Worker``: it
    ignores Ctrl-C, exits with a SIGKILLed parent, and a dead one fails its call rather than
    hangs)."""

    def __init__(self, what: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:

        self._worker = Worker()
        self._what, self._fn, self._args, self._kwargs = what, fn, args, kwargs
        self._call = self._worker.submit(fn, *args, **kwargs)

    def result(self) -> Any:
        """Wait for the call, raise its error if it failed, and reap the worker. If the worker
        exited before it answered (it died, or could not start), the call runs in this process,
        and it is said. A Ctrl-C while waiting stops the worker."""

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
    """``mpa_gym.agents.evaluation.robustness.robustness(policies, **kwargs)`` started in a second
    process (a fresh interpreter: the policies load there from their specs), or None on a single
    core."""
    if len(os.sched_getaffinity(0)) < 2:
        return None

    return Background("the robustness sweep", sweep, policies, **kwargs)


def seed_groups(groups: list[list[str]], results: dict[str, Any]) -> dict[str, Any]:
    """The groups of run folders of one config (``mpa_gym.agents.evaluation.seeds.group_runs``): per
    scenario the IQM of each metric and its 95 % stratified-bootstrap CI over the runs, and the
    aggregate learning curves (:mod:`mpa_gym.agents.evaluation.seeds`). A lone run of its config is
    in no group."""

    out: dict[str, Any] = {}
    for runs in groups:
        out[group_label(runs)] = {"runs": [spec_label(r) for r in runs],
                                  "results": aggregate(results, runs),
                                  "curves": learning_curves(runs)}
    return out


# What drove a report row (``report["kinds"]``): a classical baseline, a run folder under its
# supervisor, the same run's policy without it (``RUN_DIR:alone``), a run without a supervisor,
# any other controller
KINDS = {"baseline": "baseline", "supervised": "supervised (policy + fallback)",
         "alone": "the policy alone", "policy": "the policy (no supervisor)",
         "controller": "controller"}


def controller_kind(spec: str, learned: dict[str, Any]) -> str:
    """``spec``'s key of :data:`KINDS` (``learned``: the loaded run folders, spec → (policy, env
    id, config))."""
    if spec in BASELINES:
        return "baseline"
    run, supervised = run_of(spec)
    if run is None:
        return "controller"
    if not supervised:
        return "alone"
    if spec in learned and isinstance(learned[spec][0], Supervised):
        return "supervised"
    return "policy"


# The report's scenario groups, each summarised by its best controller: the paper's scenarios
# and the held-out plants; any other scenario evaluated falls in OTHER_GROUP.
SCENARIO_GROUPS = {"paper": ("the paper's scenarios", PAPER_SCENARIOS),
                   "held_out": ("held-out plants", HELDOUT_SCENARIOS)}
OTHER_GROUP = ("other", "other scenarios")
# the robustness sweep's combined-effect levels, when the report has the sweep
LEVELS_GROUP = ("levels", "robustness levels")
SUMMARY_METRICS = ("position_rmse_mm", "stiffness_rmse_pct")
# [mm] means closer than this are a tie (equal to the three decimals the report prints): the
# best is then one that drove all its own steps, not a supervised loop whose fallback drove
# most of them to its fallback's figure
SUMMARY_TIE_MM = 5e-4


def scenario_groups(names: list[str]) -> dict[str, dict[str, Any]]:
    """The groups of :data:`SCENARIO_GROUPS` (then :data:`OTHER_GROUP`) among the scenario
    ``names`` of a report: ``{key: {"title": ..., "scenarios": [...]}}``, empty groups left
    out."""
    out = {key: {"title": title, "scenarios": [n for n in names if n in members]}
           for key, (title, members) in SCENARIO_GROUPS.items()}
    grouped = {n for _, members in SCENARIO_GROUPS.values() for n in members}
    out[OTHER_GROUP[0]] = {"title": OTHER_GROUP[1],
                           "scenarios": [n for n in names if n not in grouped]}
    return {k: v for k, v in out.items() if v["scenarios"]}


def summary(report: dict[str, Any]) -> dict[str, Any]:
    """The report's summary: per scenario group (:func:`scenario_groups`) and controller the mean
    of each of ``SUMMARY_METRICS`` over the group's scenarios, and the best controller (lowest
    mean position RMSE among those whose episodes all ran to the end; within
    ``SUMMARY_TIE_MM`` of it, one in whose episodes no fallback took over comes first). With
    the robustness sweep, its levels are one more group (:data:`LEVELS_GROUP`: position RMSE
    only; a terminated cell has none).

    Several runs of one config (``report["groups"]``) are one row: each run's mean over the
    group's scenarios, then their interquartile mean and its 95 % stratified-bootstrap CI
    (``<metric>_ci``; rliable, :func:`mpa_gym.agents.evaluation.seeds.iqm_ci`). Each row says
    who drove: its kind (:data:`KINDS`), in how many of its episodes a supervisor's fallback
    took over (``fallback_episodes``) and the share of steps the learned policy drove."""
    res = report["results"]
    seed = report.get("groups") or {}
    kinds = report.get("kinds") or {}
    in_group = {r for g in seed.values() for r in g["runs"]}
    rows = {c: [c] for c in next(iter(res.values())) if c not in in_group}
    rows.update({g: v["runs"] for g, v in seed.items()})
    sgroups = scenario_groups(list(res))
    tables = {key: (res, SUMMARY_METRICS) for key in sgroups}  # where a group's figures are
    levels = (report.get("robustness") or {}).get("levels") or {}
    if levels:  # the sweep's levels: position only (the sweep measures no stiffness)
        sgroups[LEVELS_GROUP[0]] = {"title": LEVELS_GROUP[1], "scenarios": list(levels)}
        tables[LEVELS_GROUP[0]] = (levels, ("position_rmse_mm",))
    columns = [(key, metric) for key in sgroups for metric in tables[key][1]]
    out: dict[str, Any] = {key: {**grp, "controllers": {}} for key, grp in sgroups.items()}
    for row, labels in rows.items():
        # each run's mean over each group's scenarios, for every (group, metric): runs × columns;
        # NaN where an episode has no figure (a terminated sweep cell)
        means = np.array([[np.mean([np.nan if tables[key][0][sc][lab].get(metric) is None
                                    else tables[key][0][sc][lab][metric]
                                    for sc in sgroups[key]["scenarios"]])
                           for key, metric in columns] for lab in labels])
        point, ci = means[0], np.full((2, len(columns)), np.nan)
        finite = np.all(np.isfinite(means), axis=0)
        if len(labels) > 1:  # one bootstrap for all the row's columns that have figures
            point = np.full(len(columns), np.nan)
            if finite.any():
                point[finite], ci[:, finite] = iqm_ci(means[:, finite])
        for key, grp in sgroups.items():
            table, metrics = tables[key]
            per = [table[sc][lab] for lab in labels for sc in grp["scenarios"]]
            entry: dict[str, Any] = {
                "kind": kinds.get(labels[0], "controller"), "n_runs": len(labels),
                "episodes": len(per), "terminated": sum(bool(m["terminated"]) for m in per),
                "fallback_episodes": sum(m.get("fallback_s") is not None for m in per),
                "chosen_episodes": sum(m.get("chosen") is not None for m in per),
                "policy_share": float(np.mean([m.get("policy_share", 1.0) for m in per]))}
            for metric in metrics:
                j = columns.index((key, metric))
                entry[metric] = float(point[j]) if finite[j] else None
                if len(labels) > 1 and finite[j]:
                    entry[f"{metric}_ci"] = [float(ci[0, j]), float(ci[1, j])]
            if len(labels) > 1:
                entry["runs"] = labels
            out[key]["controllers"][row] = entry
    for grp in out.values():
        ok = {r: e["position_rmse_mm"] for r, e in grp["controllers"].items()
              if not e["terminated"] and e["position_rmse_mm"] is not None}
        if not ok:
            grp["best"] = None
            continue
        low = min(ok.values())
        tied = [r for r, v in ok.items() if v <= low + SUMMARY_TIE_MM]
        own = [r for r in tied if not grp["controllers"][r]["fallback_episodes"]]
        grp["best"] = min(own or tied, key=ok.get)
    return {"metrics": list(SUMMARY_METRICS), "groups": out}


def who_drove_text(entry: dict[str, Any]) -> str:
    """A summary row's who-drove cell, e.g. ``supervised (policy + fallback) ‡: a fallback
    drove in 2 of 8 episodes (chosen on the model in 1); the policy drove 72 % of steps``."""
    text = KINDS.get(entry["kind"], entry["kind"])
    if entry["fallback_episodes"]:
        chosen = entry.get("chosen_episodes") or 0
        text += (f" ‡: a fallback drove in {entry['fallback_episodes']} of "
                 f"{entry['episodes']} episodes"
                 + (f" (chosen on the model in {chosen})" if chosen else "")
                 + f"; the policy drove {entry['policy_share'] * 100:.0f} % of steps")
    elif entry["kind"] == "supervised":
        text += ": the policy drove every step"
    if entry["n_runs"] > 1:
        text += f" (IQM over {entry['n_runs']} runs)"
    return text


def summary_cell(entry: dict[str, Any], metric: str, fmt: str) -> str:
    """``0.123`` or, for several runs, ``0.123 [0.100, 0.150]``; ``(k terminated)`` after;
    ``–`` where the group has no such figure (the sweep's stiffness, a terminated cell)."""
    cell = "–" if entry.get(metric) is None else f"{entry[metric]:{fmt}}"
    if f"{metric}_ci" in entry:
        lo, hi = entry[f"{metric}_ci"]
        cell += f" [{lo:{fmt}}, {hi:{fmt}}]"
    if entry["terminated"]:
        cell += f" ({entry['terminated']} of {entry['episodes']} terminated)"
    return cell


def summary_markdown(summ: dict[str, Any]) -> list[str]:
    """The report's first section: the best controller per scenario group, then every
    controller's means per group."""
    groups = summ["groups"]
    out = ["## Summary", "",
           "Per scenario group: the mean over its scenarios of each controller's position RMSE "
           "and stiffness RMSE (last three periods); best: the lowest mean position RMSE among "
           "controllers none of whose episodes terminated (a tie, within "
           f"{SUMMARY_TIE_MM:g} mm, goes to a controller that drove all its steps itself). "
           "Several runs of one config are one "
           "row: the interquartile mean over the runs of their means, and its 95 % "
           "stratified-bootstrap confidence interval [low, high] (rliable). Who drove: "
           "`(alone)` is a run's policy without its supervisor, its own figures; ‡ marks a "
           "supervised row in which a fallback took over: its figures are the supervised "
           "loop's, not the policy's.", "",
           "| scenario group | best | position RMSE [mm] | stiffness RMSE [% of k̂] | "
           "who drove |", "|---|---|---|---|---|"]
    for g in groups.values():
        title = f"{g['title']} ({len(g['scenarios'])})"
        best = g["best"]
        if best is None:
            out.append(f"| {title} | none: every controller terminated somewhere | – | – | – |")
            continue
        e = g["controllers"][best]
        who = who_drove_text(e)
        alone = best + ALONE_LABEL
        if e["fallback_episodes"] and alone in g["controllers"]:
            a = g["controllers"][alone]
            who += (f"; the policy alone, {alone}: "
                    f"{summary_cell(a, 'position_rmse_mm', '.3f')} mm")
        out.append(f"| {title} | **{best}{' ‡' if e['fallback_episodes'] else ''}** | "
                   f"{summary_cell(e, 'position_rmse_mm', '.3f')} | "
                   f"{summary_cell(e, 'stiffness_rmse_pct', '.2f')} | {who} |")
    out += ["", "| controller | who drove | " + " | ".join(
        f"{g['title']}: position [mm] | {g['title']}: stiffness [%]" for g in groups.values())
        + " |", "|---|---|" + "---|---|" * len(groups)]
    rows = next(iter(groups.values()))["controllers"]
    for row, first in rows.items():
        cells = []
        for g in groups.values():
            e = g["controllers"][row]
            star = "**" if g["best"] == row else ""
            took = (f" ‡ fallback in {e['fallback_episodes']} of {e['episodes']}"
                    if e["fallback_episodes"] else "")
            cells += [f"{star}{summary_cell(e, 'position_rmse_mm', '.3f')}{star}{took}",
                      summary_cell(e, "stiffness_rmse_pct", ".2f")]
        kind = KINDS.get(first["kind"], first["kind"]) + (
            f" (IQM over {first['n_runs']} runs)" if first["n_runs"] > 1 else "")
        out.append(f"| {row} | {kind} | " + " | ".join(cells) + " |")
    return [*out, ""]


def learning_speed(policies: list[str], results: dict[str, Any], scenario: str = "heldout_b"
                   ) -> dict[str, Any]:
    """For each run folder: the env steps its held-out evaluations took to reach the
    feedforward's position RMSE on ``scenario`` (default ``heldout_b``, the held-out plant
    under an unknown 0.8 kg load; the feedforward is measured in this same report)."""
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
        out[spec_label(spec)] = entry
    return out


def tuned_on(spec: str, gains: Gains | None = None) -> str:
    """What a controller was tuned or trained on, for the report (``gains``: the gains it ran
    with instead of its defaults)."""

    if spec in (gains or {}):
        return ("gains " + ", ".join(f"{k} = {v:.4g}" for k, v in gains[spec].items())
                + " (given with --gains); defaults: " + TUNED_ON[spec])
    if spec in TUNED_ON:
        return TUNED_ON[spec]
    if is_user_spec(spec):
        return f"your own controller ({spec})"
    run, supervised = run_of(spec)
    if run is not None:
        policy, _, cfg = load_policy(str(run), supervised=False)
        rnd = load_scenario(cfg.env_kwargs.get("scenario", "nominal")).randomize
        steps = getattr(getattr(policy, "model", None), "num_timesteps", cfg.n_timesteps)
        zoo = run_files(run).zoo_args is not None
        return (f"PPO, {steps} env steps on the training scenario of its config "
                f"(randomize: {rnd.describe()})"
                + ("; trained by rl-baselines3-zoo (its config.yml and args.yml), which "
                   "ignores the config's mpa_gym section: no supervisor, not anchored at rest"
                   if zoo else "")
                + ("" if supervised or cfg.supervisor is None else
                   "; evaluated alone, without its config's supervisor"))
    return "–"


COLUMNS = [("position_rmse_mm", "position RMSE [mm]"), ("position_max_mm", "max |X − X̂| [mm]"),
           ("stiffness_rmse_pct", "stiffness RMSE [% of k̂]"),
           ("saturation_pct", "pressure saturation [% of steps]"),
           ("recovery_s", "recovery after impulse [s]"), ("return", "return"),
           ("fallback_s", "supervisor's fallback took over at [s]"),
           ("last_resort_s", "supervisor's last resort took over at [s]"),
           ("policy_share", "share of steps the learned policy drove")]
WHO_DROVE = ("fallback_s", "last_resort_s", "policy_share")  # columns that say who drove
def _fmt(v: Any) -> str:
    return "–" if v is None else ("never" if v == math.inf else f"{v:.3f}")


def markdown(report: dict[str, Any]) -> str:
    res = report["results"]
    groups = report.get("groups") or {}
    stages = report.get("stages") or {}
    in_group = {r for g in groups.values() for r in g["runs"]}
    ctrls = [c for c in next(iter(res.values())) if c not in in_group]
    out = ["# Evaluation report", ""]
    if report.get("summary"):
        out += summary_markdown(report["summary"])
    out += [f"Episode seed {report['seed']}; metrics over the last three reference periods; "
            "saturation over the whole episode; recovery: time after the impulse until "
            f"|X − X̂| stays below {RECOVERY_BAND_M * 1e3:g} mm."]
    if groups:
        out.append("Several runs of one config are one column: the interquartile mean over "
                   "the runs and its 95 % stratified-bootstrap confidence interval [low, high] "
                   "(rliable); recovery is their median. " + "; ".join(
                       f"{g}: {len(v['runs'])} runs ({', '.join(v['runs'])})"
                       for g, v in groups.items()) + ".")
    if any(Path(c).name == c and not builds_per_scenario(c) for c in ctrls):
        out.append("A learned policy given as a single run has no interval (n = 1): train "
                   "several seeds (`mpa-gym train --seeds 0 1 2 3 4`) and pass all the runs.")
    if report.get("supervisors"):
        out.append("Who drove: a run under a supervisor is shown twice, as the supervised "
                   "system (its name) and as the policy without its supervisor "
                   "(`<run> (alone)`, the policy's own figures). ‡: a supervisor's fallback "
                   "drove part of this episode (which controller, from when, and the share of "
                   "steps the learned policy drove): the figure is the supervised loop's, not "
                   "the policy's; for a group, in how many of its runs that happened.")
    out.append("")
    if report.get("controllers"):
        out += ["## Controllers", "", "| controller | tuned / trained on |", "|---|---|"]
        sup = report.get("supervisors") or {}
        out += [f"| {c} | {d}" + (f"; under a supervisor: {sup[c]}" if c in sup else "") + " |"
                for c, d in report["controllers"].items()] + [""]
    for key, title in COLUMNS:
        if key in WHO_DROVE and not report.get("supervisors"):
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
                cell = _fmt(row[c].get(key)) + (" (terminated)" if row[c]["terminated"] else "")
                if key == f"{row[c].get('chosen')}_s" or (
                        key == "fallback_s" and row[c].get("chosen") == CHOSEN[LAST_RESORT]):
                    cell = "chosen on the model" if key == f"{row[c]['chosen']}_s" else "–"
                took = "" if key in WHO_DROVE else hand_overs(row[c], stages.get(c))
                cells.append(cell + (f" ‡ {took}" if took else ""))
            for g in groups.values():
                a = g["results"][sc]
                cell = _fmt(a.get(key))
                if f"{key}_ci" in a:
                    lo, hi = a[f"{key}_ci"]
                    cell += f" [{lo:.3f}, {hi:.3f}]"
                if key in ("fallback_s", "last_resort_s"):
                    cell = f"in {a[key.removesuffix('_s') + '_runs']} of {a['n_runs']} runs"
                    if a.get("chosen_runs"):
                        cell += f" (chosen on the model in {a['chosen_runs']})"
                if a["terminated"]:
                    cell += f" ({a['terminated']} of {a['n_runs']} terminated)"
                if key not in WHO_DROVE and a.get("fallback_runs"):
                    cell += (f" ‡ a fallback drove in {a['fallback_runs']} of {a['n_runs']} "
                             "runs" + (f" (chosen on the model in {a['chosen_runs']})"
                                       if a.get("chosen_runs") else ""))
                cells.append(cell)
            out.append(f"| {sc} | " + " | ".join(cells) + " |")
        out.append("")
    if any(g["curves"] for g in groups.values()):
        out += ["## Learning curves", "", "IQM and 95 % CI of the held-out position RMSE over "
                "each group's runs at every evaluation during training (the policy alone: "
                "training's evaluations run without a supervisor): "
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
        out += robustness_markdown(report["robustness"])
    if report.get("no_harm"):
        out += no_harm_markdown(report["no_harm"])
    if report.get("random_rigs"):
        out += rigs.markdown(report["random_rigs"])
    return "\n".join(out)


def scenario_figure(sc: str, per_ctrl: dict[str, Trace],
                    stages: dict[str, list[str]] | None = None) -> Figure:
    """One scenario's figure: X vs X̂ [mm], the error X − X̂ [mm] in a panel of its own, k vs k̂ and
    both pressures for every controller; a vertical line in every panel, in the controller's
    colour, where a supervised controller's fallback (dashed) and last resort (dotted) took over,
    labelled in the error panel (``stages``: the supervisor's controllers, ``report["stages"]``)."""
    from matplotlib.figure import Figure

    # fixed margins: a constrained layout measured every text box of the 14 figures of a
    # report again at each draw, half of the plotting time
    fig = Figure(figsize=(9, 9.5))
    fig.subplots_adjust(left=0.09, right=0.98, bottom=0.05, top=0.96, hspace=0.12)
    ax = fig.subplots(5, 1, sharex=True)
    first = next(iter(per_ctrl.values()))
    ax[0].plot(first.t, first.x_ref * 1e3, "k--", lw=1, label="X̂")
    ax[2].plot(first.t, first.k_ref, "k--", lw=1, label="k̂")
    for i, (name, tr) in enumerate(per_ctrl.items()):
        c = f"C{i}"
        ax[0].plot(tr.t, tr.x * 1e3, color=c, lw=1, label=name)
        ax[1].plot(tr.t, (tr.x - tr.x_ref) * 1e3, color=c, lw=1, label=name)
        ax[2].plot(tr.t, tr.k, color=c, lw=1, label=name)
        ax[3].plot(tr.t, tr.pressure_bar[:, 0], color=c, lw=1, label=name)
        ax[4].plot(tr.t, tr.pressure_bar[:, 1], color=c, lw=1, label=name)
        names = (stages or {}).get(name)
        for (key, stage), ls in zip(HAND_OVERS, ("--", ":"), strict=True):
            t = take_over_times(tr.t, tr.fallback)[key]
            if t is None or stage < tr.start:  # a stage the chosen start passed over
                continue
            who = names[stage] if names else CHOSEN[stage]
            said = "chosen on the model" if stage == tr.start else f"from {t:.1f} s"
            for a in ax:
                a.axvline(t, color=c, ls=ls, lw=1.2,
                          label=f"{name}: {who} {said}" if a is ax[1] else None)
    ax[0].set(ylabel="X [mm]", title=f"scenario {sc}")
    ax[1].set(ylabel="X − X̂ [mm]")
    ax[2].set(ylabel="k [N/m]")
    ax[3].set(ylabel="P'_e [bar]")
    ax[4].set(ylabel="P'_f [bar]", xlabel="time [s]")
    for a in ax:
        a.legend(loc="upper right", fontsize=7, ncol=4)
    return fig


def plot(report: dict[str, Any], out_dir: Path) -> list[Path]:
    """One PNG per scenario (:func:`scenario_figure`)."""
    paths = []
    for sc, per_ctrl in report["traces"].items():
        path = out_dir / f"{sc}.png"
        scenario_figure(sc, per_ctrl, report.get("stages")).savefig(path, dpi=90)
        paths.append(path)
    return paths


def hand_over_lines(report: dict[str, Any]) -> list[str]:
    """``<controller> on <scenario>: pid from 9.5 s; policy 79 % of steps`` for every row of a
    report in which a supervisor's fallback took over, the same for every robustness level and
    kick, and the count per robustness grid (``mpa-gym evaluate``'s summary)."""
    stages = report.get("stages") or {}
    rob = report.get("robustness") or {}
    rows = [(sc, row) for sc, row in report["results"].items()]
    rows += [(f"{key[:-1]} {n}", per) for key in ("levels", "kicks")
             for n, per in (rob.get(key) or {}).items()]
    lines = [f"{c} on {where}: {hand_overs(m, stages.get(c))}"
             for where, row in rows for c, m in row.items() if m.get("fallback_s") is not None]
    for name, g in (rob.get("grids") or {}).items():
        n_cells = len(g["rows"]["values"]) * len(g["cols"]["values"])
        lines += [f"{c} on grid {name}: {n} of {n_cells} cells"
                  for c, n in (g.get("hand_overs") or {}).items() if n]
        lines += [f"{c} on grid {name}: a fallback chosen on the model on {n} of {n_cells} "
                  "cells" for c, n in (g.get("chosen") or {}).items() if n]
    return lines


def write_report(report: dict[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """report.json, report.md and plots/<scenario>.png in ``out_dir``."""
    out = Path(out_dir)
    (out / "plots").mkdir(parents=True, exist_ok=True)
    data = {"seed": report["seed"], "results": _finite(report["results"]),
            "learning": report.get("learning", {}),
            "controllers": report.get("controllers", {}),
            "supervisors": report.get("supervisors", {}),
            "stages": report.get("stages", {}),
            "groups": _finite(report.get("groups", {})), "no_harm": report.get("no_harm", {}),
            "kinds": report.get("kinds", {}), "summary": report.get("summary", {})}
    plots = list(report.get("plots") or plot(report, out / "plots"))
    if report.get("random_rigs"):
        data["random_rigs"] = report["random_rigs"]
    if report.get("robustness"):
        data["robustness"] = _finite(report["robustness"])
        plots += robustness_plot(report["robustness"], out / "plots")
    atomic_write_text(out / "report.json", json.dumps(data, indent=1, allow_nan=False))
    atomic_write_text(out / "report.md", markdown(report))
    curves = {g: v["curves"] for g, v in (report.get("groups") or {}).items() if v["curves"]}
    if curves:
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
