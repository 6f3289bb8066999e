"""Robustness sweep: every controller over grids of real-rig plant effects, and three levels of
combined effects in the style of realworldrl_suite (Dulac-Arnold et al., 2020: easy / medium /
hard perturbation specs).

Each grid runs as one batch through the native vector env: leg i is the grid's cell i, with its
own plant set by ``reset(options={"plant": [dict per leg]})``, so a 5 × 5 grid costs one episode
of a 25-leg batch. Per cell and controller, over the last three reference periods:

- ``position_rmse_mm``: RMSE of X − X̂;
- ``aperiodic_rmse_mm``: RMSE of what is left of X − X̂ after removing its average over the
  three periods (its periodic part). A stable closed loop settles onto a motion with the
  reference's period (a sag under a load is periodic and leaves nothing); a limit cycle at
  another frequency or a growing oscillation does not;
- ``unstable``: ``aperiodic_rmse_mm`` > ``UNSTABLE_APERIODIC_MM`` (1 mm, 5 % of the reference's
  20 mm amplitude) or the episode terminated (the leg left its bounds or the model's domain);
- ``terminated``;
- who drove (``mpa_gym.agents.controllers.supervisor.who_drove``): ``fallback_s`` and
  ``last_resort_s``, when a supervisor's fallback and last resort took over (None: they did
  not, or there is no supervisor), and ``policy_share``, the share of the episode's steps the
  learned policy drove (1.0 where nothing took over: every baseline and unsupervised policy).

A supervised run folder is swept twice, as given (the supervised system) and as
``RUN_DIR:alone`` (``mpa_gym.agents.learned.policies.ALONE``: the policy without its
supervisor), so that the grids and the no-harm audit show both side by side.

A learned controller's cells are marked ``held_out`` where a value lies outside what its
training scenario draws (its ``randomize`` range, or its fixed plant value).

``KICKS`` are plants hit by ``LEVEL_KICK`` alone (no other effect): the time after it until
|X − X̂| stays below 1 mm. ``no_harm`` audits a report for what a residual must never do: on
every scenario, grid cell, level and kick plant, a learned controller's position RMSE must be
at most the feedforward's it corrects and at most ``HARM_RATIO`` times the best feedback
baseline's (either bound raised to ``HARM_FLOOR_MM``), and its loop stable where the
feedforward's is.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mpa_gym.agents.controllers.baselines import Policy
from mpa_gym.agents.controllers.gains import Gains
from mpa_gym.agents.controllers.supervisor import (
    CHOSEN,
    FALLBACK,
    LAST_RESORT,
    NOISE_FLOOR_MM,
    handed_over,
)
from mpa_gym.agents.evaluation.episodes import (
    UNSTABLE_APERIODIC_MM,
    Job,
    cell_metrics,
    eval_task,
    recovery_s,
    run_episodes,
    stack_jobs,
)
from mpa_gym.agents.evaluation.select import predict
from mpa_gym.agents.learned.config import EVAL_SEED
from mpa_gym.agents.learned.policies import (
    has_supervisor,
    load_for_plant,
    load_policy,
    run_of,
    selects,
    spec_label,
    tells_delays,
    with_alone,
)
from mpa_gym.analysis.scenario import Impulse, Plant, Randomization, Scenario, load_scenario


@dataclass(frozen=True)
class Grid:
    """A two-field grid of plants on top of ``base`` (per-leg plant fields) and ``rig``
    (rig-wide plant fields, shared by every cell)."""

    name: str
    row_field: str
    row_values: tuple[float, ...]
    col_field: str
    col_values: tuple[float, ...]
    base: dict[str, float] = field(default_factory=dict)
    rig: dict[str, float] = field(default_factory=dict)

    def cells(self) -> list[dict[str, float]]:
        """Per-leg plant dicts, row-major."""
        return [{**self.base, self.row_field: r, self.col_field: c}
                for r in self.row_values for c in self.col_values]


GRIDS = (
    # around the slow-regulator plant (docs/design.md#reference-plants): a 30 ms lag and a
    # 0.02 bar quantum; dead time up to 40 ms and loads up to 2 kg (cells beyond a learned
    # controller's training ranges are marked held out in the report)
    Grid("dead_time_x_mass", "pressure_dead_time_s", (0.0, 0.01, 0.02, 0.03, 0.04),
         "extra_mass_kg", (0.0, 0.5, 1.0, 1.6, 2.0), base={"pressure_lag_s": 0.03},
         rig={"pressure_quantum_bar": 0.02}),
    # the friction plant (docs/design.md#reference-plants): braid-friction hysteresis and
    # slider friction behind a 20 ms lag
    Grid("hysteresis_x_slider_friction", "braid_friction_ratio", (0.0, 0.01, 0.03, 0.05),
         "slider_friction_N", (0.0, 0.5, 1.5, 3.0), base={"pressure_lag_s": 0.02}),
)

# Combined effects at three levels (each a plant of its own), with a 30 N × 50 ms kick at 10 s.
LEVELS: dict[str, dict[str, float]] = {
    "easy": {"pressure_dead_time_s": 0.01, "pressure_lag_s": 0.02, "pressure_slew_bar_per_s": 20.0,
             "braid_friction_ratio": 0.01, "slider_friction_N": 0.5,
             "slider_viscous_Ns_per_m": 1.0, "extra_mass_kg": 0.3},
    "medium": {"pressure_dead_time_s": 0.02, "pressure_lag_s": 0.03,
               "pressure_slew_bar_per_s": 10.0, "braid_friction_ratio": 0.03,
               "slider_friction_N": 1.5, "slider_viscous_Ns_per_m": 3.0, "extra_mass_kg": 0.8},
    "hard": {"pressure_dead_time_s": 0.03, "pressure_lag_s": 0.05, "pressure_slew_bar_per_s": 5.0,
             "braid_friction_ratio": 0.05, "slider_friction_N": 3.0,
             "slider_viscous_Ns_per_m": 5.0, "extra_mass_kg": 1.6},
}
LEVEL_RIG = {"pressure_quantum_bar": 0.02}
LEVEL_KICK = Impulse(t_s=10.0, force_N=30.0, duration_s=0.05)
# Plants hit by LEVEL_KICK alone (recovery time): the leg with a 1.6 kg load
KICKS: dict[str, dict[str, float]] = {"load_1.6kg": {"extra_mass_kg": 1.6}}

HARM_RATIO = 1.5  # a learned residual may be this much worse than the best feedback baseline
HARM_FLOOR_MM = NOISE_FLOOR_MM  # [mm] an RMSE below this is no harm (sensor noise)
FEEDBACK_BASELINES = ("pid", "mbfb", "rc")


def _scenario(base: Scenario, name: str, rig: dict[str, float],
              disturbances: tuple[Impulse, ...] = ()) -> Scenario:
    return dataclasses.replace(base, name=name, plant=Plant(**rig), disturbances=disturbances,
                               randomize=Randomization())


def run_batch(spec: str | Policy, sc: Scenario, plants: list[dict[str, float]], seed: int,
              gains: Gains | None = None) -> dict[str, np.ndarray]:
    """One episode of controller ``spec`` (a name, a run folder, or a policy object for
    ``MPALegResidual-v0``) on a batch with one leg per plant: per leg the time, X and X̂ after
    each step until the episode ends (NaN after a termination), whether it terminated, its
    number of steps (``steps``), and per step the supervisor's stage that drove it
    (``fallback``, ``mpa_gym.agents.controllers.supervisor``; 0, the policy, without one).
    ``gains``: the baselines' gains where not their defaults (``load_gains``'s)."""
    return run_batches([spec], sc, plants, seed, gains)[0]


def plant_jobs(spec: str | Policy, sc: Scenario, plants: list[dict[str, float]], seed: int,
               gains: Gains | None = None) -> list[Job]:
    """One episode of ``spec`` (a name, or a controller object) on ``sc`` per plant, plant j's
    reset with seed ``seed + j``; one controller object for all of them (a batch), except a
    policy that observes the rig's delays, which is told each plant's
    (``policies.load_for_plant``: one object for the plants of equal delays), and a supervised
    run whose start is chosen on the model (``policies.selects``): its stages are predicted on
    each plant (``select.predict``), and the plants that start at the same stage (and are told
    the same delays) share one object, started there. Those objects run as one stack
    (``episodes.stack_jobs``), one call per step."""
    tells = isinstance(spec, str) and tells_delays(spec)
    told: dict[Any, tuple[Policy, str, Any]] = {}
    if tells:  # one object per pair of delays told
        for p in plants:
            if _delays(p) not in told:
                told[_delays(p)] = load_for_plant(spec, sc, p, gains)
        loaded = [told[_delays(p)] for p in plants]
    else:
        one = (load_policy(spec, {"scenario": sc}, gains=gains) if isinstance(spec, str)
               else (spec, "MPALegResidual-v0", None))
        loaded = [one] * len(plants)
    if isinstance(spec, str) and selects(spec):  # one object per start (and delays told)
        started: dict[Any, tuple[Policy, str, Any]] = {}
        chose: set[int] = set()  # the objects loaded above that already have their start
        for j, (p, figures) in enumerate(zip(plants, predict(loaded, [sc] * len(plants),
                                                                plants), strict=True)):
            key = (_delays(p) if tells else None, loaded[j][0].spec.select.start(*figures))
            if key not in started:
                fresh = id(loaded[j][0]) not in chose
                started[key] = loaded[j] if fresh else load_for_plant(spec, sc, p, gains)
                chose.add(id(started[key][0]))
                # the start the key says (its predicted figures: this group's first plant's)
                started[key][0].choose(*figures)
            loaded[j] = started[key]
    jobs = [Job(sc, policy, env_id, eval_task(run_cfg), plant=p, seed=seed + j)
            for j, ((policy, env_id, run_cfg), p) in enumerate(zip(loaded, plants, strict=True))]
    return stack_jobs(jobs, [list(range(len(jobs)))])  # the objects above, one call per step


def _delays(plant: dict[str, float]) -> tuple[Any, Any]:
    """What a policy that observes the rig's delays is told of ``plant``."""
    return plant.get("pressure_dead_time_s"), plant.get("pressure_lag_s")


