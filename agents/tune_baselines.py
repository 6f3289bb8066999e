"""Tuning the classical baselines on the PPO residual's training plants (Optuna, TPE).

A fair comparison holds the learned residual against controllers tuned on the same plants it
trained on. ``tune`` draws ``n_plants`` plants from the training scenario of a PPO config
(its ``randomize`` ranges, with a fixed seed), runs each candidate's gains on all of them as
one batch of the native vector env, and minimises the mean position RMSE over the plants, each
over the last three periods of a ``episode_s`` episode (a terminated leg counts as
``FAILED_MM``). The mean, not the worst case: with dead times up to 30 ms the worst training
plant stayed at 9.4 mm (pid) and 23.6 mm (mbfb) for the best of 80 trials, and a worst-case
objective tunes for that one plant only. The search space of each controller is ``SPACES``;
the budget is ``n_trials`` Optuna trials with a seeded TPE sampler, so a run is reproducible.

``mpa-gym tune-baselines`` runs it and prints the gains and what they were tuned on; the
defaults of ``PIDResidual`` / ``StiffnessFeedback`` and ``baselines.TUNED_ON`` come from it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from agents.baselines import make_baseline
from agents.config import load_config
from agents.robustness import cell_metrics, run_batch
from mpa_gym.analysis.scenario import Scenario, load_scenario

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "ppo_residual_robust.yaml"
FAILED_MM = 100.0  # [mm] the score of a plant on which the loop terminated

# controller -> field -> (low, high, log scale)
SPACES: dict[str, dict[str, tuple[float, float, bool]]] = {
    "pid": {"kp_bar_per_m": (5.0, 300.0, True), "ki_bar_per_m_s": (10.0, 1e4, True),
            "kd_bar_s_per_m": (0.1, 40.0, True), "tf_s": (0.0, 0.05, False)},
    "mbfb": {"kp_N_per_m": (100.0, 1e4, True), "ki_N_per_m_s": (10.0, 1e4, True),
             "kd_N_s_per_m": (5.0, 400.0, True), "tf_s": (0.0, 0.05, False)},
}


def training_plants(config: str | Path = DEFAULT_CONFIG, n_plants: int = 16, seed: int = 0,
                    episode_s: float = 15.0) -> tuple[Scenario, list[dict[str, float]]]:
    """The config's training scenario (its duration set to ``episode_s``, its randomisation
    taken out) and ``n_plants`` draws from its ``randomize`` ranges."""
    sc = load_scenario(load_config(config).env_kwargs["scenario"])
    rng = np.random.default_rng(seed)
    plants = [sc.randomize.sample(rng) for _ in range(n_plants)]
    base = dataclasses.replace(sc, duration_s=episode_s,
                               randomize=dataclasses.replace(sc.randomize, ranges=()))
    return base, plants


def score(name: str, gains: dict[str, float], sc: Scenario, plants: list[dict[str, float]],
          seed: int = 0) -> float:
    """[mm] mean position RMSE of baseline ``name`` with ``gains`` over ``plants``."""
    policy = dataclasses.replace(make_baseline(name, sc), **gains)
    run = run_batch(policy, sc, plants, seed)
    m = cell_metrics(run, sc.reference.period, float(run["t"][0]))
    return float(np.mean([FAILED_MM if c["terminated"] else c["position_rmse_mm"] for c in m]))


def tune(name: str, config: str | Path = DEFAULT_CONFIG, n_trials: int = 80,
         n_plants: int = 16, seed: int = 0, episode_s: float = 15.0) -> dict[str, Any]:
    """Optuna TPE over ``SPACES[name]``, starting from the current defaults (enqueued as the
    first trial). Returns the best gains, their score (``score``) and what they were tuned
    on."""
    import optuna

    if name not in SPACES:
        raise ValueError(f"policy={name!r} has no tunable gains; choose one of {sorted(SPACES)}")
    for key, v, lo in (("n_trials", n_trials, 1), ("n_plants", n_plants, 1)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise ValueError(f"{key}={v!r} must be a whole number >= {lo}")
    sc, plants = training_plants(config, n_plants, seed, episode_s)
    space = SPACES[name]
    default = make_baseline(name, sc)

    def objective(trial: optuna.Trial) -> float:
        gains = {k: trial.suggest_float(k, lo, hi, log=log) for k, (lo, hi, log) in
                 space.items()}
        return score(name, gains, sc, plants, seed)

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize",
                                sampler=optuna.samplers.TPESampler(seed=seed))
    study.enqueue_trial({k: min(max(getattr(default, k), lo), hi)
                         for k, (lo, hi, _) in space.items()})
    study.optimize(objective, n_trials=n_trials)
    return {"policy": name, "gains": study.best_params,
            "mean_position_rmse_mm": study.best_value,
            "default_mean_position_rmse_mm": study.trials[0].value,
            "tuned_on": {"config": str(config), "n_plants": n_plants, "plant_seed": seed,
                         "episode_s": episode_s, "randomize": {
                             k: [lo, hi] for k, lo, hi in
                             load_scenario(load_config(config).env_kwargs["scenario"])
                             .randomize.ranges},
                         "objective": "mean position RMSE over the plants, last 3 periods "
                                      f"(terminated: {FAILED_MM:g} mm)",
                         "budget": f"{n_trials} Optuna TPE trials (seed {seed})"}}
