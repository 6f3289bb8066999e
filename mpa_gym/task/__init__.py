"""Layer 3: what the simulated and the hardware envs share (the step contract, timing and
limits, reward, safety, plans)."""

from mpa_gym.task.config import TaskConfig
from mpa_gym.task.contract import (
    INFO_KEYS,
    OBS_COLUMNS,
    OBS_NAMES,
    RESIDUAL_OBS_NAMES,
    REWARD_KEYS,
    SAFETY_CLIPPED,
    SAFETY_SLEW,
    action_space,
    check_action,
    obs_index,
    obs_names,
    observation_space,
    step_info,
)
from mpa_gym.task.plan import TaskPlan, make_plan, stiffness_design

__all__ = [
    "INFO_KEYS",
    "OBS_COLUMNS",
    "OBS_NAMES",
    "RESIDUAL_OBS_NAMES",
    "REWARD_KEYS",
    "SAFETY_CLIPPED",
    "SAFETY_SLEW",
    "TaskConfig",
    "TaskPlan",
    "action_space",
    "check_action",
    "make_plan",
    "obs_index",
    "obs_names",
    "observation_space",
    "step_info",
    "stiffness_design",
]