def run_batches(specs: list[str | Policy], sc: Scenario, plants: list[dict[str, float]],
                seed: int, gains: Gains | None = None) -> list[dict[str, np.ndarray]]:
    """:func:`run_batch` for several controllers at once, each on every plant, as one call of
    ``mpa_gym.agents.evaluation.episodes.run_episodes``: controllers that run in the same env (id
    and task settings) share one vector env, a block of legs each, so a step of the sweep is one
    engine call per env rather than per controller; leg j of every block is reset with seed
    ``seed + j``, as the single batch seeds it."""
    jobs = [job for spec in specs for job in plant_jobs(spec, sc, plants, seed, gains)]
    traces = run_episodes(jobs, seed)
    n = len(plants)
    steps = max(len(tr.t) for tr in traces)
    dt = float(traces[0].t[0])
    out = []
    for c in range(len(specs)):
        mine = traces[c * n:(c + 1) * n]
        x = np.full((steps, n), np.nan)
        xr = np.full((steps, n), np.nan)
        fb = np.zeros((steps, n), dtype=np.int8)  # the supervisor's stage at the step
        for j, tr in enumerate(mine):
            x[:len(tr.t), j], xr[:len(tr.t), j] = tr.x, tr.x_ref
            if tr.fallback is not None:
                fb[:len(tr.t), j] = tr.fallback
        out.append({"t": dt * np.arange(1, steps + 1), "x": x, "x_ref": xr,
                    "terminated": np.array([tr.terminated for tr in mine]), "fallback": fb,
                    "steps": np.array([len(tr.t) for tr in mine]),
                    "start": np.array([tr.start for tr in mine])})
    return out


