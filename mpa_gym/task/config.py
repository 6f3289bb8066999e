"""What sim and hardware share: the task's timing, limits, reward weights and spaces (layer 3)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces

from mpa_gym.model.params import BAR, check_range

# Observation layout (float32), shared by every env id; the residual env appends k̂.
OBS_NAMES = ("x_m", "v_mps", "x_ref_m", "v_ref_mps", "sin_phase", "cos_phase", "pe_bar", "pf_bar")
RESIDUAL_OBS_NAMES = (*OBS_NAMES, "k_ref_kN_per_m")
# Info keys every env fills on every step (DESIGN.md contract) and the reward breakdown.
INFO_KEYS = ("x_m", "x_ref_m", "k_N_per_m", "k_ref_N_per_m", "pressure_cmd_bar", "pressure_bar")
REWARD_KEYS = ("reward_position", "reward_stiffness", "reward_effort")
# Safety flags (bit mask in info["safety"]).
SAFETY_CLIPPED = 1  # a command was clipped to [0, p_max]
SAFETY_SLEW = 2  # a command was slew-rate limited


@dataclass(frozen=True)
class TaskConfig:
    """Timing, safety limits and reward of the task (one per env; sim and hardware alike)."""

    dt_s: float = 0.01  # [s] control period (100 Hz, the rig's default rate)
    substeps: int = 2  # RK4 steps per control period (sim only): 2 keeps X within 1e-6 m
    episode_s: float | None = None  # [s] episode length; None: the scenario's duration_s
    p_max_bar: float = 7.0  # [bar] regulator limit: commands are clipped to [0, p_max]
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
        check_range("x_min_m", self.x_min_m, 0.6, 0.86, unit="m")
        check_range("x_max_m", self.x_max_m, self.x_min_m, 0.87, low_open=True, unit="m")
        check_range("residual_scale_bar", self.residual_scale_bar, 0.0, 7.0, low_open=True,
                    unit="bar")
        check_range("sigma_x_m", self.sigma_x_m, 0.0, 1.0, low_open=True, unit="m")
        check_range("sigma_k", self.sigma_k, 0.0, 10.0, low_open=True)
        if self.w_stiffness is not None:
            check_range("w_stiffness", self.w_stiffness, 0.0, 1.0)
        check_range("w_effort", self.w_effort, 0.0, 10.0)

    @classmethod
    def from_kwargs(cls, kwargs: dict[str, Any] | None) -> TaskConfig:
        """Build from a dict, naming any unknown key and the allowed ones."""
        kwargs = dict(kwargs or {})
        allowed = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(kwargs) - allowed)
        if unknown:
            raise ValueError(f"task: unknown key(s) {unknown}; allowed keys are {sorted(allowed)}")
        return cls(**kwargs)

    def stiffness_weight(self, residual: bool) -> float:
        if self.w_stiffness is not None:
            return self.w_stiffness
        return 0.3 if residual else 0.0

    @property
    def max_delta_Pa(self) -> float:
        """[Pa] largest command change in one control period."""
        return self.slew_bar_per_s * BAR * self.dt_s


def action_space() -> spaces.Box:
    """Both ids: two normalised actions in [−1, 1] (extensor first), as SB3 recommends."""
    return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)


def observation_space(cfg: TaskConfig, residual: bool) -> spaces.Box:
    """Bounds of the observation (positions [m], velocities [m/s], pressures [bar], k̂ [kN/m]).

    Generous enough for the state one step past a termination bound plus sensor noise."""
    lo = [0.0, -10.0, 0.0, -10.0, -1.0, -1.0, -1.0, -1.0]
    hi = [1.0, 10.0, 1.0, 10.0, 1.0, 1.0, cfg.p_max_bar + 1.0, cfg.p_max_bar + 1.0]
    if residual:
        lo.append(-100.0)
        hi.append(100.0)
    return spaces.Box(np.array(lo, dtype=np.float32), np.array(hi, dtype=np.float32),
                      dtype=np.float32)


def check_action(action: Any, n: int | None = None) -> np.ndarray:
    """Validate an action: shape (2,) (or (n, 2) for a vector env), finite; then clip to [−1, 1].

    Out-of-range finite values are clipped, as SB3 does with its policies' actions (documented
    in the envs' Action Space); NaN, ±inf and wrong shapes raise ``ValueError``.
    """
    a = np.asarray(action, dtype=np.float64)
    shape = (2,) if n is None else (n, 2)
    if a.shape != shape:
        raise ValueError(f"action has shape {a.shape}; expected {shape} (extensor, flexor) in "
                         "[-1, 1]")
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise ValueError(f"action{list(bad)}={a[tuple(bad)]!r} must be finite; allowed range "
                         "[-1, 1]")
    return np.clip(a, -1.0, 1.0)


