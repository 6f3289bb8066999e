"""The simulated rig behind every sim env: a compiled step over a batch of legs, and the engine
that owns the batch's state. ``MPALegEnv`` is a batch of one, ``MPALegVectorEnv`` a batch of N;
both call the same kernel, so they agree step for step by construction (and a test says so).

Per step and leg: action → pressure command (direct or feedforward + residual) → safety layer
(slew limit, clip to [0, p_max]) → regulator (quantisation, dead time, first-order lag inside the
RK4 step) → plant (Eq. 15, RK4 over one control period) → true stiffness (Eq. 23) → reward,
termination → sensors (encoder quantum, white noise) → observation.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numba
import numpy as np

from mpa_gym.analysis.scenario import (
    INITIAL_OFFSETS,
    Plant,
    ScenarioError,
    check_plant_value,
)
from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.kernels import command_from_action, reward_terms, safe_command
from mpa_gym.task.plan import TaskPlan

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


# Columns of the per-step table (TaskPlan arrays side by side, row j = step j).
T_XREF, T_VREF, T_KREF, T_SIN, T_COS, T_FFE, T_FFF, T_FEXT = range(8)
# Entries of the scalar settings vector.
(S_RESIDUAL, S_SCALE, S_PMAX, S_DMAX, S_QUANTUM, S_DT, S_XLO, S_XHI, S_SIGX, S_SIGK, S_WK, S_WU,
 S_ENC, S_SUB) = range(14)
# Columns of the per-leg output: command (2), true k, reward and its three terms, flags, terminated.
O_CMDE, O_CMDF, O_K, O_R, O_RX, O_RK, O_RU, O_FLAGS, O_TERM = range(9)


@numba.njit(**JIT)
def _observe(obs, i, X, V, Pe, Pf, j, noise, enc, tab):
    x_meas = X if enc <= 0.0 else np.round(X / enc) * enc
    obs[i, 0] = x_meas + noise[i, 0]
    obs[i, 1] = V + noise[i, 1]
    obs[i, 2] = tab[j, T_XREF]
    obs[i, 3] = tab[j, T_VREF]
    obs[i, 4] = tab[j, T_SIN]
    obs[i, 5] = tab[j, T_COS]
    obs[i, 6] = Pe / 1e5 + noise[i, 2]
    obs[i, 7] = Pf / 1e5 + noise[i, 3]
    if obs.shape[1] > 8:
        obs[i, 8] = tab[j, T_KREF] / 1000.0


@numba.njit(**JIT)
def observe_rows(obs, rows, state, idx, noise, enc, tab):
    """Write the observation of the legs in ``rows`` (after a reset)."""
    for i in rows:
        _observe(obs, i, state[i, 0], state[i, 1], state[i, 2], state[i, 3], idx[i], noise, enc,
                 tab)


@numba.njit(**JIT)
def _step_leg(i, action, state, prev_cmd, idx, consts, lag, delay, head, noise, s, tab, obs, out):
    """One control period of leg i (see the module docstring)."""
    residual = s[S_RESIDUAL] > 0.0
    j = idx[i]
    a_e = min(max(action[i, 0], -1.0), 1.0)
    a_f = min(max(action[i, 1], -1.0), 1.0)
    ce = command_from_action(a_e, tab[j, T_FFE], residual, s[S_SCALE], s[S_PMAX])
    cf = command_from_action(a_f, tab[j, T_FFF], residual, s[S_SCALE], s[S_PMAX])
    ce, fl_e = safe_command(ce, prev_cmd[i, 0], s[S_PMAX], s[S_DMAX])
    cf, fl_f = safe_command(cf, prev_cmd[i, 1], s[S_PMAX], s[S_DMAX])
    prev_cmd[i, 0] = ce
    prev_cmd[i, 1] = cf
    out[i, O_CMDE] = ce
    out[i, O_CMDF] = cf
    out[i, O_FLAGS] = fl_e | fl_f
    q = s[S_QUANTUM]
    if q > 0.0:
        ce = np.round(ce / q) * q
        cf = np.round(cf / q) * q
    if delay.shape[1] > 0:
        de, df = delay[i, head, 0], delay[i, head, 1]
        delay[i, head, 0] = ce
        delay[i, head, 1] = cf
        ce, cf = de, df
    X, V, Pe, Pf = fast.plant_step(state[i, 0], state[i, 1], state[i, 2], state[i, 3], ce, cf,
                                   tab[j, T_FEXT], lag[i], s[S_DT], consts[i], int(s[S_SUB]))
    failed = not (np.isfinite(X) and np.isfinite(V))
    if failed:  # the step left the model's domain: keep the last state, terminate
        X, V, Pe, Pf = state[i, 0], state[i, 1], state[i, 2], state[i, 3]
    state[i, 0] = X
    state[i, 1] = V
    state[i, 2] = Pe
    state[i, 3] = Pf
    _, k = fast.force_and_stiffness(X, V, Pe, Pf, consts[i])
    out[i, O_K] = k
    j += 1
    idx[i] = j
    r, rx, rk, ru = reward_terms(X - tab[j, T_XREF], k, tab[j, T_KREF], a_e, a_f,
                                 s[S_SIGX], s[S_SIGK], s[S_WK], s[S_WU])
    ok = (s[S_XLO] <= X <= s[S_XHI]) and not failed
    out[i, O_TERM] = 0.0 if ok else 1.0
    out[i, O_R] = r if ok else 0.0
    out[i, O_RX] = rx if ok else 0.0
    out[i, O_RK] = rk if ok else 0.0
    out[i, O_RU] = ru
    _observe(obs, i, X, V, Pe, Pf, j, noise, s[S_ENC], tab)


@numba.njit(**JIT)
def _first_bad_action(action):
    for i in range(action.shape[0]):
        if not (np.isfinite(action[i, 0]) and np.isfinite(action[i, 1])):
            return i
    return -1


@numba.njit(**JIT)
def step_batch(action, state, prev_cmd, idx, consts, lag, delay, head, noise, s, tab, obs, out):
    """One control period for every leg of the batch.

    Returns the index of the first leg whose action is not finite (nothing is changed then),
    or −1. Finite actions are clipped to [−1, 1].
    """
    bad = _first_bad_action(action)
    if bad >= 0:
        return bad
    for i in range(state.shape[0]):
        _step_leg(i, action, state, prev_cmd, idx, consts, lag, delay, head, noise, s, tab, obs,
                  out)
    return -1


@numba.njit(parallel=True, **JIT)
def step_batch_parallel(action, state, prev_cmd, idx, consts, lag, delay, head, noise, s, tab,
                        obs, out):
    """``step_batch`` with the legs spread over the cores, for large batches (a thread pool has
    a fixed cost of microseconds per call, which a single leg should not pay)."""
    bad = _first_bad_action(action)
    if bad >= 0:
        return bad
    for i in numba.prange(state.shape[0]):
        _step_leg(i, action, state, prev_cmd, idx, consts, lag, delay, head, noise, s, tab, obs,
                  out)
    return -1


PARALLEL_MIN_LEGS = 256


# Plant fields each leg of a batch may have its own value of (the rest belong to the rig).
PER_LEG_FIELDS = frozenset({"extra_mass_kg", "mass_kg", "gamma_Ns_per_m", "C1_Pa", "C2_Pa",
                            "thickness_m", "pressure_lag_s", *INITIAL_OFFSETS})


def _table(plan: TaskPlan) -> np.ndarray:
    """The per-step table of one plan, (n_steps + 1, 8) with the T_* columns."""
    tab = np.zeros((plan.n_steps + 1, 8))
    tab[:, T_XREF], tab[:, T_VREF], tab[:, T_KREF] = plan.x_ref, plan.v_ref, plan.k_ref
    tab[:, T_SIN], tab[:, T_COS] = plan.sin_phase, plan.cos_phase
    tab[:-1, T_FFE:T_FFF + 1] = plan.ff
    tab[:-1, T_FEXT] = plan.f_ext
    return tab


def resolve_plant(base: Plant, draws: dict[str, float], fixed: dict[str, Any] | None
                  ) -> tuple[Plant, float, float]:
    """The episode's plant: the scenario's, then randomised draws, then ``fixed`` (reset options).

    Returns (plant, initial X offset, initial V offset).
    """
    values = dict(draws)
    for k, v in (fixed or {}).items():
        values[k] = check_plant_value(k, v, "options['plant']")
    offsets = {k: values.pop(k, 0.0) for k in INITIAL_OFFSETS}
    return (dataclasses.replace(base, **values), offsets["initial_x_offset_m"],
            offsets["initial_v_offset_mps"])


class SimEngine:
    """State and buffers of a batch of ``n`` simulated legs following task plans.

    With several plans (one scenario, several stiffness designs) each episode follows one of
    them, drawn at reset. Their tables are stacked along the step axis, plan p occupying rows
    p (N + 1) … p (N + 1) + N, so a leg's step index points straight into its plan's rows and the
    compiled step needs no notion of plans at all.
    """

    def __init__(self, plans: TaskPlan | list[TaskPlan], n: int, residual: bool,
                 params: Params = DEFAULT_PARAMS) -> None:
        plans = list(plans) if isinstance(plans, list | tuple) else [plans]
        plan = plans[0]
        for other in plans[1:]:
            if other.n_steps != plan.n_steps or other.scenario != plan.scenario or \
                    other.cfg != plan.cfg:
                raise ValueError("all plans of an engine share the scenario and task settings")
        self.plans = plans
        self.plan, self.n, self.residual, self.params = plan, int(n), bool(residual), params
        cfg: TaskConfig = plan.cfg
        self.cfg = cfg
        self.obs_dim = 9 if residual else 8
        self.w_k = cfg.stiffness_weight(residual)
        self.state = np.zeros((n, 4))
        self.prev_cmd = np.zeros((n, 2))
        self.idx = np.zeros(n, dtype=np.int64)  # row of the stacked tables
        self.start = np.zeros(n, dtype=np.int64)  # first row of each leg's plan
        self.base_consts = fast.pack(plan.scenario.plant_params(params))
        self.consts = np.tile(self.base_consts, (n, 1))
        self.lag = np.zeros(n)
        self.plants: list[Plant] = [plan.scenario.plant] * n
        self.obs = np.zeros((n, self.obs_dim))
        self.out = np.zeros((n, 9))
        self.noise = np.zeros((n, 4))
        self.head = 0
        self.rows_per_plan = plan.n_steps + 1
        self.tab = np.concatenate([_table(p) for p in plans])
        self._configure_shared(plan.scenario.plant)

    def _configure_shared(self, pl: Plant) -> None:
        """Regulator quantum, dead time and sensors are the rig's, shared by the batch."""
        c = self.cfg
        self.settings = np.array([
            1.0 if self.residual else 0.0, c.residual_scale_bar * BAR, c.p_max_bar * BAR,
            c.max_delta_Pa, pl.pressure_quantum_bar * BAR, c.dt_s, c.x_min_m, c.x_max_m,
            c.sigma_x_m, c.sigma_k, self.w_k, c.w_effort, pl.encoder_resolution_m,
            float(c.substeps)])
        self.noise_std = np.array([pl.position_noise_m, pl.velocity_noise_mps,
                                   pl.pressure_noise_bar * BAR / 1e5,
                                   pl.pressure_noise_bar * BAR / 1e5])
        self.has_noise = bool(self.noise_std.any())
        n_delay = round(pl.pressure_dead_time_s / self.cfg.dt_s)
        if not hasattr(self, "delay") or self.delay.shape[1] != n_delay:
            self.delay = np.zeros((self.n, n_delay, 2))
            self.head = 0

    def draw_noise(self, rows: Any, rngs: list[np.random.Generator]) -> None:
        """Sensor noise for ``rows``, each from its own generator (so legs are independent)."""
        if not self.has_noise:
            return
        for i in rows:
            self.noise[i] = rngs[i].standard_normal(4) * self.noise_std

    def reset_rows(self, rows: Any, rngs: list[np.random.Generator],
                   options: dict[str, Any] | None = None) -> None:
        """Start new episodes for ``rows``: draw (or fix) the plant, the initial state."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        fixed, x0, v0 = self._reset_options(options)
        sc = self.plan.scenario
        if len(self.plans) > 1:  # each new episode follows one of the designs
            which = np.array([rngs[i].integers(len(self.plans)) for i in rows])
        else:
            which = np.zeros(rows.size, dtype=np.int64)
        p0 = np.array([p.p0 for p in self.plans])[which]
        per_leg = bool(sc.randomize.ranges) or any(k in PER_LEG_FIELDS for k in fixed or {})
        dx = np.zeros(rows.size)
        dv = np.zeros(rows.size)
        if per_leg:  # each leg its own plant
            for r, i in enumerate(rows):
                plant, dx[r], dv[r] = resolve_plant(sc.plant, sc.randomize.sample(rngs[i]), fixed)
                try:
                    self.consts[i] = fast.pack(sc.plant_params(self.params, plant))
                except ValueError as e:
                    raise ScenarioError(f"episode plant is invalid: {e}") from None
                self.plants[i] = plant
                self.lag[i] = plant.pressure_lag_s
        else:  # the scenario's plant for every leg: no per-leg work
            self.consts[rows] = self.base_consts
            self.lag[rows] = sc.plant.pressure_lag_s
            for i in rows:
                self.plants[i] = sc.plant
        self.state[rows, 0] = x0 + dx
        self.state[rows, 1] = v0 + dv
        self.state[rows, 2:] = p0
        self.prev_cmd[rows] = p0
        self.delay[rows] = p0[:, None, :]
        self.idx[rows] = self.start[rows] = which * self.rows_per_plan
        self.out[rows] = 0.0
        self.out[rows, O_CMDE:O_CMDF + 1] = p0
        self.out[rows, O_K] = [fast.force_and_stiffness(*self.state[i], self.consts[i])[1]
                               for i in (rows if per_leg else rows[:1])]
        self.draw_noise(rows, rngs)
        observe_rows(self.obs, rows, self.state, self.idx, self.noise, self.settings[S_ENC],
                     self.tab)

    def _reset_options(self, options: dict[str, Any] | None
                       ) -> tuple[dict[str, Any] | None, float, float]:
        """Validate reset options; apply rig-wide ones; return (per-leg plant fields, X0, V0)."""
        options = dict(options or {})
        unknown = sorted(set(options) - {"plant", "initial_state"})
        if unknown:
            raise ValueError(f"reset options: unknown key(s) {unknown}; allowed keys are "
                             "['initial_state', 'plant']")
        fixed = options.get("plant")
        if fixed is not None and not isinstance(fixed, dict):
            raise ValueError(f"options['plant'] must be a dict of plant fields, got {fixed!r}")
        sc = self.plan.scenario
        shared = {k: check_plant_value(k, v, "options['plant']") for k, v in (fixed or {}).items()
                  if k not in PER_LEG_FIELDS}
        if shared:
            self._configure_shared(dataclasses.replace(sc.plant, **shared))
        x0, v0 = sc.start_state()
        init = options.get("initial_state")
        if init is not None:
            try:
                x0, v0 = float(init["x_m"]), float(init["v_mps"])
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"options['initial_state']={init!r} must be "
                                 "{'x_m': float, 'v_mps': float}") from None
            lo, hi = self.cfg.x_min_m, self.cfg.x_max_m
            if not (lo <= x0 <= hi and np.isfinite(v0)):
                raise ValueError(f"options['initial_state'].x_m={x0} must lie in the position "
                                 f"bounds [{lo}, {hi}] m and v_mps={v0} must be finite")
        return fixed, x0, v0

    def step(self, action: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Advance every leg one control period (action: (n, 2) float64; clipped to [−1, 1]).

        Raises ValueError, changing nothing, if an action is NaN or infinite."""
        if self.has_noise:
            self.draw_noise(range(self.n), rngs)
        kernel = step_batch_parallel if self.n >= PARALLEL_MIN_LEGS else step_batch
        bad = kernel(action, self.state, self.prev_cmd, self.idx, self.consts, self.lag,
                         self.delay, self.head, self.noise, self.settings, self.tab, self.obs,
                         self.out)
        if bad >= 0:
            where = f"action[{bad}]" if self.n > 1 else "action"
            raise ValueError(f"{where}={action[bad].tolist()} must be finite; allowed range "
                             "[-1, 1] (extensor, flexor)")
        if self.delay.shape[1]:
            self.head = (self.head + 1) % self.delay.shape[1]

    @property
    def truncated(self) -> np.ndarray:
        """Legs whose episode has run its full length."""
        return self.idx - self.start >= self.plan.n_steps

    def plan_of(self, i: int) -> TaskPlan:
        """The plan leg i follows in its current episode."""
        return self.plans[int(self.start[i] // self.rows_per_plan)]

    def info(self, i: int) -> dict[str, Any]:
        """The step info of leg i (DESIGN.md keys, the reward terms, safety flags)."""
        j = int(self.idx[i])
        o = self.out[i]
        return {
            "x_m": float(self.state[i, 0]),
            "x_ref_m": float(self.tab[j, T_XREF]),
            "k_N_per_m": float(o[O_K]),
            "k_ref_N_per_m": float(self.tab[j, T_KREF]),
            "pressure_cmd_bar": o[O_CMDE:O_CMDF + 1] / BAR,
            "pressure_bar": self.state[i, 2:4] / BAR,
            "reward_position": float(o[O_RX]),
            "reward_stiffness": float(o[O_RK]),
            "reward_effort": float(o[O_RU]),
            "safety": int(o[O_FLAGS]),
            "t_s": (j - int(self.start[i])) * self.cfg.dt_s,
        }


__all__ = ["SimEngine", "observe_rows", "resolve_plant", "step_batch"]