def training_ranges(spec: str) -> dict[str, tuple[float, float]] | None:
    """What a run folder's training scenario draws, field -> (low, high); None for a
    baseline (no training plants)."""
    run, _ = run_of(spec)
    if run is None:
        return None
    _, _, cfg = load_policy(str(run), supervised=False)
    sc = load_scenario(cfg.env_kwargs["scenario"])
    ranges = {k: (v, v) for k, v in dataclasses.asdict(sc.plant).items() if v is not None}
    ranges.update(sc.randomize.span(sc.plant))
    return ranges


def held_out(plant: dict[str, float], ranges: dict[str, tuple[float, float]] | None
             ) -> bool | None:
    """Whether ``plant`` has a value the training scenario never draws (None: no training)."""
    if ranges is None:
        return None
    default = Plant()
    for k, v in plant.items():
        lo, hi = ranges.get(k, (getattr(default, k), getattr(default, k)))
        if lo is None or not (lo - 1e-12 <= v <= hi + 1e-12):
            return True
    return False


def robustness(policies: list[str], scenario: Any = "nominal", seed: int = EVAL_SEED,
               grids: tuple[Grid, ...] | None = None,
               levels: dict[str, dict[str, float]] | None = None, kick: Impulse | None = None,
               kicks: dict[str, dict[str, float]] | None = None, gains: Gains | None = None
               ) -> dict[str, Any]:
    """The sweep: ``{"grids": {name: {...}}, "levels": {...}, "kicks": {...}}`` (module
    docstring); by default ``GRIDS``, ``LEVELS``, ``KICKS`` and ``LEVEL_KICK`` on the nominal
    scenario. A supervised run folder is swept also alone (``with_alone``); the baselines run
    with ``gains`` where given (``load_gains``'s)."""
    policies = with_alone(policies)
    grids = GRIDS if grids is None else grids
    levels = LEVELS if levels is None else levels
    kicks = KICKS if kicks is None else kicks
    kick = LEVEL_KICK if kick is None else kick
    base = load_scenario(scenario)
    period = base.reference.period
    labels = {p: spec_label(p) for p in policies}
    ranges = {p: training_ranges(p) for p in policies}
    out: dict[str, Any] = {"scenario": base.name, "seed": seed,
                           "unstable_aperiodic_mm": UNSTABLE_APERIODIC_MM, "grids": {},
                           "levels": {}}
    for g in grids:
        sc = _scenario(base, g.name, g.rig)
        cells = g.cells()
        entry: dict[str, Any] = {
            "rows": {"field": g.row_field, "values": list(g.row_values)},
            "cols": {"field": g.col_field, "values": list(g.col_values)},
            "base": g.base, "rig": g.rig, "controllers": {}}
        for p, run in zip(policies, run_batches(policies, sc, cells, seed, gains), strict=True):
            m = cell_metrics(run, period, float(run["t"][0]))
            for cell, plant in zip(m, cells, strict=True):
                cell["held_out"] = held_out(plant, ranges[p])
            nc = len(g.col_values)
            entry["controllers"][labels[p]] = [m[r * nc:(r + 1) * nc]
                                               for r in range(len(g.row_values))]
            if has_supervisor(p):  # the counts of hand-overs and starts chosen, for the report
                entry.setdefault("hand_overs", {})[labels[p]] = sum(map(handed_over, m))
                entry.setdefault("chosen", {})[labels[p]] = sum(
                    c["chosen"] is not None for c in m)
        out["grids"][g.name] = entry
    out["levels_kick"] = dataclasses.asdict(kick)
    for key, plants_by_name, rig in (("levels", levels, LEVEL_RIG), ("kicks", kicks, {})):
        out[key] = {}
        if not plants_by_name:
            continue
        sc = _scenario(base, key, rig, (kick,))
        names = list(plants_by_name)
        plants = [plants_by_name[n] for n in names]
        out[f"{key}_plants"] = {n: {**plants_by_name[n], **rig} for n in names}
        for p, run in zip(policies, run_batches(policies, sc, plants, seed, gains),
                          strict=True):
            m = cell_metrics(run, period, float(run["t"][0]))
            for i, n in enumerate(names):
                m[i]["recovery_s"] = (None if run["terminated"][i] else recovery_s(
                    run["t"], run["x"][:, i] - run["x_ref"][:, i], kick.t_s + kick.duration_s))
                m[i]["held_out"] = held_out(plants[i], ranges[p])
                out[key].setdefault(n, {})[labels[p]] = m[i]
    return out


