"""The supervisor's levels and fallback order, chosen on a run's training plants.

A monitor's level decides when the supervisor (``mpa_gym.agents.controllers.supervisor``) takes
the loop from the policy. Chosen on the plants a report then scores, it fits those plants and
fires on good loops elsewhere; so it is chosen here on draws of the run's own training
randomisation (``CALIBRATION_SEED``, disjoint from the training envs' and the evaluation's
seeds), and its rule is stated:

- the policy alone and every candidate fallback (``CANDIDATES``, with the supervisor's
  ``gains``) run one episode of ``episode_s`` on each of ``n_plants`` draws;
- the fallback order is the candidates sorted by their mean position RMSE (an unstable or
  terminated episode counts ``FAILED_MM``) over the plants a fallback is for, those on which
  the policy alone is unstable or tracks worse than a candidate: the first drives after the
  policy, the second after the first;
- a plant is one the policy must keep where the policy alone tracks at least as well as the
  first fallback would and its loop is stable (the sweep's criterion,
  ``mpa_gym.agents.evaluation.robustness.cell_metrics``);
- each monitor of the policy's stage gets the level ``margin`` × the highest running RMS it
  reaches on those plants (replayed offline on the episode's error, as the supervisor computes
  it online), never below ``floor_mm`` (the limit-cycle monitor never below √2 ×
  ``UNSTABLE_APERIODIC_MM``, the sweep's instability criterion made causal: it fires on
  instability, not on the quantum and friction of a loop that tracks): so on no plant the
  policy should keep would it fire,
  with a margin for plants between the draws; a monitor that would have to sit above the
  allowed levels (``LEVEL_MAX_MM``) to stay quiet there is dropped.

``mpa-gym calibrate RUN_DIR`` prints what it found and, with ``--write``, writes the levels and
the order into the run folder's ``config.yaml`` (the old one kept beside it); the section's
``gains`` and ``select`` are kept as they were.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mpa_gym.agents.controllers.supervisor import (
    LEVEL_MAX_MM,
    Divergence,
    LimitCycle,
    Stage,
    SupervisorSpec,
)
from mpa_gym.agents.evaluation.episodes import run_episodes
from mpa_gym.agents.evaluation.robustness import UNSTABLE_APERIODIC_MM, cell_metrics, plant_jobs
from mpa_gym.agents.learned.config import EVAL_SEED, load_config
from mpa_gym.agents.learned.policies import ALONE
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.files import atomic_write_text
from mpa_gym.model.params import check_range

CALIBRATION_SEED = 2 * EVAL_SEED  # plants and episode seeds: beyond training and evaluation
CANDIDATES = ("pid", "afc", "mbfb", "rc")  # the fallbacks compared
FAILED_MM = 100.0  # [mm] an unstable or terminated episode's score in the fallback order
MARGIN = 1.5  # a level is this times the highest RMS on the plants the policy keeps
FLOOR_MM = 0.3  # [mm] no level below this (sensor noise and quantum are a few hundredths)


@dataclasses.dataclass(frozen=True)
class Calibration:
    """What ``calibrate`` found: the spec to use and the figures behind it."""

    spec: SupervisorSpec
    order: list[tuple[str, float]]  # candidates with their mean RMSE [mm], best first
    ordered_on: int  # the plants the order was measured on (those a fallback is for)
    kept: int  # plants the policy keeps (tracks at least as well as the first fallback)
    n_plants: int
    peaks_mm: dict[str, float]  # per monitor, the highest RMS on the kept plants
    dropped: list[str]  # monitors that could not stay quiet on the kept plants

    def section(self) -> dict[str, Any]:
        """The spec as a config's ``mpa_gym.supervisor`` section."""
        return {"monitors": {m.name: dataclasses.asdict(m) for m in self.spec.monitors},
                "stages": [{"controller": s.controller, "monitors": list(s.monitors),
                            **({"grace_periods": s.grace_periods} if s.grace_periods else {})}
                           for s in self.spec.stages],
                **({"gains": self.spec.gains} if self.spec.gains else {}),
                "select": (None if self.spec.select is None
                           else dataclasses.asdict(self.spec.select))}

    def as_dict(self) -> dict[str, Any]:
        return {**self.section(),
                "rule": self.spec.describe(),
                "fallback_order": [{"controller": c, "mean_position_rmse_mm": v}
                                   for c, v in self.order],
                "ordered_on_plants": self.ordered_on,
                "kept_plants": self.kept, "n_plants": self.n_plants,
                "peaks_mm": self.peaks_mm, "dropped": self.dropped}


def running_rms(monitor: Any, e: np.ndarray, n_period: int, dt: float) -> np.ndarray:
    """[mm] (steps, n) the running RMS of ``monitor`` over errors ``e`` (steps, n) [m] after
    each step, computed as the supervisor does online (``Monitor.update``) from the episode's
    start."""
    z = np.zeros(e.shape[1])
    out = np.empty(e.shape)
    for k in range(e.shape[0]):
        past = e[k - n_period] if k >= n_period else np.zeros(e.shape[1])
        z = monitor.update(z, e[k], past, np.full(e.shape[1], k >= monitor.arm_periods
                                                   * n_period), dt)
        out[k] = np.sqrt(z) * 1e3
    return out


