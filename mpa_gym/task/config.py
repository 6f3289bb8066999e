"""What sim and hardware share: the task's timing, limits and reward weights (layer 3); the
step contract (spaces, observation and info layout, action check) is ``task.contract``."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from mpa_gym.design.feedforward import P_MAX_DEFAULT
from mpa_gym.model.params import BAR, check_keys, check_range

# [m] the hip heights of the rig's mechanical end stops (lower, upper): the leg cannot leave this
# range, a vented leg rests on the lower one; the termination bounds lie within it
END_STOPS_M = (0.6, 0.87)


@dataclass(frozen=True)
class TaskConfig:
    """Timing, safety limits and reward of the task (one per env; sim and hardware alike)."""

    dt_s: float = 0.01  # [s] control period (100 Hz, the rig's default rate)
    substeps: int = 2  # RK4 steps per control period (sim only): 2 keeps X within 1e-6 m
    episode_s: float | None = None  # [s] episode length; None: the scenario's duration_s
    p_max_bar: float = P_MAX_DEFAULT / BAR  # [bar] regulator limit (7): commands clipped to it
    slew_bar_per_s: float = 50.0  # [bar/s] largest command change per second
    x_min_m: float = 0.70  # [m] the episode terminates below this hip height
    x_max_m: float = 0.86  # [m] … or above this one (inside the MPA length domain)
    residual_scale_bar: float = 1.0  # [bar] residual env: action ±1 = feedforward ± this
    sigma_x_m: float = 0.005  # [m] position error at which the position reward halves
    sigma_k: float = 0.10  # [-] relative stiffness error at which its reward halves
    w_stiffness: float | None = None  # weight of the stiffness term; None: 0.3 residual, 0 direct
    w_effort: float = 0.01  # weight of the action-effort penalty |a|²

    def __post_init__(self) -> None:
        check_range("dt_s", self.dt_s, 1e-4, 0.1, unit="s")
        if isinstance(self.substeps, bool) or not isinstance(self.substeps, int) or \
                not 1 <= self.substeps <= 100:
            raise ValueError(f"substeps={self.substeps!r} must be a whole number in [1, 100]")
        if self.episode_s is not None:
            check_range("episode_s", self.episode_s, self.dt_s, 3600.0, unit="s")
        check_range("p_max_bar", self.p_max_bar, 0.0, 10.0, low_open=True, unit="bar")
        check_range("slew_bar_per_s", self.slew_bar_per_s, 0.0, 1e4, low_open=True, unit="bar/s")
        check_range("x_min_m", self.x_min_m, END_STOPS_M[0], 0.86, unit="m")
        check_range("x_max_m", self.x_max_m, self.x_min_m, END_STOPS_M[1], low_open=True,
                    unit="m")
        check_range("residual_scale_bar", self.residual_scale_bar, 0.0, P_MAX_DEFAULT / BAR,
                    low_open=True, unit="bar")
        check_range("sigma_x_m", self.sigma_x_m, 0.0, 1.0, low_open=True, unit="m")
        check_range("sigma_k", self.sigma_k, 0.0, 10.0, low_open=True)
        if self.w_stiffness is not None:
            check_range("w_stiffness", self.w_stiffness, 0.0, 1.0)
        check_range("w_effort", self.w_effort, 0.0, 10.0)

    @classmethod
    def from_kwargs(cls, kwargs: dict[str, Any] | None) -> TaskConfig:
        """Build from a dict, naming any unknown key and the allowed ones."""
        allowed = {f.name for f in dataclasses.fields(cls)}
        if kwargs is not None and not isinstance(kwargs, dict):
            raise ValueError(f"task={kwargs!r} must be a mapping of task settings; allowed keys "
                             f"are {sorted(allowed)}")
        kwargs = dict(kwargs or {})
        check_keys("task", kwargs, allowed)
        return cls(**kwargs)

    def stiffness_weight(self, residual: bool) -> float:
        if self.w_stiffness is not None:
            return self.w_stiffness
        return 0.3 if residual else 0.0

    @property
    def max_delta_Pa(self) -> float:
        """[Pa] largest command change in one control period."""
        return self.slew_bar_per_s * BAR * self.dt_s
