"""Classical controllers for ``MPALegResidual-v0`` behind SB3's policy interface.

Every controller has ``predict(observation, state=None, episode_start=None,
deterministic=True) -> (action, state)`` like an SB3 model, takes one observation (9,) or a
batch (n, 9), and returns residual actions in [−1, 1]. They know only what a controller on the
rig knows: the observation and the *nominal* model the feedforward was designed on (never the
true plant).

- ``ZeroResidual`` (``ff``): the paper's feedforward expert, Eq. (16) / Eq. (25) alone.
- ``PIDResidual`` (``pid``): feedforward + PID on the position error, added antagonistically
  (+u on the extensor, −u on the flexor, in bar).
- ``StiffnessFeedback`` (``mbfb``): model-based feedback that uses the redundancy of the two
  pressures: each step it solves, on the nominal model at the measured state, for the pressures
  whose ground force is m(dV̂/dt + g) plus a PID force correction *and* whose joint stiffness
  (Eq. 23) is k̂ — two equations affine in (P'_e, P'_f).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from mpa_gym.design.feedforward import affine_in_pressures
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.plan import TaskPlan, make_plan

# observation columns (mpa_gym.task.config.RESIDUAL_OBS_NAMES)
OX, OV, OXR, OVR, OSIN, OCOS, OPE, OPF, OK = range(9)


class Policy(Protocol):
    """What evaluation needs of a controller: SB3's ``predict``."""

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]: ...


@dataclass
class _PlanPolicy:
    """A controller that knows the env's plan (reference and nominal feedforward)."""

    plan: TaskPlan
    params: Params = field(default_factory=lambda: DEFAULT_PARAMS)

    @property
    def cfg(self) -> TaskConfig:
        return self.plan.cfg

    def _time(self, obs: np.ndarray) -> np.ndarray:
        """[s] time within the period, from the observed phase."""
        T = self.plan.design.reference.period
        return np.mod(np.arctan2(obs[:, OSIN], obs[:, OCOS]) / (2 * math.pi) * T, T)

    def _feedforward(self, obs: np.ndarray) -> np.ndarray:
        """[Pa] (n, 2): the command the env's feedforward applies over this step (mid-step)."""
        return self.plan.design.pressures(self._time(obs) + 0.5 * self.cfg.dt_s)

    def _pid(self, obs: np.ndarray, state: Any, episode_start: np.ndarray | None, kp: float,
             ki: float, kd: float) -> tuple[np.ndarray, np.ndarray]:
        """(Kp e + Ki ∫e + Kd ė, ∫e) for e = X̂ − X; the integral is the policy's state."""
        integ = np.zeros(obs.shape[0]) if state is None else np.array(state, dtype=float)
        if episode_start is not None:
            integ[np.asarray(episode_start, dtype=bool).reshape(-1)] = 0.0
        e = obs[:, OXR] - obs[:, OX]
        integ = integ + e * self.cfg.dt_s
        return kp * e + ki * integ + kd * (obs[:, OVR] - obs[:, OV]), integ

    def _to_action(self, obs: np.ndarray, pressures: np.ndarray) -> np.ndarray:
        """Residual action that makes the env command ``pressures`` [Pa], clipped to [−1, 1]."""
        a = (pressures - self._feedforward(obs)) / (self.cfg.residual_scale_bar * BAR)
        return np.clip(a, -1.0, 1.0).astype(np.float32)


def _batch(observation: np.ndarray) -> tuple[np.ndarray, bool]:
    obs = np.asarray(observation, dtype=np.float64)
    single = obs.ndim == 1
    obs = obs.reshape(1, -1) if single else obs
    if obs.shape[1] != 9:
        raise ValueError(f"observation has {obs.shape[1]} entries; these controllers need "
                         "MPALegResidual-v0's 9")
    return obs, single


class ZeroResidual:
    """The feedforward expert: a zero residual applies Eq. (16) / Eq. (25) exactly."""

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs, single = _batch(observation)
        a = np.zeros((obs.shape[0], 2), dtype=np.float32)
        return (a[0] if single else a), state


