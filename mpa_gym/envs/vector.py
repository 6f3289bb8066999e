"""Native vector environments: N legs stepped by one compiled kernel over numpy arrays.

Sub-env i behaves exactly as the single env reset with seed ``seed + i`` (Gymnasium's seeding
convention for vector envs): same plan, same kernel, its own random generator for domain
randomisation and sensor noise. Episodes reset in the same step (``AutoresetMode.SAME_STEP``):
a finished sub-env returns its first new observation, and the last one is in
``info["final_obs"]`` (an object array) with its info in ``info["final_info"]`` (a dict of
arrays), each with its ``_`` mask, as ``SyncVectorEnv`` does it; the SB3 adapter turns these into
SB3's ``terminal_observation``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from mpa_gym.envs.leg_env import make_plans, task_config
from mpa_gym.envs.sim import SimEngine
from mpa_gym.model.params import DEFAULT_PARAMS, Params
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.contract import O_R, O_TERM, action_space, check_action, observation_space


class MPALegVectorEnv(VectorEnv):
    """``num_envs`` copies of ``MPALeg-v0`` (same arguments), stepped together.

    ``step`` takes actions of shape (num_envs, 2) and returns observations (num_envs, obs_dim)
    float32, rewards, terminations and truncations of shape (num_envs,), and ``info`` as a dict
    of arrays with the single env's keys (``pressure_cmd_bar`` and ``pressure_bar`` of shape
    (num_envs, 2)).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": [], "autoreset_mode":
                                          AutoresetMode.SAME_STEP}
    residual = False

    def __init__(
        self,
        num_envs: int = 1,
        scenario: Any = "nominal",
        stiffness: Any = None,
        task: TaskConfig | dict[str, Any] | None = None,
        render_mode: str | None = None,
        params: Params = DEFAULT_PARAMS,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int | np.integer) or \
                not 1 <= num_envs <= 1_000_000:
            raise ValueError(f"num_envs={num_envs!r} must be a whole number in [1, 1000000]")
        if render_mode is not None:
            raise ValueError(f"render_mode={render_mode!r}: the vector env does not render; "
                             "render a single env (gymnasium.make) instead")
        self.num_envs = int(num_envs)
        self.cfg = task_config(task)
        self.engine = SimEngine(make_plans(scenario, stiffness, self.cfg, params),
                                self.num_envs, self.residual, params)
        self.plan = self.engine.plan  # the first design (all share the episode length)
        self.single_action_space = action_space()
        self.single_observation_space = observation_space(self.cfg, self.residual)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.render_mode = None
        self._rngs: list[np.random.Generator] = []
        self._all = np.arange(self.num_envs)

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every sub-env; ``seed`` an int (sub-env i gets seed + i) or a list."""
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif isinstance(seed, int | np.integer):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed has {len(seeds)} entries; expected num_envs="
                                 f"{self.num_envs}")
        if seed is not None or not self._rngs:
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        self.engine.reset_rows(self._all, self._rngs, options)
        return self.engine.obs.astype(np.float32), self._infos()

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        if not self._rngs:
            raise RuntimeError("step() called before reset()")
        a = check_action(actions, self.num_envs)
        e = self.engine
        e.step(a, self._rngs)
        terminated = e.out[:, O_TERM] > 0.0
        truncated = e.truncated & ~terminated
        rewards = e.out[:, O_R].copy()
        done = terminated | truncated
        if not done.any():
            return e.obs.astype(np.float32), rewards, terminated, truncated, self._infos()
        # same-step autoreset (as SyncVectorEnv does it): the finished legs' last observation and
        # info go to final_obs / final_info, the returned ones are their new episode's first
        final_info = self._infos()
        final_info.update({f"_{k}": done for k in list(final_info)})
        final_obs = np.full(self.num_envs, None, dtype=object)
        rows = np.flatnonzero(done)
        last = e.obs[rows].astype(np.float32)
        for r, i in enumerate(rows):
            final_obs[i] = last[r]
        e.reset_rows(rows, self._rngs)
        infos = self._infos()
        infos.update(final_obs=final_obs, _final_obs=done, final_info=final_info,
                     _final_info=done)
        return e.obs.astype(np.float32), rewards, terminated, truncated, infos

    def _infos(self) -> dict[str, Any]:
        return self.engine.info()


class MPALegResidualVectorEnv(MPALegVectorEnv):
    """``num_envs`` copies of ``MPALegResidual-v0`` (same arguments), stepped together."""

    residual = True
