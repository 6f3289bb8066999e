"""Stable-Baselines3 adapter for the native vector envs (SB3 has no gymnasium.vector support).

``SB3VecEnv(gymnasium.make_vec("MPALegResidual-v0", num_envs=8, vectorization_mode=
"vector_entry_point"))`` is an SB3 ``VecEnv``: it turns the vector env's same-step autoreset into
SB3's conventions (``terminal_observation`` and ``TimeLimit.truncated`` in each env's info), and
its dict-of-arrays info into a list of per-env dicts.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn


class SB3VecEnv(VecEnv):
    """Wrap a Gymnasium ``VectorEnv`` with same-step autoreset as an SB3 ``VecEnv``."""

    def __init__(self, venv: VectorEnv) -> None:
        mode = venv.metadata.get("autoreset_mode")
        if mode != AutoresetMode.SAME_STEP:
            raise ValueError(f"SB3VecEnv needs autoreset_mode=SAME_STEP, got {mode!r}")
        self.venv = venv
        self.render_mode = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self._actions: np.ndarray | None = None

    def reset(self) -> np.ndarray:
        seeds = self._seeds
        seed: Any = None if all(s is None for s in seeds) else seeds
        opts = self._options[0] if self._options and self._options[0] else None
        obs, info = self.venv.reset(seed=seed, options=opts)
        self.reset_infos = self._split(info)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None, "step_async() first"
        obs, rew, term, trunc, info = self.venv.step(self._actions)
        infos = self._split(info)
        dones = term | trunc
        for i in np.flatnonzero(dones):
            infos[i]["terminal_observation"] = info["final_obs"][i]
            infos[i]["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
        return obs, rew.astype(np.float32), dones, infos

    def _split(self, info: dict[str, Any]) -> list[dict[str, Any]]:
        keys = [k for k in info if not k.startswith("_") and k not in ("final_obs", "final_info")]
        # after an autoreset the finished envs report their last step's info, not the reset's
        final = info.get("final_info")
        if final is not None:
            info = {k: np.where(info["_final_info"].reshape(-1, *[1] * (np.ndim(info[k]) - 1)),
                                final[k], info[k]) for k in keys}
        return [{k: info[k][i] for k in keys} for i in range(self.num_envs)]

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.venv, attr_name)] * len(self._get_indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result] * len(self._get_indices(indices))

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None
                       ) -> list[bool]:
        return [False] * len(self._get_indices(indices))

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None] * self.num_envs


def make_sb3_vec_env(env_id: str = "MPALegResidual-v0", n_envs: int = 8, seed: int | None = None,
                     **env_kwargs: Any) -> SB3VecEnv:
    """The native vector env of ``env_id`` as an SB3 VecEnv (seeded if ``seed`` is given)."""
    venv = gym.make_vec(env_id, num_envs=n_envs, vectorization_mode="vector_entry_point",
                        **env_kwargs)
    vec = SB3VecEnv(venv)
    if seed is not None:
        vec.seed(seed)
    return vec
