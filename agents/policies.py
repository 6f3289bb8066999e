"""Learned policies behind the same ``predict`` interface as the baselines, and loading any
controller by name (``ff``, ``pid``, ``mbfb``) or run folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agents.baselines import BASELINES, Policy, make_baseline
from agents.config import TrainConfig
from agents.wrappers import (
    FeatureSpec,
    check_action_kwargs,
    force_stiffness_to_residual,
    integral_step,
)
from mpa_gym.task.config import TaskConfig


class LearnedPolicy:
    """An SB3 model with its observation normaliser, feature state and action coordinates.

    ``predict`` takes the env's own observation (as the baselines do): it appends the tracking
    error features when the model was trained with ``TrackingErrorObservation`` (``features``;
    their integrals and the previous action are the returned state), normalises with the
    training statistics, and returns the deterministic action — mapped from force–stiffness
    coordinates to the env's residual action when the model was trained with
    ``ForceStiffnessAction`` (``force_stiffness`` = (force_N, stiffness_rel, residual scale)).
    """

    def __init__(self, model: Any, normalizer: Any = None, features: FeatureSpec | None = None,
                 dt: float = 0.01, force_stiffness: tuple[float, float, float] | None = None
                 ) -> None:
        self.model, self.normalizer, self.features, self.dt = model, normalizer, features, dt
        self.force_stiffness = force_stiffness

    @classmethod
    def from_config(cls, model: Any, normalizer: Any, cfg: TrainConfig) -> LearnedPolicy:
        """The policy for a model trained with ``cfg``'s wrappers and task."""
        task = cfg.env_kwargs.get("task") or {}
        ow, aw = cfg.observation_wrapper, cfg.action_wrapper
        fs = None
        if aw is not None:
            scale = TaskConfig.from_kwargs(task).residual_scale_bar
            fs = (*check_action_kwargs(**aw)[:2], scale)
        return cls(model, normalizer, FeatureSpec(**ow) if ow is not None else None,
                   float(task.get("dt_s", 0.01)), fs)

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        """Actions for one observation or a batch; ``state`` (returned, passed back on the next
        call) holds each row's integrals and previous action, reset where ``episode_start``."""
        raw = np.asarray(observation, dtype=np.float32)
        single = raw.ndim == 1
        raw = raw.reshape(1, -1) if single else raw
        obs, spec = raw, self.features
        if spec is not None:
            n, m = raw.shape[0], spec.n_integrals
            st = np.zeros((n, m + 2)) if state is None else np.array(state, float).reshape(n, -1)
            if state is not None:
                st[:, :m] = integral_step(st[:, :m], raw, self.dt, spec.limit_m_s)
            if episode_start is not None:
                st[np.asarray(episode_start, dtype=bool).reshape(-1)] = 0.0
            obs, state = spec.features(raw, st[:, :m], st[:, m:]), st
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        action, _ = self.model.predict(obs, deterministic=deterministic)
        if self.force_stiffness is not None:
            action = force_stiffness_to_residual(action, raw, *self.force_stiffness)
        if spec is not None:
            state[:, spec.n_integrals:] = np.clip(action, -1.0, 1.0)  # what the env applies
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
    return LearnedPolicy.from_config(model, norm, cfg), cfg


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