def _cases(results: dict[str, Any], rob: dict[str, Any] | None
           ) -> list[tuple[str, dict[str, dict[str, Any]]]]:
    """(where, {controller: metrics}) for every scenario, grid cell, level and kick plant."""
    cases = [(f"scenario {sc}", per) for sc, per in results.items()]
    if not rob:
        return cases
    for name, g in rob["grids"].items():
        ctrls = g["controllers"]
        for r, rv in enumerate(g["rows"]["values"]):
            for c, cv in enumerate(g["cols"]["values"]):
                cases.append((f"{name} {g['rows']['field']} {rv:g}, {g['cols']['field']} {cv:g}",
                              {k: rows[r][c] for k, rows in ctrls.items()}))
    for key in ("levels", "kicks"):
        cases += [(f"{key[:-1]} {n}", per) for n, per in (rob.get(key) or {}).items()]
    return cases


def _rmse(m: dict[str, Any]) -> float:
    """[mm] a case's position RMSE; inf where the episode terminated."""
    v = m.get("position_rmse_mm")
    return math.inf if m.get("terminated") or v is None else float(v)


def _none_if_inf(v: float) -> float | None:
    """None (terminated) for an infinite RMSE: JSON has no infinity."""
    return None if math.isinf(v) else v


def no_harm(results: dict[str, Any], rob: dict[str, Any] | None, learned: list[str]
            ) -> dict[str, Any]:
    """The no-harm audit (module docstring) of each learned controller in ``learned``: per
    controller the number of cases checked and every case that breaks a bound, with the
    figures. Needs ``ff`` and a feedback baseline in the report; ``{}`` without them."""
    out: dict[str, Any] = {}
    cases = _cases(results, rob)
    if not learned or not cases or "ff" not in cases[0][1] or \
            not any(b in cases[0][1] for b in FEEDBACK_BASELINES):
        return out
    for ctrl in learned:
        harm = []
        for where, per in cases:
            m, ff = per[ctrl], per["ff"]
            best = min(_rmse(per[b]) for b in FEEDBACK_BASELINES if b in per)
            x, f = _rmse(m), _rmse(ff)
            reasons = []
            if x > max(f, HARM_FLOOR_MM):
                reasons.append("worse than ff")
            if x > max(HARM_RATIO * best, HARM_FLOOR_MM):
                reasons.append(f"over {HARM_RATIO:g}× the best feedback baseline")
            if m.get("unstable") and not ff.get("unstable"):
                reasons.append("unstable where ff is stable")
            if reasons:
                harm.append({"case": where, "position_rmse_mm": _none_if_inf(x),
                             "ff_mm": _none_if_inf(f), "best_feedback_mm": _none_if_inf(best),
                             "held_out": m.get("held_out"), "reasons": reasons})
        out[ctrl] = {"checked": len(cases), "harm": harm}
    return out


