"""Training wrappers of a learned policy's controller front-end
(``mpa_gym.agents.learned.frontend``: the tracking-error features, the force–stiffness action
coordinates and the stiffness estimator, their definitions and their reasons).

``TrackingErrorObservation`` appends the features to the env's observation (or gives them
alone: ``errors_only``); ``ForceStiffnessAction`` takes actions (a_F, a_k) in force–stiffness
coordinates and gives the residual env their pressure correction, with the stiffness
estimator's a_k if ``stiffness_adapt_s`` (regressed on X̂ and V̂ with
``stiffness_adapt_velocity``; a share of k̂ with ``stiffness_adapt_relative``).
``rate_penalty`` w subtracts w·|a_t − a_{t−1}|² from the reward (a_{−1} = 0 each episode), the
action-rate term of legged-robot RL, against high-frequency corrections that a lagging
regulator turns into a limit cycle; it shapes training only, so a trained policy runs without
it.

Single-env wrappers are what an rl-zoo config names as ``env_wrapper``; the ``…Vector…`` ones wrap
the native vector env (same-step autoreset). All of them call the front-end's row kernels on
``STATE`` records, one per env, as the loaded and the deployed policy do, so they agree.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

from mpa_gym.agents.learned.frontend import (
    ActionSpec,
    FeatureSpec,
    Frontend,
    adapt_time_constant,
    new_state,
)
from mpa_gym.task.contract import OBS_KREF as OK
from mpa_gym.task.contract import OBS_XREF as OXR
from mpa_gym.task.contract import check_action

# the specs are the wrappers' kwargs; configs name them here (mpa_gym.agents.learned.config)
__all__ = ["ActionSpec", "FeatureSpec", "ForceStiffnessAction", "ForceStiffnessVectorAction",
           "TrackingErrorObservation", "TrackingErrorVectorObservation", "adapt_time_constant"]


def _plant_delays(env: Any, state: np.ndarray, rows: Any) -> None:
    """The records ``rows`` get their episode's regulator dead time and lag (the delay
    observation), from the simulated plant of each row."""
    plants = env.unwrapped.engine.plants
    for i in rows:
        state[i]["delay_s"] = (plants[i].pressure_dead_time_s, plants[i].pressure_lag_s)


class TrackingErrorObservation(gym.Wrapper):
    """Single env: [observation (left out if errors_only), X̂ − X, V̂ − V, I_0, (I_sh, I_ch)…,
    (a_prev), (fine error), (R_h…, Q_h… if remodulate)] (``frontend.observe_row``); the
    record ``state`` restarts with each episode; ``env_obs`` keeps the env's own last
    observation. kwargs: the fields of ``FeatureSpec``."""

    def __init__(self, env: gym.Env, **kwargs: Any) -> None:
        super().__init__(env)
        self.feature_spec = FeatureSpec(**kwargs)
        self.frontend = Frontend(self.feature_spec, None, env.unwrapped.cfg.dt_s)
        self.observation_space = self.feature_spec.space(env.observation_space)
        self.state = new_state(1)
        self.env_obs: np.ndarray | None = None  # the env's own last observation

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.env_obs = obs
        _plant_delays(self.env, self.state, [0])
        return self.frontend.observe(obs, self.state, True)[0], info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        last = self.env_obs
        if last is None:
            raise RuntimeError("call reset() before step()")
        obs, r, te, tr, info = self.env.step(action)  # the env checks the action
        self.frontend.act(action, last, self.state)  # a_prev: the action as applied
        self.env_obs = obs
        return self.frontend.observe(obs, self.state, False)[0], r, te, tr, info


class TrackingErrorVectorObservation(VectorWrapper):
    """Native vector env (same-step autoreset): the features of ``TrackingErrorObservation``."""

    def __init__(self, env: VectorEnv, **kwargs: Any) -> None:
        super().__init__(env)
        self.feature_spec = FeatureSpec(**kwargs)
        self.frontend = Frontend(self.feature_spec, None, env.unwrapped.cfg.dt_s)
        self.single_observation_space = self.feature_spec.space(env.single_observation_space)
        self.observation_space = batch_space(self.single_observation_space, env.num_envs)
        self.state = new_state(env.num_envs)
        self.env_obs: np.ndarray | None = None  # the env's own last observations

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.env_obs = obs
        _plant_delays(self.env, self.state, range(self.num_envs))
        return self.frontend.observe(obs, self.state, True), info

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        last = self.env_obs
        if last is None:
            raise RuntimeError("call reset() before step()")
        obs, r, te, tr, info = self.env.step(actions)  # the env checks the actions
        self.frontend.act(actions, last, self.state)  # a_prev: the actions as applied
        done = np.logical_or(te, tr)
        if done.any():  # the finished episodes' features go with their final observation
            final = info["final_obs"].copy()  # an object array, None where not done
            for i in np.flatnonzero(done):
                final[i] = self.frontend.observe(final[i], self.state[i:i + 1].copy(),
                                                 False)[0]
            info["final_obs"] = final
            _plant_delays(self.env, self.state, np.flatnonzero(done))
        self.env_obs = obs  # a finished env's obs starts a new episode: its record restarts
        return self.frontend.observe(obs, self.state, done), r, te, tr, info


class _ForceStiffnessMap:
    """What both force–stiffness wrappers share: the front-end with the action map, the last
    observation (X̂ and k̂ for the map), a ``STATE`` record per env (the harmonic force
    correction and the stiffness estimator), the last action (for the rate penalty) and the
    reset that restarts them."""

    env: Any
    _obs: np.ndarray | None
    _prev: np.ndarray

    def _setup(self, env: Any, spec: ActionSpec, n: int) -> None:
        self.action_spec = spec
        self.force_N, self.stiffness_rel, self.rate_penalty = (
            spec.force_N, spec.stiffness_rel, spec.rate_penalty)
        if not getattr(env.unwrapped, "residual", False):
            raise ValueError("ForceStiffnessAction needs MPALegResidual-v0 (residual actions and "
                             "the k̂ observation)")
        self.scale_bar = float(env.unwrapped.cfg.residual_scale_bar)
        # X̂ and k̂ come from the observation beneath when it is the env's own, else from the
        # TrackingErrorObservation directly beneath, which keeps the env's (its features may
        # leave it out: errors_only)
        self._from_features = hasattr(env, "env_obs")
        own, seen = env.unwrapped.observation_space, env.observation_space
        if not self._from_features and seen != own:
            raise ValueError(f"ForceStiffnessAction needs the env's observation (X̂ in column "
                             f"{OXR}, k̂ in column {OK}) but the observation beneath has shape "
                             f"{seen.shape}, not {own.shape}: wrap a TrackingErrorObservation "
                             "directly, or the env itself")
        self.frontend = Frontend(None, spec, env.unwrapped.cfg.dt_s, self.scale_bar)
        self._obs = None
        self._prev = np.zeros((n, 2))
        self.state = new_state(n)  # harmonic corrections and stiffness estimators, one per env

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._obs = self._env_obs(obs)
        self._prev[:] = 0.0
        self.state[:] = new_state(1)
        return obs, info

    def _env_obs(self, obs: Any) -> np.ndarray:
        """The env's own observation, for the map's X̂ and k̂ (``_setup``)."""
        return np.asarray(self.env.env_obs if self._from_features else obs)

    def _rate_cost(self, a: np.ndarray, done: np.ndarray) -> np.ndarray:
        """rate_penalty · |a − a_prev|² per env (a_prev = 0 at an episode's first step); then
        ``a`` becomes the previous action, except where an episode just ended."""
        cost = self.rate_penalty * np.sum((a - self._prev) ** 2, axis=1)
        self._prev[:] = a
        self._prev[done] = 0.0
        return cost

    def _residual(self, a: np.ndarray) -> np.ndarray:
        """(n, 2) validated (a_F, a_k) → the residual action for the last observation."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        return self.frontend.act(a, self._obs, self.state)


class ForceStiffnessAction(_ForceStiffnessMap, gym.Wrapper):
    """Single residual env: actions (a_F, a_k) in force–stiffness coordinates
    (``frontend.act_row``). kwargs: the fields of ``ActionSpec``."""

    def __init__(self, env: gym.Env, **kwargs: Any) -> None:
        gym.Wrapper.__init__(self, env)
        self._setup(env, ActionSpec(**kwargs), 1)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        a = np.clip(check_action(action)[None], -1.0, 1.0)
        residual = self._residual(a)[0]
        obs, r, te, tr, info = self.env.step(residual)
        self._obs = self._env_obs(obs)
        if self.rate_penalty:
            r = float(r - self._rate_cost(a, np.array([te or tr]))[0])
        return obs, r, te, tr, info


class ForceStiffnessVectorAction(_ForceStiffnessMap, VectorWrapper):
    """Native vector env: the action coordinates of ``ForceStiffnessAction``. kwargs: the
    fields of ``ActionSpec``."""

    def __init__(self, env: VectorEnv, **kwargs: Any) -> None:
        VectorWrapper.__init__(self, env)
        self._setup(env, ActionSpec(**kwargs), env.num_envs)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        a = np.clip(check_action(actions, self.num_envs), -1.0, 1.0)
        residual = self._residual(a)
        obs, r, te, tr, info = self.env.step(residual)
        self._obs = self._env_obs(obs)  # same-step autoreset: a new episode's first observation
        done = np.logical_or(te, tr)
        self.state[done] = new_state(1)
        if self.rate_penalty:
            r = r - self._rate_cost(a, done)
        return obs, r, te, tr, info
