"""Controller-side state for learned policies: the integral of the tracking error.

A memoryless policy can only answer an unknown static load with a proportional correction, so a
steady sag remains (a PID has its integrator for that). These wrappers append
I = clip(∫(X̂ − X) dt, ±``limit_m_s``) to the observation — controller state, computed from what
the env already observes, never a plant parameter. ``IntegralErrorObservation`` wraps a single
env (and is what an rl-zoo config names as ``env_wrapper``); ``IntegralErrorVectorObservation``
wraps the native vector env (same-step autoreset). Both use ``integral_step``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

OX, OXR = 0, 2  # observation columns of X and X̂


def integral_step(integ: np.ndarray, obs: np.ndarray, dt: float, limit: float) -> np.ndarray:
    """I ← clip(I + (X̂ − X) dt, ±limit) for one observation (…, obs_dim) or a batch."""
    return np.clip(integ + (obs[..., OXR] - obs[..., OX]) * dt, -limit, limit)


def _augmented_space(space: spaces.Box, limit: float) -> spaces.Box:
    return spaces.Box(np.append(space.low, -limit).astype(np.float32),
                      np.append(space.high, limit).astype(np.float32), dtype=np.float32)


class IntegralErrorObservation(gym.Wrapper):
    """Single env: observation + [∫(X̂ − X) dt] (m s), reset to 0 with each episode."""

    def __init__(self, env: gym.Env, limit_m_s: float = 0.02) -> None:
        super().__init__(env)
        if not limit_m_s > 0:
            raise ValueError(f"limit_m_s={limit_m_s!r} must be > 0 m s")
        self.limit = float(limit_m_s)
        self.dt = float(env.unwrapped.cfg.dt_s)
        self.observation_space = _augmented_space(env.observation_space, self.limit)
        self.integ = 0.0

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.integ = 0.0
        return np.append(obs, self.integ).astype(np.float32), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, r, te, tr, info = self.env.step(action)
        self.integ = float(integral_step(np.float64(self.integ), obs, self.dt, self.limit))
        return np.append(obs, self.integ).astype(np.float32), r, te, tr, info


class IntegralErrorVectorObservation(VectorWrapper):
    """Native vector env (same-step autoreset): observation + [∫(X̂ − X) dt] per sub-env."""

    def __init__(self, env: VectorEnv, limit_m_s: float = 0.02) -> None:
        super().__init__(env)
        self.limit = float(limit_m_s)
        self.dt = float(env.unwrapped.cfg.dt_s)
        self.single_observation_space = _augmented_space(env.single_observation_space,
                                                         self.limit)
        self.observation_space = batch_space(self.single_observation_space, env.num_envs)
        self.integ = np.zeros(env.num_envs)

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.integ[:] = 0.0
        return self._augment(obs), info

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        obs, r, te, tr, info = self.env.step(actions)
        done = te | tr
        if done.any():  # the finished episodes' integral goes with their final observation
            final = info["final_obs"].copy()
            for i in np.flatnonzero(done):
                last = integral_step(self.integ[i], final[i], self.dt, self.limit)
                final[i] = np.append(final[i], last).astype(np.float32)
            info["final_obs"] = final
        self.integ = integral_step(self.integ, obs, self.dt, self.limit)
        self.integ[done] = 0.0  # the returned obs of a finished env starts a new episode
        return self._augment(obs), r, te, tr, info

    def _augment(self, obs: np.ndarray) -> np.ndarray:
        return np.concatenate([obs, self.integ[:, None]], axis=1).astype(np.float32)