def _cell(m: dict[str, Any]) -> str:
    fb, lr, first = m.get("fallback_s"), m.get("last_resort_s"), m.get("chosen")
    took = ("" if fb is None or first == CHOSEN[LAST_RESORT] else
            " ‡chosen" if first == CHOSEN[FALLBACK] else f" ‡{fb:.1f} s") + (
        "" if lr is None else " §chosen" if first == CHOSEN[LAST_RESORT] else f" §{lr:.1f} s")
    if fb is not None and m.get("policy_share") is not None:
        took += f" (policy {m['policy_share'] * 100:.0f} %)"
    if m["terminated"]:
        return "terminated" + took
    s = f"{m['position_rmse_mm']:.3f}"
    return s + (" **unstable**" if m["unstable"] else "") + took


def markdown(rob: dict[str, Any]) -> list[str]:
    """The robustness section of the Markdown report."""
    out = ["## Robustness sweep", "",
           f"Base scenario `{rob['scenario']}`, episode seed {rob['seed']}. Position RMSE [mm] "
           "over the last three periods; **unstable**: the error's part that does not repeat "
           f"with the reference's period exceeds {rob['unstable_aperiodic_mm']:g} mm RMS (a "
           "limit cycle or a divergence); terminated: the leg left its bounds. A learned "
           "controller's cells outside its training ranges are marked †; ‡t s: its "
           "supervisor's fallback took over at t s, §t s: its last resort did (‡chosen, "
           "§chosen: it drove from the start, chosen on the model), (policy p %): "
           "the share of steps the learned policy drove (the figure is the supervised "
           "loop's); `(alone)`: the same run without its supervisor, the policy's own "
           "figures.", ""]
    for name, g in rob["grids"].items():
        rf, cf = g["rows"]["field"], g["cols"]["field"]
        out += [f"### {name}", "", f"Rows `{rf}`, columns `{cf}`; every cell also has "
                f"{g['base'] or 'nothing else'} per leg and {g['rig'] or 'nothing'} rig-wide.",
                ""]
        for ctrl, rows in g["controllers"].items():
            n, c = g.get("hand_overs", {}).get(ctrl), g.get("chosen", {}).get(ctrl)
            count = ("" if n is None else
                     f" (its supervisor handed over on {n} of {sum(map(len, rows))} cells"
                     + (f"; a fallback chosen on the model drove {c}" if c else "") + ")")
            out += [f"**{ctrl}**{count}", "", f"| {rf} \\ {cf} | "
                    + " | ".join(f"{v:g}" for v in g["cols"]["values"]) + " |",
                    "|---|" + "---|" * len(g["cols"]["values"])]
            for rv, row in zip(g["rows"]["values"], rows, strict=True):
                out.append(f"| {rv:g} | " + " | ".join(
                    _cell(m) + (" †" if m.get("held_out") else "") for m in row) + " |")
            out.append("")
    kick = rob.get("levels_kick") or {}
    for key, title in (("levels", "Levels (realworldrl_suite style)"),
                       ("kicks", "Kicks (the kick alone on a load)")):
        if not rob.get(key):
            continue
        ctrls = list(next(iter(rob[key].values())))
        out += [f"### {title}", "",
                f"Each plant (with a {kick['force_N']:g} N × {kick['duration_s']:g} s "
                f"kick at {kick['t_s']:g} s): position RMSE [mm] / recovery after the kick [s].",
                "", f"| {key[:-1]} | plant | " + " | ".join(ctrls) + " |",
                "|---|---|" + "---|" * len(ctrls)]
        for lv, per in rob[key].items():
            plant = ", ".join(f"{k} {v:g}" for k, v in rob[f"{key}_plants"][lv].items())
            cells = []
            for c in ctrls:
                m = per[c]
                rec = m.get("recovery_s")
                rec_s = "–" if rec is None else ("never" if rec == math.inf else f"{rec:.2f}")
                cells.append(f"{_cell(m)} / {rec_s}" + (" †" if m.get("held_out") else ""))
            out.append(f"| {lv} | {plant} | " + " | ".join(cells) + " |")
        out.append("")
    return out


