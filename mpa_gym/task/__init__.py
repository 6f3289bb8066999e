"""Layer 3: what the simulated and the hardware envs share (spaces, reward, safety, plans)."""

from mpa_gym.task.config import (
    INFO_KEYS,
    OBS_NAMES,
    RESIDUAL_OBS_NAMES,
    REWARD_KEYS,
    TaskConfig,
    action_space,
    check_action,
    observation_space,
)
from mpa_gym.task.plan import TaskPlan, make_plan, stiffness_design

__all__ = [
    "INFO_KEYS",
    "OBS_NAMES",
    "RESIDUAL_OBS_NAMES",
    "REWARD_KEYS",
    "TaskConfig",
    "TaskPlan",
    "action_space",
    "check_action",
    "make_plan",
    "observation_space",
    "stiffness_design",
]
