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
- ``return``: the episode's summed reward; ``terminated``: whether the leg left its bounds.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import mpa_gym  # noqa: F401
from agents.baselines import Policy
from agents.policies import load_policy
from mpa_gym.analysis.scenario import load_scenario

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


def run_episode(env: gym.Env, policy: Policy, seed: int, options: dict[str, Any] | None = None
                ) -> Trace:
    """Roll ``policy`` out for one episode of ``env`` (deterministic actions)."""
    obs, info = env.reset(seed=seed, options=options)
    state, start = None, np.array([True])
    rows: list[tuple[Any, ...]] = []
    rewards = []
    terminated = False
    while True:
        action, state = policy.predict(obs, state, start, deterministic=True)
        start = np.array([False])
        obs, r, terminated, truncated, info = env.step(action)
        rows.append((info["t_s"], info["x_m"], info["x_ref_m"], info["k_N_per_m"],
                     info["k_ref_N_per_m"], info["pressure_bar"].copy(),
                     info["pressure_cmd_bar"].copy(), bool(info["safety"] & 1)))
        rewards.append(r)
        if terminated or truncated:
            break
    cols = list(zip(*rows, strict=True))
    return Trace(np.array(cols[0]), np.array(cols[1]), np.array(cols[2]), np.array(cols[3]),
                 np.array(cols[4]), np.array(cols[5]), np.array(cols[6]), np.array(cols[7]),
                 np.array(rewards), bool(terminated))


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
    }


def make_env(env_id: str, scenario: Any, run_cfg: Any = None) -> gym.Env:
    """The env a controller is evaluated in: the scenario, with a learned policy's own task
    settings (control period, limits) if it has a run config."""
    task = (run_cfg.env_kwargs.get("task") if run_cfg is not None else None) or {}
    task = {k: v for k, v in task.items() if k != "episode_s"}  # the scenario's duration rules
    return gym.make(env_id, scenario=scenario, task=task)


def evaluate(policies: list[str], scenarios: list[Any], seed: int = 1_000_000
             ) -> dict[str, Any]:
    """Metrics and traces of each controller on each scenario (episode seed ``seed``)."""
    results: dict[str, dict[str, Any]] = {}
    traces: dict[str, dict[str, Trace]] = {}
    for sc_spec in scenarios:
        sc = load_scenario(sc_spec)
        impulses = [d for d in sc.disturbances if d.type == "impulse"]
        end = impulses[0].t_s + impulses[0].duration_s if impulses else None
        results[sc.name], traces[sc.name] = {}, {}
        for spec in policies:
            policy, env_id, run_cfg = load_policy(spec, {"scenario": sc})
            env = make_env(env_id, sc, run_cfg)
            tr = run_episode(env, policy, seed)
            env.close()
            results[sc.name][_label(spec)] = metrics(tr, sc.reference.period, end)
            traces[sc.name][_label(spec)] = tr
    return {"results": results, "traces": traces, "seed": seed,
            "learning": learning_speed(policies, results)}


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
        hist = json.loads(hist_path.read_text())
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


def _label(spec: str) -> str:
    return Path(spec).name if Path(spec).is_dir() else spec


COLUMNS = [("position_rmse_mm", "position RMSE [mm]"), ("position_max_mm", "max |X − X̂| [mm]"),
           ("stiffness_rmse_pct", "stiffness RMSE [% of k̂]"),
           ("saturation_pct", "pressure saturation [% of steps]"),
           ("recovery_s", "recovery after impulse [s]"), ("return", "return")]


def markdown(report: dict[str, Any]) -> str:
    res = report["results"]
    ctrls = list(next(iter(res.values())))
    out = ["# Evaluation report", "",
           f"Episode seed {report['seed']}; metrics over the last three reference periods; "
           "saturation over the whole episode; recovery: time after the impulse until "
           f"|X − X̂| stays below {RECOVERY_BAND_M * 1e3:g} mm.", ""]
    for key, title in COLUMNS:
        out += [f"## {title}", "", "| scenario | " + " | ".join(ctrls) + " |",
                "|---|" + "---|" * len(ctrls)]
        for sc, row in res.items():
            cells = []
            for c in ctrls:
                v = row[c][key]
                cell = "–" if v is None else ("never" if v == math.inf else f"{v:.3f}")
                cells.append(cell + (" (terminated)" if row[c]["terminated"] else ""))
            out.append(f"| {sc} | " + " | ".join(cells) + " |")
        out.append("")
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
    return "\n".join(out)


def plot(report: dict[str, Any], out_dir: Path) -> list[Path]:
    """One PNG per scenario: X vs X̂, k vs k̂ and both pressures for every controller."""
    from matplotlib.figure import Figure

    paths = []
    for sc, per_ctrl in report["traces"].items():
        fig = Figure(figsize=(9, 8), layout="constrained")
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
            "learning": report.get("learning", {})}
    (out / "report.json").write_text(json.dumps(data, indent=1, allow_nan=False))
    (out / "report.md").write_text(markdown(report))
    return {"json": out / "report.json", "markdown": out / "report.md",
            "plots": out / "plots", **{f"plot_{p.stem}": p for p in plot(report, out / "plots")}}


def _finite(o: Any) -> Any:
    """JSON has no infinity: a recovery that never happens is written as "never"."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, float) and math.isinf(o):
        return "never"
    return o