@dataclass
class PIDResidual(_PlanPolicy):
    """Feedforward + PID: u = Kp e + Ki ∫e + Kd ė [bar], e = X̂ − X; residual (+u, −u)."""

    # Tuned for the lowest worst-case position RMSE over four plants drawn from the training
    # ranges (+1 kg; m 4.1 kg with C1 −9 %, t +20 %, 40 ms lag; +1.2 kg with γ 20 N s/m and 40 ms
    # lag; m 3.5 kg with C1 +15 % and 20 ms lag) on a grid Kp ∈ {8…150}, Ki ∈ {20…6000},
    # Kd ∈ {0.3…20}; the optimum is inside the grid (worst case 0.020 mm).
    kp_bar_per_m: float = 80.0
    ki_bar_per_m_s: float = 3000.0
    kd_bar_s_per_m: float = 12.0

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs, single = _batch(observation)
        u, integ = self._pid(obs, state, episode_start, self.kp_bar_per_m, self.ki_bar_per_m_s,
                             self.kd_bar_s_per_m)
        a = np.stack([u, -u], axis=-1) / self.cfg.residual_scale_bar
        a = np.clip(a, -1.0, 1.0).astype(np.float32)
        return (a[0] if single else a), integ


@dataclass
class StiffnessFeedback(_PlanPolicy):
    """Model-based, stiffness-preserving feedback (module docstring).

    Force law: F* = m (dV̂/dt + g) + Kp e + Ki ∫e + Kd ė on the nominal m; pressures from
    F(X, V, P') = F* and k(X, V, P') = k̂ at the measured (X, V), both affine in P'.
    """

    # Tuned like PIDResidual (same four training-range plants, lowest worst-case RMSE) on a grid
    # Kp ∈ {300…2000} N/m, Kd ∈ {20…140} N s/m, Ki ∈ {150…4000} N/(m s): worst case 0.48 mm.
    kp_N_per_m: float = 2000.0
    ki_N_per_m_s: float = 500.0
    kd_N_s_per_m: float = 140.0

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs, single = _batch(observation)
        correction, integ = self._pid(obs, state, episode_start, self.kp_N_per_m,
                                      self.ki_N_per_m_s, self.kd_N_s_per_m)
        x, v = obs[:, OX], obs[:, OV]
        ref = self.plan.design.reference
        a_ref = -ref.omega**2 * (obs[:, OXR] - ref.x0)
        p = self.params
        f_star = p.leg.m * (a_ref + p.leg.g) + correction
        k_star = obs[:, OK] * 1000.0
        with np.errstate(invalid="ignore"):
            c = affine_in_pressures(x, v, p)
        A = c.J
        rhs = np.stack([f_star - c.F0, k_star - c.k0], axis=-1)
        with np.errstate(invalid="ignore"):  # outside the model's domain: NaN, handled below
            pressures = np.linalg.solve(A, rhs[..., None])[..., 0]
        pressures = np.clip(pressures, 0.0, self.cfg.p_max_bar * BAR)
        a = self._to_action(obs, pressures)
        a[~np.isfinite(a)] = 0.0  # no model answer (state outside its domain): feedforward only
        return (a[0] if single else a), integ


BASELINES = {"ff": "ZeroResidual", "pid": "PIDResidual", "mbfb": "StiffnessFeedback"}


def make_baseline(name: str, scenario: Any = "nominal", stiffness: Any = None,
                  task: dict[str, Any] | TaskConfig | None = None,
                  params: Params = DEFAULT_PARAMS) -> Policy:
    """A baseline by name for an env made with the same (scenario, stiffness, task)."""
    if name not in BASELINES:
        raise ValueError(f"policy={name!r} is not a baseline; choose one of {sorted(BASELINES)} "
                         "or a run folder")
    if name == "ff":
        return ZeroResidual()
    cfg = task if isinstance(task, TaskConfig) else TaskConfig.from_kwargs(task)
    plan = make_plan(scenario, stiffness, cfg, params)
    return PIDResidual(plan, params) if name == "pid" else StiffnessFeedback(plan, params)
