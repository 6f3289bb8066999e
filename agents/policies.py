"""Learned policies behind the same ``predict`` interface as the baselines, and loading any
controller by name (``ff``, ``pid``, ``mbfb``) or run folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agents.baselines import BASELINES, Policy, make_baseline
from agents.wrappers import features, integral_step


class LearnedPolicy:
    """An SB3 model with its observation normaliser and integral-error state.

    ``predict`` takes the env's own observation (as the baselines do): it appends the integral
    of the tracking error when the model was trained with ``TrackingErrorObservation``,
    normalises with the training statistics and returns the deterministic action.
    """

    def __init__(self, model: Any, normalizer: Any = None, integral_limit: float | None = None,
                 dt: float = 0.01) -> None:
        self.model, self.normalizer = model, normalizer
        self.integral_limit, self.dt = integral_limit, dt

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation, dtype=np.float32)
        single = obs.ndim == 1
        obs = obs.reshape(1, -1) if single else obs
        if self.integral_limit is not None:
            integ = np.zeros(obs.shape[0]) if state is None else np.array(state, dtype=float)
            start = (np.ones(obs.shape[0], dtype=bool) if state is None else
                     np.zeros(obs.shape[0], dtype=bool))
            if episode_start is not None:
                start |= np.asarray(episode_start, dtype=bool).reshape(-1)
            integ = np.where(start, 0.0, integral_step(integ, obs, self.dt, self.integral_limit))
            obs = features(obs, integ)
            state = integ
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        action, _ = self.model.predict(obs, deterministic=deterministic)
        return (action[0] if single else action), state


def load_run(run_dir: str | Path, which: str = "final") -> tuple[LearnedPolicy, Any]:
    """The policy of a training run folder (``final`` model or the ``best`` one) and its config."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from agents.config import load_config

    # one small MLP per step: a thread pool only adds latency (and competes with the rig's loop)
    torch.set_num_threads(1)

    run = Path(run_dir)
    cfg = load_config(run / "config.yaml")
    model_path = run / ("model.zip" if which == "final" else "best" / Path("best_model.zip"))
    if not model_path.is_file():
        raise FileNotFoundError(f"{model_path} not found: is {run} a finished run folder?")
    model = PPO.load(model_path, device="cpu")
    norm = None
    norm_path = run / ("vecnormalize.pkl" if which == "final" else "best/vecnormalize.pkl")
    if cfg.normalize:
        if not norm_path.is_file():
            raise FileNotFoundError(f"{norm_path} not found (the run normalises observations)")
        norm = VecNormalize.load(str(norm_path), _DummyVec(model))
        norm.training = False
        norm.norm_reward = False
    task = cfg.env_kwargs.get("task") or {}
    dt = float(task.get("dt_s", 0.01))
    return LearnedPolicy(model, norm, 0.02 if cfg.integral_observation else None, dt), cfg


class _DummyVec:
    """Just enough of a VecEnv for VecNormalize.load (spaces and num_envs)."""

    def __init__(self, model: Any) -> None:
        self.observation_space = model.observation_space
        self.action_space = model.action_space
        self.num_envs = 1
        self.render_mode = None


def load_policy(spec: str, env_kwargs: dict[str, Any] | None = None) -> tuple[Policy, str, Any]:
    """(policy, env id, run config or None) for ``ff`` / ``pid`` / ``mbfb`` or a run folder.

    Baselines are built for the env made with ``env_kwargs`` (scenario, stiffness, task).
    """
    if spec in BASELINES:
        kw = env_kwargs or {}
        return (make_baseline(spec, kw.get("scenario", "nominal"), kw.get("stiffness"),
                              kw.get("task")), "MPALegResidual-v0", None)
    if Path(spec).is_dir():
        policy, cfg = load_run(spec)
        return policy, cfg.env_id, cfg
    raise ValueError(f"policy={spec!r} is neither a baseline {sorted(BASELINES)} nor a run "
                     "folder")