def no_harm_markdown(audit: dict[str, Any]) -> list[str]:
    """The no-harm section of the Markdown report."""
    if not audit:
        return []
    out = ["## No harm", "",
           "A learned residual must not do worse than the feedforward it corrects, nor than "
           f"{HARM_RATIO:g}× the best feedback baseline ({', '.join(FEEDBACK_BASELINES)}), on "
           f"any scenario, grid cell, level or kick plant (either bound raised to "
           f"{HARM_FLOOR_MM:g} mm), nor be unstable where the feedforward is stable. "
           "† : outside the controller's training ranges. A supervised run is audited twice: "
           "as the supervised system and, `(alone)`, as the policy without its supervisor.",
           ""]
    for ctrl, a in audit.items():
        out.append(f"**{ctrl}**: {len(a['harm'])} of {a['checked']} cases break a bound.")
        if a["harm"]:
            out += ["", "| case | RMSE [mm] | ff [mm] | best feedback [mm] | bound broken |",
                    "|---|---|---|---|---|"]
            for h in a["harm"]:
                out.append(f"| {h['case']}{' †' if h.get('held_out') else ''} | "
                           f"{_mm(h['position_rmse_mm'])} | {_mm(h['ff_mm'])} | "
                           f"{_mm(h['best_feedback_mm'])} | {'; '.join(h['reasons'])} |")
        out.append("")
    return out


