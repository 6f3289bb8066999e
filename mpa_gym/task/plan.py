"""A task plan: the reference, feedforward and disturbance tables an episode steps through.

Everything here depends only on the scenario, the stiffness target and the nominal design model,
so it is computed once per env and shared by every episode (and by every sub-env of a vector env).
Step i covers [t_i, t_i + dt] with t_i = i dt: the feedforward command for it is Eq. (16) (or
Eq. 25) evaluated at the mid-step t_i + dt/2, held over the step as a regulator command is; the
external force is the mean of the scenario's disturbances over the step (same impulse).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mpa_gym.analysis.scenario import Inputs, Scenario, load_scenario
from mpa_gym.design.feedforward import FeedforwardDesign, StiffnessProfile
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params
from mpa_gym.task import contract as C
from mpa_gym.task.config import TaskConfig


def stiffness_design(scenario: Scenario, stiffness: Any, params: Params) -> FeedforwardDesign:
    """The scenario's own design, or an Eq. (25) design for ``stiffness``: "kmax", "kmin", a
    constant [N/m] or a profile {"t_s": [...], "k_N_per_m": [...]} over one period."""
    ref = scenario.reference
    if stiffness is None:
        return scenario.design(params)
    if isinstance(stiffness, str) and stiffness in ("kmax", "kmin"):
        return Inputs(stiffness=stiffness).design(ref, params)
    if isinstance(stiffness, int | float) and not isinstance(stiffness, bool):
        return Inputs(stiffness_const_N_per_m=float(stiffness)).design(ref, params)
    if isinstance(stiffness, dict) and set(stiffness) == {"t_s", "k_N_per_m"}:
        prof = StiffnessProfile(tuple(map(float, stiffness["t_s"])),
                                tuple(map(float, stiffness["k_N_per_m"])), ref.period)
        return FeedforwardDesign(ref, stiffness=prof, params=params)
    raise ValueError(f"stiffness={stiffness!r} must be None, 'kmax', 'kmin', a number [N/m] or "
                     "{'t_s': [...], 'k_N_per_m': [...]}")


@dataclass(frozen=True)
class TaskPlan:
    scenario: Scenario
    cfg: TaskConfig
    design: FeedforwardDesign
    n_steps: int  # steps per episode
    t: np.ndarray  # [s] (n+1,) t_i
    x_ref: np.ndarray  # [m] (n+1,) X̂(t_i)
    v_ref: np.ndarray  # [m/s] (n+1,)
    k_ref: np.ndarray  # [N/m] (n+1,) k̂(t_i) (the design's stiffness along the reference)
    sin_phase: np.ndarray  # (n+1,) sin(2π t_i / T)
    cos_phase: np.ndarray  # (n+1,)
    ff: np.ndarray  # [Pa] (n, 2) feedforward command of step i (mid-step)
    f_ext: np.ndarray  # [N] (n,) mean disturbance force over step i
    p0: np.ndarray  # [Pa] (2,) pressures at t = 0 (the design's)

    def table(self) -> np.ndarray:
        """The plan as one (n_steps + 1, len(PLAN)) array, row j = step j, columns the PLAN
        signals of ``task.contract`` (the feedforward and disturbance rows stop at n − 1)."""
        tab = np.zeros((self.n_steps + 1, len(C.PLAN)))
        tab[:, C.T_XREF], tab[:, C.T_VREF], tab[:, C.T_KREF] = self.x_ref, self.v_ref, self.k_ref
        tab[:, C.T_SIN], tab[:, C.T_COS] = self.sin_phase, self.cos_phase
        tab[:-1, C.T_FFE], tab[:-1, C.T_FFF] = self.ff[:, 0], self.ff[:, 1]
        tab[:-1, C.T_FEXT] = self.f_ext
        return tab


def make_plan(scenario: Any = "nominal", stiffness: Any = None, cfg: TaskConfig | None = None,
              params: Params = DEFAULT_PARAMS) -> TaskPlan:
    """Tables for a scenario (name, path, dict or Scenario) and an optional stiffness target."""
    sc = load_scenario(scenario)
    cfg = cfg or TaskConfig()
    design = stiffness_design(sc, stiffness, params).require_feasible(p_max=cfg.p_max_bar * BAR)
    episode = cfg.episode_s if cfg.episode_s is not None else sc.duration_s
    n = max(1, round(episode / cfg.dt_s))
    t = np.arange(n + 1) * cfg.dt_s
    s = design.sample(t)
    w = design.reference.omega
    f_ext = np.zeros(n)
    for d in sc.disturbances:
        a, b = d.t_s, d.t_s + d.duration_s
        overlap = np.clip(np.minimum(t[1:], b) - np.maximum(t[:-1], a), 0.0, None)
        f_ext += d.force_N * overlap / cfg.dt_s
    return TaskPlan(sc, cfg, design, n, t, s.x_ref, s.v_ref, s.k, np.sin(w * t), np.cos(w * t),
                    design.pressures(t[:-1] + 0.5 * cfg.dt_s), f_ext, design.pressures(0.0))
