"""Tuning the classical baselines on the PPO residual's training plants (Optuna, TPE).

A fair comparison holds the learned residual against controllers tuned on the same plants it
trained on. ``tune`` draws ``n_plants`` plants from the training scenario of a PPO config (its
``randomize`` ranges, with a fixed seed) and adds each draw's *undamped twin*, the same plant
with the effects that damp or limit an oscillation taken out (``UNDAMPED``: the leg's viscous
damping at the low end of its range, no braid or slider friction, no regulator rate limit).
Uniform draws of a dozen fields rarely combine a long dead time with little friction, yet that
is the plant a loop goes unstable on (a rig's friction changes with wear and lubrication, its
regulator with the supply), and gains tuned on the draws alone can be unstable on the
robustness grid's slow-regulator cells. It runs each candidate's gains on all of them as one
batch of the native vector env, and minimises the mean position RMSE
over the plants, each over the last three periods of a ``episode_s`` episode. A plant on which
the loop is unstable (``mpa_gym.agents.evaluation.robustness``: its error does not settle onto the
reference's period) or terminated counts as ``FAILED_MM``: a control engineer does not field gains
that oscillate on a plant they were tuned for, however small the mean, and a plain mean can pick
a derivative gain far above the leg's critical damping that oscillates on the plants with the
longest dead times (CHANGELOG.md, 0.1.0, 2c66f17). The mean, not the worst case: with dead times
up to 30 ms the worst training plant stays at several millimetres for every gain tried, and a
worst-case objective tunes for that one plant only. The search space of each controller is
``SPACES``; the budget is ``n_trials`` Optuna trials with a seeded TPE sampler, so a run is
reproducible.

``mpa-gym tune-baselines`` runs it and prints the gains and what they were tuned on, and with
``--out FILE`` writes them as a gains file (:func:`write_gains`) that ``evaluate``, ``rollout``,
``bench --loop`` (``--gains FILE``) and a run config's ``supervisor.gains`` read; the defaults
of ``PIDResidual`` / ``StiffnessFeedback`` / ``RepetitiveControl`` and ``baselines.TUNED_ON``
come from it.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from mpa_gym.agents.controllers.baselines import make_baseline
from mpa_gym.agents.controllers.gains import gains_yaml
from mpa_gym.agents.evaluation.robustness import cell_metrics, run_batch
from mpa_gym.agents.learned.config import DEFAULT_CONFIG, load_config
from mpa_gym.agents.training.trials import quiet_signalled_trials
from mpa_gym.analysis.scenario import KICK_FIELDS, Randomization, Scenario, load_scenario
from mpa_gym.files import atomic_write_text
from mpa_gym.model.params import check_range

FAILED_MM = 100.0  # [mm] the score of a plant on which the loop was unstable or terminated
# The undamped twin of a plant (module docstring): field -> "low" (the low end of its range) or
# a value; the leg's damping at the low end, friction and the rate limit off (a slew of 0 is an
# unlimited regulator).
UNDAMPED: dict[str, str | float] = {"gamma_Ns_per_m": "low", "braid_friction_ratio": 0.0,
                                    "slider_friction_N": 0.0, "slider_viscous_Ns_per_m": 0.0,
                                    "pressure_slew_bar_per_s": 0.0}

# controller -> field -> (low, high, log scale)
SPACES: dict[str, dict[str, tuple[float, float, bool]]] = {
    "pid": {"kp_bar_per_m": (5.0, 300.0, True), "ki_bar_per_m_s": (10.0, 1e4, True),
            "kd_bar_s_per_m": (0.1, 40.0, True), "tf_s": (0.0, 0.05, False)},
    "mbfb": {"kp_N_per_m": (100.0, 1e4, True), "ki_N_per_m_s": (10.0, 1e4, True),
             "kd_N_s_per_m": (5.0, 400.0, True), "tf_s": (0.0, 0.05, False)},
    # the repetitive memory on pid's tuned loop: its learning gain and the dead time its
    # filter is designed to tolerate (baselines.repetitive_design)
    "rc": {"learn": (0.02, 1.5, True), "delay_margin_s": (0.0, 0.15, False)},
}


def training_plants(config: str | Path = DEFAULT_CONFIG, n_plants: int = 16, seed: int = 0,
                    episode_s: float = 15.0) -> tuple[Scenario, list[dict[str, float]]]:
    """The config's training scenario (its duration set to ``episode_s``, its randomisation
    taken out), ``n_plants`` draws from its ``randomize`` ranges and then their undamped twins
    (``undamped``): 2 ``n_plants`` plants.

    Every effect is on in every draw (a range's ``p_off`` is ignored): ``p_off`` gives the
    residual's training one-effect plants to learn from, while gains are fielded on a rig that
    has all the effects at once. Tuned on draws with half the dead times off, the pid's gains
    doubled and went unstable from 20 ms of dead time on the unloaded leg. The random kick is
    left out (``every_effect``)."""
    sc = load_scenario(load_config(config).env_kwargs["scenario"])
    rng = np.random.default_rng(seed)
    every = every_effect(sc.randomize)
    plants = [every.sample(rng) for _ in range(n_plants)]
    ranges = {k: (lo, hi) for k, lo, hi in sc.randomize.ranges}
    plants += [undamped(p, ranges) for p in plants]
    base = dataclasses.replace(sc, duration_s=episode_s,
                               randomize=Randomization())
    return base, plants


def every_effect(randomize: Randomization) -> Randomization:
    """``randomize`` with every field drawn in every draw (its ``p_off`` left out), less the
    random kick (``KICK_FIELDS``): a disturbance of the residual's training episodes, not an
    effect of the rig the gains are fielded on, and over before the objective's window (the
    last three periods) opens. Left out, the draws are those of a config without kicks, which
    the committed gains were tuned on."""
    return Randomization(tuple(r for r in randomize.ranges if r[0] not in KICK_FIELDS))


def undamped(plant: dict[str, float], ranges: dict[str, tuple[float, float]]
             ) -> dict[str, float]:
    """``plant`` with ``UNDAMPED``'s fields set: the low end for the "low" fields the ranges draw
    (others keep the scenario's value), the value for the rest."""
    out = dict(plant)
    for k, v in UNDAMPED.items():
        if v != "low":
            out[k] = v
        elif k in ranges:
            out[k] = ranges[k][0]
    return out


def score(name: str, gains: dict[str, float], sc: Scenario, plants: list[dict[str, float]],
          seed: int = 0) -> float:
    """[mm] mean position RMSE of baseline ``name`` with ``gains`` over ``plants``, an unstable
    or terminated plant counting as ``FAILED_MM``."""
    policy = dataclasses.replace(make_baseline(name, sc), **gains)
    run = run_batch(policy, sc, plants, seed)
    m = cell_metrics(run, sc.reference.period, float(run["t"][0]))
    return float(np.mean([FAILED_MM if c["unstable"] else c["position_rmse_mm"] for c in m]))


def tune(name: str, config: str | Path = DEFAULT_CONFIG, n_trials: int = 80,
         n_plants: int = 16, seed: int = 0, episode_s: float = 15.0) -> dict[str, Any]:
    """Optuna TPE over ``SPACES[name]``, starting from the current defaults (enqueued as the
    first trial). Returns the best gains, their score (``score``) and what they were tuned
    on."""
    import optuna

    if name not in SPACES:
        raise ValueError(f"policy={name!r} has no tunable gains; choose one of {sorted(SPACES)}")
    for flag, v, lo, hi in (("--n-trials", n_trials, 1, 10**6), ("--n-plants", n_plants, 1, 10**4),
                            ("--seed", seed, 0, 2**32 - 1)):  # the sampler's seed: numpy's u32
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise ValueError(f"{flag}={v!r} must be a whole number in [{lo}, {hi}]")
    check_range("--episode-s", episode_s, 3.0, 600.0, unit="s")  # rc learns over periods
    sc, plants = training_plants(config, n_plants, seed, episode_s)
    space = SPACES[name]
    default = make_baseline(name, sc)

    def objective(trial: optuna.Trial) -> float:
        gains = {k: trial.suggest_float(k, lo, hi, log=log) for k, (lo, hi, log) in
                 space.items()}
        try:
            return score(name, gains, sc, plants, seed)
        except ValueError as e:  # gains the controller's design refuses (rc: no filter)
            trial.set_user_attr("refused", str(e))
            return FAILED_MM

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize",
                                sampler=optuna.samplers.TPESampler(seed=seed))
    study.enqueue_trial({k: min(max(getattr(default, k), lo), hi)
                         for k, (lo, hi, _) in space.items()})
    with quiet_signalled_trials():  # a Ctrl-C / SIGTERM is one line (the CLI's), no traceback
        study.optimize(objective, n_trials=n_trials)
    return {"policy": name, "gains": study.best_params,
            "mean_position_rmse_mm": study.best_value,
            "default_mean_position_rmse_mm": study.trials[0].value,
            "tuned_on": {"config": str(config), "n_plants": n_plants, "plant_seed": seed,
                         "undamped_twins": UNDAMPED,
                         "episode_s": episode_s,
                         "randomize": every_effect(load_scenario(
                             load_config(config).env_kwargs["scenario"]).randomize).as_dict(),
                         "objective": "mean position RMSE over the plants, last 3 periods "
                                      f"(unstable or terminated: {FAILED_MM:g} mm)",
                         "budget": f"{n_trials} Optuna TPE trials (seed {seed})"}}


def write_gains(results: list[dict[str, Any]] | None, path: str | Path) -> Path:
    """Write :func:`tune`'s ``results`` as a gains file at ``path``
    (``mpa_gym.agents.controllers.gains``: each controller's gains, and under ``tuned_on`` what
    they were tuned on and their score). With ``results`` None, only check that ``path`` can
    be written (``--out``, before any trial)."""
    p = Path(path)
    if results is None:
        if p.is_dir():
            raise ValueError(f"--out {str(path)!r} is a folder; give a file name (FILE.yaml)")
        if not p.parent.is_dir():
            raise ValueError(f"--out {str(path)!r}: folder {str(p.parent)!r} does not exist")
        if not os.access(p.parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
            raise ValueError(f"--out {str(path)!r} is not writable")
        return p
    atomic_write_text(p, gains_yaml(
        {r["policy"]: r["gains"] for r in results},
        {r["policy"]: {**r["tuned_on"], "mean_position_rmse_mm": r["mean_position_rmse_mm"]}
         for r in results}))
    return p