def _mm(v: float | None) -> str:
    return "terminated" if v is None else f"{v:.3f}"


def plot(rob: dict[str, Any], out_dir: Path) -> list[Path]:
    """One PNG per grid: a heatmap of position RMSE per controller (log colour scale, shared),
    unstable cells hatched and marked U, terminated cells marked T."""
    import matplotlib
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    paths = []
    for name, g in rob["grids"].items():
        ctrls = list(g["controllers"])
        vals = {c: np.array([[np.nan if m["position_rmse_mm"] is None else m["position_rmse_mm"]
                              for m in row] for row in g["controllers"][c]]) for c in ctrls}
        finite = np.concatenate([v[np.isfinite(v)] for v in vals.values()])
        lo = max(float(finite.min()), 1e-3) if finite.size else 1e-3
        hi = max(float(finite.max()), 10 * lo) if finite.size else 1.0
        fig = Figure(figsize=(3.2 * len(ctrls) + 1, 3.4), layout="constrained")
        axes = np.atleast_1d(fig.subplots(1, len(ctrls)))
        im = None
        cmap = matplotlib.colormaps["viridis"].with_extremes(bad="lightgray")  # terminated
        for ax, c in zip(axes, ctrls, strict=True):
            im = ax.imshow(np.clip(vals[c], lo, hi), norm=LogNorm(lo, hi), cmap=cmap,
                           origin="lower", aspect="auto")
            for r, row in enumerate(g["controllers"][c]):
                for k, m in enumerate(row):
                    txt = ("T" if m["terminated"] else f"{m['position_rmse_mm']:.2g}"
                           + ("\nU" if m["unstable"] else ""))
                    ax.text(k, r, txt, ha="center", va="center", fontsize=7,
                            color="red" if m["unstable"] else "white")
            ax.set_xticks(range(len(g["cols"]["values"])), [f"{v:g}" for v in
                                                            g["cols"]["values"]])
            ax.set_yticks(range(len(g["rows"]["values"])), [f"{v:g}" for v in
                                                            g["rows"]["values"]])
            ax.set(title=c, xlabel=g["cols"]["field"], ylabel=g["rows"]["field"])
        fig.colorbar(im, ax=list(axes), label="position RMSE [mm]")
        path = out_dir / f"robustness_{name}.png"
        fig.savefig(path, dpi=90)
        paths.append(path)
    return paths
