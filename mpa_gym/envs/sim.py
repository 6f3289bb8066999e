"""The simulated rig behind every sim env: a compiled step over a batch of legs, and the engine
that owns the batch's state. ``MPALegEnv`` is a batch of one, ``MPALegVectorEnv`` a batch of N;
both call the same kernel, so they agree step for step by construction (and a test says so).

Per step and leg: action → pressure command (direct or feedforward + residual) → safety layer
(slew limit, clip to [0, p_max]) → regulator (quantisation, then dead time, slew limit and
first-order lag solved exactly inside the RK4 steps; a dead time that is not a whole number of
control periods switches the command inside the period) → plant (Eq. 15 with the braid and
slider friction, RK4 over one control period, under the plan's disturbance and the leg's own
random kick) → true stiffness (Eq. 23) → reward, termination (``task.kernels.finish_step``, the
rig's composition too) → sensors (encoder quantum, white noise) → observation.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numba
import numpy as np

from mpa_gym.analysis.scenario import (
    EPISODE_FIELDS,
    Plant,
    ScenarioError,
    check_plant_value,
)
from mpa_gym.model import fast
from mpa_gym.model.jit import JIT
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_keys
from mpa_gym.task.config import END_STOPS_M, TaskConfig
from mpa_gym.task.contract import (
    O_CMDE,
    O_CMDF,
    O_FLAGS,
    O_K,
    OUT,
    ST_PE,
    ST_PF,
    ST_V,
    ST_X,
    STATE,
    T_FEXT,
    T_FFE,
    T_FFF,
    obs_spec,
    step_info,
)
from mpa_gym.task.homing import HomingConfig, HomingError, home, vented_rest
from mpa_gym.task.kernels import (
    S_DMAX,
    S_DT,
    S_ENC,
    S_PMAX,
    S_QUANTUM,
    S_RESIDUAL,
    S_SCALE,
    S_SUB,
    command_from_action,
    finish_step,
    observe,
    safe_command,
    task_settings,
)
from mpa_gym.task.plan import TaskPlan


@numba.njit(**JIT)
def _observe(obs, i, X, V, Pe, Pf, j, noise, enc, tab, spec):
    """Observation row i: the encoder quantises X, then ``task.kernels.observe``."""
    x_meas = X if enc <= 0.0 else np.round(X / enc) * enc
    observe(obs[i], x_meas, V, Pe, Pf, tab[j], noise[i], spec)


@numba.njit(**JIT)
def observe_rows(obs, rows, state, idx, noise, enc, tab, spec):
    """Write the observation of the legs in ``rows`` (after a reset)."""
    for i in rows:
        _observe(obs, i, state[i, ST_X], state[i, ST_V], state[i, ST_PE], state[i, ST_PF], idx[i],
                 noise, enc, tab, spec)


@numba.njit(**JIT)
def kick_force(kick, j, dt):
    """The mean over step j (rows of the stacked plan tables, [j dt, (j + 1) dt]) of a kick
    ``(start, end, force)`` given on the same time axis: the plan's ``f_ext`` rule for an
    impulse (``task.plan``), so a drawn kick and the same ``Impulse`` in ``disturbances`` agree."""
    t0 = j * dt
    overlap = min(t0 + dt, kick[1]) - max(t0, kick[0])
    return kick[2] * overlap / dt if overlap > 0.0 else 0.0


@numba.njit(**JIT)
def _step_leg(i, action, state, prev_cmd, idx, consts, dead, hist, head, noise, s, tab, spec,
              kick, obs, out):
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
    # dead time T_d = n dt + φ: the command of n periods ago takes over at φ into this period
    cap = hist.shape[1]
    hist[i, head, 0] = ce
    hist[i, head, 1] = cf
    n_d = int(dead[i, 0])
    new = (head - n_d) % cap
    old = (head - n_d - 1) % cap
    X, V, Pe, Pf = fast.plant_step(state[i, ST_X], state[i, ST_V], state[i, ST_PE],
                                   state[i, ST_PF], hist[i, old, 0], hist[i, old, 1],
                                   hist[i, new, 0], hist[i, new, 1], dead[i, 1],
                                   tab[j, T_FEXT] + kick_force(kick[i], j, s[S_DT]),
                                   s[S_DT], consts[i], int(s[S_SUB]))
    failed = not (np.isfinite(X) and np.isfinite(V))
    if failed:  # the step left the model's domain: keep the last state, terminate
        X, V, Pe, Pf = state[i, ST_X], state[i, ST_V], state[i, ST_PE], state[i, ST_PF]
    state[i, ST_X] = X
    state[i, ST_V] = V
    state[i, ST_PE] = Pe
    state[i, ST_PF] = Pf
    _, k = fast.force_and_stiffness(X, V, Pe, Pf, consts[i])
    j += 1
    idx[i] = j
    finish_step(out[i], X, k, tab[j], a_e, a_f, s, failed)  # reward, termination (task layer)
    _observe(obs, i, X, V, Pe, Pf, j, noise, s[S_ENC], tab, spec)


@numba.njit(**JIT)
def step_batch(action, state, prev_cmd, idx, consts, dead, hist, head, noise, s, tab, spec, kick,
               obs, out):
    """One control period for every leg of the batch (actions checked by the env beforehand
    with ``task.contract.check_action``; they are clipped to [−1, 1] here)."""
    for i in range(state.shape[0]):
        _step_leg(i, action, state, prev_cmd, idx, consts, dead, hist, head, noise, s, tab, spec,
                  kick, obs, out)


@numba.njit(parallel=True, **JIT)
def step_batch_parallel(action, state, prev_cmd, idx, consts, dead, hist, head, noise, s, tab,
                        spec, kick, obs, out):
    """``step_batch`` with the legs spread over the cores, for large batches (a thread pool has
    a fixed cost of microseconds per call, which a single leg should not pay)."""
    for i in numba.prange(state.shape[0]):
        _step_leg(i, action, state, prev_cmd, idx, consts, dead, hist, head, noise, s, tab, spec,
                  kick, obs, out)


PARALLEL_MIN_LEGS = 256
RESET_OPTIONS = ("homing", "initial_state", "plant")  # the keys reset(options=...) takes


# Plant fields each leg of a batch may have its own value of (the rest belong to the rig).
PER_LEG_FIELDS = frozenset({"extra_mass_kg", "mass_kg", "gamma_Ns_per_m", "C1_Pa", "C2_Pa",
                            "thickness_m", "pressure_lag_s", "pressure_dead_time_s",
                            "pressure_slew_bar_per_s", "braid_friction_ratio",
                            "slider_friction_N", "slider_viscous_Ns_per_m", *EPISODE_FIELDS})


def resolve_plant(base: Plant, draws: dict[str, float], fixed: dict[str, Any] | None
                  ) -> tuple[Plant, dict[str, float]]:
    """The episode's plant: the scenario's, then randomised draws, then ``fixed`` (reset options).

    Returns (plant, the episode's other draws: every ``EPISODE_FIELDS`` key, 0 where not drawn
    or fixed: the initial-state offsets and the random kick).
    """
    values = dict(draws)
    for k, v in (fixed or {}).items():
        values[k] = check_plant_value(k, v, "options['plant']")
    episode = {k: values.pop(k, 0.0) for k in EPISODE_FIELDS}
    return dataclasses.replace(base, **values), episode


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
        self.spec = obs_spec(residual)  # the observation layout (task.contract)
        self.obs_dim = self.spec.shape[0]
        self.state = np.zeros((n, len(STATE)))
        self.prev_cmd = np.zeros((n, 2))
        self.idx = np.zeros(n, dtype=np.int64)  # row of the stacked tables
        self.start = np.zeros(n, dtype=np.int64)  # first row of each leg's plan
        self.base_consts = fast.pack(plan.scenario.plant_params(params))
        self.consts = np.tile(self.base_consts, (n, 1))
        # per leg: (whole periods n, remainder φ [s]) of the dead time, and the command history
        self.dead = np.zeros((n, 2))
        self.hist = np.zeros((n, 2, 2))
        self.head = 0
        # per leg: its random kick as (start, end, force) on the stacked tables' time axis
        # (row j starts at j dt), so the kernel needs no notion of plans (``kick_force``)
        self.kick = np.zeros((n, 3))
        self.plants: list[Plant] = [plan.scenario.plant] * n
        self.obs = np.zeros((n, self.obs_dim))
        self.out = np.zeros((n, len(OUT)))
        self.noise = np.zeros((n, len(STATE)))  # sensor noise of each STATE signal, SI
        self.homing_s = np.zeros(n)  # [s] how long each leg's last homing took (sim time)
        self.rows_per_plan = plan.n_steps + 1
        self.tab = np.concatenate([p.table() for p in plans])
        self._configure_shared(plan.scenario.plant)

    def _configure_shared(self, pl: Plant) -> None:
        """Regulator quantum and sensors are the rig's, shared by the batch."""
        self.settings = task_settings(self.cfg, self.residual, pl.pressure_quantum_bar * BAR,
                                      pl.encoder_resolution_m)
        std = {"x_m": pl.position_noise_m, "v_mps": pl.velocity_noise_mps,
               "pe_Pa": pl.pressure_noise_bar * BAR, "pf_Pa": pl.pressure_noise_bar * BAR}
        self.noise_std = np.array([std[name] for name in STATE])  # SI, per STATE signal
        self.has_noise = bool(self.noise_std.any())

    def _set_dead_time(self, i: int, dead_time_s: float) -> None:
        """Leg i's dead time as whole periods + remainder; grows the history if it must."""
        dt = self.cfg.dt_s
        n_d = int(np.floor(dead_time_s / dt + 1e-9))
        frac = max(dead_time_s - n_d * dt, 0.0)
        if frac < 1e-12 * dt:
            frac = 0.0
        self.dead[i] = (n_d, frac)
        cap = self.hist.shape[1]
        if n_d + 2 > cap:  # keep every leg's history: the same lags map to the same entries
            new = np.zeros((self.n, n_d + 2, 2))
            for k in range(cap):
                new[:, (self.head - k) % new.shape[1]] = self.hist[:, (self.head - k) % cap]
            self.hist = new

    def draw_noise(self, rows: Any, rngs: list[np.random.Generator]) -> None:
        """Sensor noise for ``rows``, each from its own generator (so legs are independent)."""
        if not self.has_noise:
            return
        for i in rows:
            self.noise[i] = rngs[i].standard_normal(len(STATE)) * self.noise_std

    def reset_rows(self, rows: Any, rngs: list[np.random.Generator],
                   options: dict[str, Any] | None = None) -> None:
        """Start new episodes for ``rows``: draw (or fix) the plant, the initial state; with
        ``options["homing"]``, home each leg to the start as the rig's reset does."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        homing = None
        if isinstance(options, dict) and "homing" in options:  # the rest is checked below
            homing = HomingConfig.from_option(options["homing"])
            options = {k: v for k, v in options.items() if k != "homing"}
        fixed, x0, v0 = self._reset_options(options)
        sc = self.plan.scenario
        if len(self.plans) > 1:  # each new episode follows one of the designs
            which = np.array([rngs[i].integers(len(self.plans)) for i in rows])
        else:
            which = np.zeros(rows.size, dtype=np.int64)
        p0 = np.array([p.p0 for p in self.plans])[which]
        if isinstance(fixed, list):  # one plant per leg (a batch of different rigs)
            per_leg, fixed_of = True, fixed
        else:
            per_leg = bool(sc.randomize.ranges) or any(k in PER_LEG_FIELDS for k in fixed or {})
            fixed_of = [fixed] * self.n
        dx = np.zeros(rows.size)
        dv = np.zeros(rows.size)
        self.kick[rows] = 0.0
        t_start = which * self.rows_per_plan * self.cfg.dt_s  # the episodes' t = 0 on that axis
        if per_leg:  # each leg its own plant
            for r, i in enumerate(rows):
                plant, ep = resolve_plant(sc.plant, sc.randomize.sample(rngs[i]), fixed_of[i])
                dx[r], dv[r] = ep["initial_x_offset_m"], ep["initial_v_offset_mps"]
                t0 = t_start[r] + ep["kick_t_s"]
                self.kick[i] = (t0, t0 + ep["kick_duration_s"], ep["kick_force_N"])
                try:
                    self.consts[i] = fast.pack(sc.plant_params(self.params, plant))
                except ValueError as e:
                    raise ScenarioError(f"episode plant is invalid: {e}") from None
                self.plants[i] = plant
                self._set_dead_time(i, plant.pressure_dead_time_s)
        else:  # the scenario's plant for every leg: no per-leg work
            self.consts[rows] = self.base_consts
            for i in rows:
                self.plants[i] = sc.plant
                self._set_dead_time(i, sc.plant.pressure_dead_time_s)
        self.state[rows, ST_X] = x0 + dx
        self.state[rows, ST_V] = v0 + dv
        self.state[rows, ST_PE:ST_PF + 1] = p0
        self.prev_cmd[rows] = p0
        self.hist[rows] = p0[:, None, :]
        if homing is not None:
            start = options.get("initial_state") is not None
            for r, i in enumerate(rows):
                self._home_row(i, homing, self.plans[which[r]],
                               (x0 + dx[r], v0 + dv[r]) if start else None)
        self.idx[rows] = self.start[rows] = which * self.rows_per_plan
        self.out[rows] = 0.0
        self.out[rows, O_CMDE:O_CMDF + 1] = self.prev_cmd[rows]
        self.out[rows, O_K] = [fast.force_and_stiffness(*self.state[i], self.consts[i])[1]
                               for i in (rows if per_leg or homing else rows[:1])]
        self.draw_noise(rows, rngs)
        observe_rows(self.obs, rows, self.state, self.idx, self.noise, self.settings[S_ENC],
                     self.tab, self.spec)

    def _home_row(self, i: int, cfg: HomingConfig, plan: TaskPlan,
                  start: tuple[float, float] | None) -> None:
        """Home leg i (``mpa_gym.task.homing``) from ``start`` (X, V) with both MPAs vented, or
        from its vented rest, through its own plant (lag, dead time, end stops); the episode then
        starts from the homed state, with the homing's command as the slew limit's last one and
        its commands still in the dead-time line. Raises ``HomingError`` like the rig's reset."""
        c = self.consts[i]
        x, v = (vented_rest(c), 0.0) if start is None else start
        leg = [x, v, 0.0, 0.0]  # X, V, P'_e, P'_f: the plant's state, both MPAs vented
        n_d, phi = int(self.dead[i, 0]), float(self.dead[i, 1])
        past = [np.zeros(2)] * (n_d + 1)  # vented: what the regulators were last told
        lo, hi = END_STOPS_M
        sub = int(self.settings[S_SUB])

        def period(cmd: np.ndarray) -> tuple[float, float]:
            """One control period of the plant under ``cmd``, the dead time as in the kernel:
            the old command until φ, then the new one."""
            past.append(cmd.copy())
            del past[:-(n_d + 2)]
            new, old = past[-1 - n_d], past[-2 - n_d]
            x, v, pe, pf = fast.plant_step(*leg, old[0], old[1], new[0], new[1], phi, 0.0,
                                           self.cfg.dt_s, c, sub)
            if not (np.isfinite(x) and np.isfinite(v)):
                raise HomingError(f"homing (sim): leg {i} left the model's domain")
            if not lo <= x <= hi:  # the rig's end stops
                x, v = min(max(x, lo), hi), 0.0
            leg[:] = x, v, pe, pf
            return x, v

        ctrl = home(cfg, plan, self.cfg, self.params, x, v, np.zeros(2), period)
        x, v, pe, pf = leg
        self.state[i, [ST_X, ST_V, ST_PE, ST_PF]] = (x, v, pe, pf)
        self.prev_cmd[i] = ctrl.cmd
        cap = self.hist.shape[1]
        for k, cmd in enumerate(reversed(past)):  # the latest at the slot before the write head
            self.hist[i, (self.head - 1 - k) % cap] = cmd
        self.homing_s[i] = ctrl.t

    def _reset_options(self, options: dict[str, Any] | None
                       ) -> tuple[dict[str, Any] | None, float, float]:
        """Validate reset options; apply rig-wide ones; return (per-leg plant fields, X0, V0)."""
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"reset options={options!r} must be a dict with the keys "
                             f"{list(RESET_OPTIONS)} (each optional)")
        options = dict(options or {})
        check_keys("reset options", options, RESET_OPTIONS)
        fixed = options.get("plant")
        if isinstance(fixed, list | tuple):  # per leg: only the fields a leg may have its own of
            if len(fixed) != self.n or not all(isinstance(f, dict) for f in fixed):
                raise ValueError(f"options['plant'] as a list must hold one dict of plant fields "
                                 f"per leg ({self.n}), got {fixed!r}")
            for i, f in enumerate(fixed):
                rig = sorted(set(f) - PER_LEG_FIELDS)
                if rig:
                    raise ValueError(f"options['plant'][{i}]: {rig} belong to the whole rig; "
                                     "give them in a single dict, not per leg")
            return list(fixed), *self._start_state(options)
        if fixed is not None and not isinstance(fixed, dict):
            raise ValueError(f"options['plant'] must be a dict of plant fields (or a list of "
                             f"one per leg), got {fixed!r}")
        sc = self.plan.scenario
        shared = {k: check_plant_value(k, v, "options['plant']") for k, v in (fixed or {}).items()
                  if k not in PER_LEG_FIELDS}
        if shared:
            self._configure_shared(dataclasses.replace(sc.plant, **shared))
        return fixed, *self._start_state(options)

    def _start_state(self, options: dict[str, Any]) -> tuple[float, float]:
        """(X0, V0): the scenario's, or options['initial_state']."""
        x0, v0 = self.plan.scenario.start_state()
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
        return x0, v0

    def step(self, action: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Advance every leg one control period (action: (n, 2) float64, as
        ``task.contract.check_action`` returns it)."""
        if self.has_noise:
            self.draw_noise(range(self.n), rngs)
        kernel = step_batch_parallel if self.n >= PARALLEL_MIN_LEGS else step_batch
        kernel(action, self.state, self.prev_cmd, self.idx, self.consts, self.dead, self.hist,
               self.head, self.noise, self.settings, self.tab, self.spec, self.kick, self.obs,
               self.out)
        self.head = (self.head + 1) % self.hist.shape[1]

    @property
    def truncated(self) -> np.ndarray:
        """Legs whose episode has run its full length."""
        return self.truncated_of()

    def truncated_of(self, i: int | None = None) -> Any:
        """Whether leg i's episode has run its full length (a bool), or every leg's (an array,
        ``truncated``); one leg's is read as Python ints, a fraction of the array ops' cost."""
        idx, start = (self.idx, self.start) if i is None else (self.idx.item(i),
                                                                self.start.item(i))
        return idx - start >= self.plan.n_steps

    def plan_of(self, i: int) -> TaskPlan:
        """The plan leg i follows in its current episode."""
        return self.plans[int(self.start[i] // self.rows_per_plan)]

    def info(self, i: int | None = None) -> dict[str, Any]:
        """The step info (``task.contract.step_info``) of leg i, or of every leg as arrays."""
        if i is None:
            j = self.idx
            return step_info(self.out, self.state, self.tab[j], (j - self.start) * self.cfg.dt_s)
        j = self.idx.item(i)
        return step_info(self.out[i], self.state[i], self.tab[j],
                         (j - self.start.item(i)) * self.cfg.dt_s)


__all__ = ["SimEngine", "observe_rows", "resolve_plant", "step_batch"]