def calibrate(run_dir: str | Path, n_plants: int = 48, episode_s: float = 24.0,
              margin: float = MARGIN, floor_mm: float = FLOOR_MM,
              seed: int = CALIBRATION_SEED) -> Calibration:
    """The module docstring's rule on ``n_plants`` draws of the run's training randomisation.
    The errors name the flags of ``mpa-gym calibrate`` (``--n-plants``, ``--episode-s``)."""
    n_plants = int(check_range("--n-plants", n_plants, 1, 4096))
    check_range("--episode-s", episode_s, 3.0, 600.0, unit="s")
    check_range("margin", margin, 1.0, 10.0)
    run = Path(run_dir)
    cfg = load_config(run / "config.yaml")
    base = load_scenario(cfg.env_kwargs["scenario"])
    sc = dataclasses.replace(base, duration_s=float(episode_s))
    rng = np.random.default_rng(seed)
    plants = [base.randomize.sample(rng) for _ in range(n_plants)]
    # the run's supervisor as configured: its fallbacks are measured with its gains, and
    # calibrating keeps its gains, select and the shape of its cascade
    current = cfg.supervisor if cfg.supervisor is not None else SupervisorSpec()
    scored = [f"{run}{ALONE}", *CANDIDATES]
    jobs = [job for spec in scored
            for job in plant_jobs(spec, sc, plants, seed, gains=current.gains)]
    traces = run_episodes(jobs, seed)
    period = sc.reference.period
    dt = float(traces[0].t[0])
    steps = max(len(tr.t) for tr in traces)
    cells, errors = {}, {}
    for c, spec in enumerate(scored):
        mine = traces[c * n_plants:(c + 1) * n_plants]
        x = np.full((steps, n_plants), np.nan)
        xr = np.full((steps, n_plants), np.nan)
        for j, tr in enumerate(mine):
            x[:len(tr.t), j], xr[:len(tr.t), j] = tr.x, tr.x_ref
        batch = {"t": dt * np.arange(1, steps + 1), "x": x, "x_ref": xr,
                 "terminated": np.array([tr.terminated for tr in mine]),
                 "steps": np.array([len(tr.t) for tr in mine])}
        cells[spec] = cell_metrics(batch, period, dt)
        errors[spec] = np.nan_to_num(xr - x, nan=1.0)  # a terminated leg: a metre of error

    def score(m: dict[str, Any]) -> float:
        return FAILED_MM if m["unstable"] else float(m["position_rmse_mm"])

    policy = cells[scored[0]]
    # the fallback order, by the mean over the plants a fallback is for: those where the policy
    # alone is unstable or tracks worse than some candidate (all plants if there are none)
    lost = np.array([p["unstable"] or any(score(p) > score(cells[c][j]) for c in CANDIDATES)
                     for j, p in enumerate(policy)])
    where = lost if lost.any() else np.ones(n_plants, dtype=bool)
    order = sorted(((c, float(np.mean([score(m) for m in np.array(cells[c])[where]])))
                    for c in CANDIDATES), key=lambda cv: cv[1])
    first = order[0][0]
    keep = np.array([not p["unstable"] and score(p) <= score(f)
                     for p, f in zip(policy, cells[first], strict=True)])
    n_period = max(1, round(period / dt))
    monitors, peaks, dropped = [], {}, []
    for m in current.monitors:
        peak = (float(running_rms(m, errors[scored[0]][:, keep], n_period, dt).max())
                if keep.any() else 0.0)
        peaks[m.name] = peak
        # never below the level a loop the sweep calls stable can reach: an aperiodic part of
        # RMS ρ gives the limit-cycle monitor ≈ √2 ρ (fire on instability, not on the noise,
        # quantum and friction of a loop that tracks)
        floor = (math.sqrt(2.0) * UNSTABLE_APERIODIC_MM if isinstance(m, LimitCycle)
                 else floor_mm)
        level = round(max(margin * peak, floor), 3)  # as written: calibrating again keeps it
        if not isinstance(m, Divergence) and level >= LEVEL_MAX_MM:
            dropped.append(m.name)
            continue
        # the clip keeps its ratio to the level (it must stay above it to let the monitor trip)
        clip = None if m.clip_mm is None else round(m.clip_mm * max(level / m.level_mm, 1.0),
                                                        3)
        monitors.append(dataclasses.replace(m, level_mm=level, clip_mm=clip))
    names = tuple(m.name for m in monitors)
    fallback = current.stages[1]
    stages = [Stage("policy", names),
              Stage(first, fallback.monitors or ("divergence",), fallback.grace_periods)]
    if len(current.stages) > 2:
        stages.append(Stage(order[1][0]))
    else:
        stages[-1] = Stage(first)
    spec = SupervisorSpec(tuple(monitors), tuple(stages), gains=current.gains,
                          select=current.select)
    return Calibration(spec, order, int(where.sum()), int(keep.sum()), n_plants, peaks,
                       dropped)


def write(run_dir: str | Path, cal: Calibration) -> Path:
    """The run folder's config.yaml with ``cal``'s section as its supervisor (the config
    before kept as config.before-calibration.yaml); returns the config's path."""
    run = Path(run_dir)
    path = run / "config.yaml"
    text = path.read_text()
    data = yaml.safe_load(text)
    data.setdefault("mpa_gym", {})["supervisor"] = cal.section()
    atomic_write_text(run / "config.before-calibration.yaml", text)
    atomic_write_text(path, yaml.safe_dump(data, sort_keys=False))
    load_config(path)  # what was written reads back
    return path
