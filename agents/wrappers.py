"""Controller-side features for learned policies: the tracking error, its rate and integral.

The env observes X and X̂ separately; a network has to subtract two numbers that each vary by
centimetres to see a sub-millimetre error, and a memoryless policy can only answer an unknown
static load with a proportional correction, so a steady sag remains (a PID has its integrator for
that). These wrappers append e = X̂ − X, ė = V̂ − V and I = clip(∫e dt, ±``limit_m_s``) to the
observation — what a PID computes from the same measurements, never a plant parameter.
``TrackingErrorObservation`` wraps a single env (and is what an rl-zoo config names as
``env_wrapper``); ``TrackingErrorVectorObservation`` wraps the native vector env (same-step
autoreset). Both use ``integral_step`` and ``features``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

OX, OV, OXR, OVR = 0, 1, 2, 3  # observation columns of X, V, X̂, V̂
N_FEATURES = 3


def integral_step(integ: np.ndarray, obs: np.ndarray, dt: float, limit: float) -> np.ndarray:
    """I ← clip(I + (X̂ − X) dt, ±limit) for one observation (…, obs_dim) or a batch."""
    return np.clip(integ + (obs[..., OXR] - obs[..., OX]) * dt, -limit, limit)


def features(obs: np.ndarray, integ: np.ndarray) -> np.ndarray:
    """obs (n, d) + integral (n,) → (n, d + 3): [obs, X̂ − X, V̂ − V, I] as float32."""
    return np.concatenate([obs, (obs[:, OXR] - obs[:, OX])[:, None],
                           (obs[:, OVR] - obs[:, OV])[:, None], np.reshape(integ, (-1, 1))],
                          axis=1).astype(np.float32)


def _augmented_space(space: spaces.Box, limit: float) -> spaces.Box:
    extra_lo = np.array([-1.0, -20.0, -limit])
    extra_hi = np.array([1.0, 20.0, limit])
    return spaces.Box(np.concatenate([space.low, extra_lo]).astype(np.float32),
                      np.concatenate([space.high, extra_hi]).astype(np.float32),
                      dtype=np.float32)


class TrackingErrorObservation(gym.Wrapper):
    """Single env: observation + [X̂ − X, V̂ − V, ∫(X̂ − X) dt]; the integral restarts at 0."""

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
        return features(obs[None], self.integ)[0], info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, r, te, tr, info = self.env.step(action)
        self.integ = float(integral_step(np.float64(self.integ), obs, self.dt, self.limit))
        return features(obs[None], self.integ)[0], r, te, tr, info


class TrackingErrorVectorObservation(VectorWrapper):
    """Native vector env (same-step autoreset): the features of ``TrackingErrorObservation``."""

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
                final[i] = features(final[i][None], last)[0]
            info["final_obs"] = final
        self.integ = integral_step(self.integ, obs, self.dt, self.limit)
        self.integ[done] = 0.0  # the returned obs of a finished env starts a new episode
        return self._augment(obs), r, te, tr, info

    def _augment(self, obs: np.ndarray) -> np.ndarray:
        return features(obs, self.integ)
