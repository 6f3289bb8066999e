"""Single-leg Gymnasium environments: ``MPALeg-v0`` and ``MPALegResidual-v0``."""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from mpa_gym.envs.rendering import LegRenderer
from mpa_gym.envs.sim import SimEngine
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.contract import (
    O_R,
    O_TERM,
    ST_PE,
    ST_PF,
    ST_X,
    action_space,
    check_action,
    obs_table,
    observation_space,
)
from mpa_gym.task.plan import TaskPlan, make_plan


def task_config(task: TaskConfig | dict[str, Any] | None) -> TaskConfig:
    return task if isinstance(task, TaskConfig) else TaskConfig.from_kwargs(task)


def make_plans(scenario: Any, stiffness: Any, cfg: TaskConfig, params: Params
               ) -> list[TaskPlan]:
    """One plan per stiffness design; a list of designs gives one drawn per episode."""
    designs = stiffness if isinstance(stiffness, list) else [stiffness]
    if not designs:
        raise ValueError("stiffness=[] must name at least one design")
    return [make_plan(scenario, s, cfg, params) for s in designs]


class MPALegEnv(gym.Env[np.ndarray, np.ndarray]):
    """
    ## Description

    The one-degree-of-freedom leg of Sugimoto, Naniwa & Osuka (Fig. 2): a hip of mass m slides
    vertically, the knee is bent by an extensor McKibben muscle wrapped on a pulley and a flexor
    across the joint. The agent sets both gauge pressures every control period (10 ms) and should
    make the hip height X follow the reference X̂(t) = X̂0 + Â sin(2πt/T) (Eq. 21). The plant is
    Eq. (15) with the MPA model of Eq. (2) and the Appendix, integrated by RK4 over each period
    (within 1e-6 m of an adaptive reference over 30 s), plus the scenario's plant realism.

    ## Action Space

    `Box(-1, 1, (2,), float32)`, extensor first. Out-of-range values are clipped to [−1, 1]
    (as SB3 clips its policies' actions); NaN, ±inf and wrong shapes raise `ValueError`.

    | Num | Action | Pressure command |
    |-----|--------|------------------|
    | 0 | extensor | P'_e = (a₀ + 1)/2 · p_max |
    | 1 | flexor | P'_f = (a₁ + 1)/2 · p_max |

    The safety layer then limits the change per period (`slew_bar_per_s`) and clips to
    [0, p_max] (`p_max_bar`, 7 bar); the regulator may quantise, delay and lag the command.

    ## Observation Space

    `Box(float32, (8,))`, measured through the rig's sensors (encoder quantum and noise); the
    layout is `mpa_gym.task.contract.OBS_COLUMNS`:

    <observation table>

    Hidden plant parameters (mass, load, γ, C1, C2, bladder thickness, regulator lag) are never
    observed.

    ## Rewards

    r = (1 − w_k) / (1 + (e_x/σ_x)²) + w_k / (1 + ((k − k̂)/(k̂ σ_k))²)
        − w_u (a₀² + a₁²)

    with e_x = X − X̂, σ_x = 5 mm, σ_k = 0.1, w_u = 0.01; here w_k = 0 (MPALegResidual-v0 uses
    0.3), so a perfect tracker earns 1 per step; the heavy-tailed kernels keep a gradient toward
    the target even for errors of several σ. k is the plant's true joint stiffness −∂F/∂X
    (Eq. 23) at the applied pressures, k̂ the design's. Each term is in `info` (`reward_position`,
    `reward_stiffness`, `reward_effort`), and r is their sum on every step. A step that
    terminates the episode earns r = 0 with all three terms 0: its state is out of bounds (or
    out of the model's domain), not one to be rewarded for tracking.

    ## Starting State

    The scenario's initial state (on the reference by default) plus any `randomize` offsets; the
    pressures start at the feedforward design's values at t = 0.

    ## Episode End

    - Termination: X leaves [`x_min_m`, `x_max_m`] = [0.70, 0.86] m (or the model's domain);
      that step's reward is 0 (Rewards). The reward, its terms and termination are composed by
      `mpa_gym.task.kernels.finish_step`, as on the rig (`MPALegHardware-v0`).
    - Truncation: after `episode_s` (default: the scenario's `duration_s`, 30 s = 3000 steps).

    ## Arguments

    - `scenario`: a name in `configs/scenarios` (`nominal`, `load_1kg`, …), a YAML path or a dict
      (schema: docs/design.md#scenarios; `plant` sets the realism, `randomize` the
      per-episode ranges).
    - `stiffness`: the design behind k̂ and (residual env) the feedforward: `None` (the
      scenario's), `"kmax"`, `"kmin"`, a constant in N/m, or `{"t_s": [...], "k_N_per_m": [...]}`;
      a list of these draws one design per episode (e.g. `[null, kmax, kmin]` for training).
    - `task`: a `TaskConfig` or dict (dt_s, episode_s, p_max_bar, slew_bar_per_s, bounds, reward).
    - `render_mode`: `"rgb_array"` or `"human"`; one frame per control period, and
      `metadata["render_fps"]` is the control rate 1 / `task.dt_s`, so videos
      (`gymnasium.wrappers.RecordVideo`) and the window play at real time.

    `reset(options={"plant": {...}, "initial_state": {"x_m": .., "v_mps": ..}})` fixes any plant
    field (e.g. `{"mass_kg": 4.2}`) or the start for that episode. `options={"homing": True}`
    (or a dict of `HomingConfig` fields) starts the episode as the rig's reset does: both MPAs
    vented, the leg at its vented rest (or at `initial_state`), then closed-loop homing to the
    start (`mpa_gym.task.homing`); `info["homing_s"]` says how long it took.

    `info` on every step: `x_m`, `x_ref_m`, `k_N_per_m`, `k_ref_N_per_m`, `pressure_cmd_bar` and
    `pressure_bar` (extensor, flexor), the reward terms, `safety` (bit 1: clipped, bit 2: slew
    limited) and `t_s`.

    ## Version History

    - v0: initial version.
    """

    # one frame per control period: ``render_fps`` is the control rate, 1 / ``task.dt_s`` (each
    # instance sets its own), so a video written with it (``gymnasium.wrappers.RecordVideo``) or
    # the human window plays at real time
    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["human", "rgb_array"],
                                          "render_fps": 1.0 / TaskConfig.dt_s}
    residual = False

    def __init__(
        self,
        scenario: Any = "nominal",
        stiffness: Any = None,
        task: TaskConfig | dict[str, Any] | None = None,
        render_mode: str | None = None,
        params: Params = DEFAULT_PARAMS,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r} must be one of "
                             f"{self.metadata['render_modes']} or None")
        self.cfg = task_config(task)
        self.metadata = {**self.metadata, "render_fps": 1.0 / self.cfg.dt_s}
        self.engine = SimEngine(make_plans(scenario, stiffness, self.cfg, params), 1,
                                self.residual, params)
        self.action_space = action_space()
        self.observation_space = observation_space(self.cfg, self.residual)
        self.render_mode = render_mode
        self._renderer: Any = None
        self._done = True
        self._rngs: list[np.random.Generator] = []

    @property
    def plan(self) -> TaskPlan:
        """The plan (reference, feedforward, disturbances) of the current episode."""
        return self.engine.plan_of(0)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._rngs = [self.np_random]
        self.engine.reset_rows([0], self._rngs, options)
        self._done = False
        if self.render_mode == "human":
            self.render()
        info = self.engine.info(0)
        if options and options.get("homing"):
            info["homing_s"] = float(self.engine.homing_s[0])
        return self.engine.obs[0].astype(np.float32), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._done:
            raise RuntimeError("step() called on a finished (or never started) episode: call "
                               "reset() first")
        a = check_action(action)
        e = self.engine
        e.step(a.reshape(1, 2), self._rngs)
        out = e.out[0].tolist()
        terminated = out[O_TERM] > 0.0
        truncated = not terminated and e.truncated_of(0)
        self._done = terminated or truncated
        if self.render_mode == "human":
            self.render()
        return e.obs[0].astype(np.float32), out[O_R], terminated, truncated, e.info(0)

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode="
                            "'rgb_array' or 'human' to gymnasium.make")
            return None

        if self._renderer is None:
            self._renderer = LegRenderer(self.engine.params, self.cfg.p_max_bar,
                                         human=self.render_mode == "human",
                                         fps=self.metadata["render_fps"])
        e = self.engine
        j = int(e.idx[0] - e.start[0])
        frame = self._renderer.draw(float(e.state[0, ST_X]), float(self.plan.x_ref[j]),
                                    e.state[0, ST_PE:ST_PF + 1] / BAR, float(self.plan.t[j]))
        return frame if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class MPALegResidualEnv(MPALegEnv):
    """
    ## Description

    `MPALeg-v0` with the paper's analytic feedforward as the expert: every control period the
    feedforward of Eq. (16) (or the Eq. 25 design for the stiffness target k̂) is applied and the
    action is a bounded residual on top of it. A zero action applies the feedforward exactly.
    The policy's job is to keep both the motion X̂ and the joint stiffness k̂ when the true plant
    differs from the design model (load, mass, γ, C1, C2, bladder, regulator).

    ## Action Space

    `Box(-1, 1, (2,), float32)`: P'_cmd = P'_ff(t + dt/2) + a · `residual_scale_bar` (1 bar),
    extensor first, then the same safety layer (slew limit, clip to [0, p_max]). Out-of-range
    values are clipped to [−1, 1]; NaN, ±inf and wrong shapes raise `ValueError`.

    ## Observation Space

    `Box(float32, (9,))`: the observations of `MPALeg-v0` and the stiffness target:

    <observation table>

    ## Rewards

    As `MPALeg-v0` with w_k = 0.3: r = 0.7 / (1 + (e_x/5 mm)²) + 0.3 / (1 + ((k − k̂)/(0.1 k̂))²)
    − 0.01 |a|², where k is the plant's true stiffness (Eq. 23) at the applied pressures.

    ## Starting State, Episode End, Arguments

    As `MPALeg-v0`. `stiffness` picks k̂ and so the feedforward: `None` (the scenario's inputs,
    whose own k is then k̂), `"kmax"`, `"kmin"`, a constant (N/m) or a profile.

    ## Version History

    - v0: initial version.
    """

    residual = True


# The observation tables of the docstrings are the step contract's (task.contract).
for _cls in (MPALegEnv, MPALegResidualEnv):
    _cls.__doc__ = (_cls.__doc__ or "").replace(
        "<observation table>", obs_table(_cls.residual).replace("\n", "\n    "))
