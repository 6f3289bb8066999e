"""Open-loop scenario simulation: the nominal feedforward against a possibly different plant.

Sec. 3.2 and 4.4: the pressures are designed on the nominal model (Eq. 16, 22, 25) and applied as
functions of time to the true plant of the scenario (mass, γ, C1, C2, bladder thickness, load,
regulator lag and dead time; open loop, so sensor noise plays no part), with the
scenario's initial state and impulses. Integration is fixed-step RK4 on a grid that also contains
every disturbance edge, so the piecewise-constant force is integrated without straddling a jump.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from mpa_gym.analysis.scenario import Scenario, load_scenario
from mpa_gym.design.feedforward import InfeasibleDesignError
from mpa_gym.model.dynamics import (
    has_pressure_state,
    integrate_reference,
    plant_rhs,
    regulator_pressure,
    rk4_step_u,
)
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, RegulatorParams, check_range

DT_DEFAULT = 5.0e-3  # [s] RK4 step, held to 1e-6 m of solve_ivp (docs/design.md#targets)
METRIC_PERIODS = 3  # rmse and max error over the last three periods (docs/design.md#cli)


def metric_window(t: np.ndarray, period_s: float) -> np.ndarray:
    """Mask of the samples every report takes its metrics over (``simulate``, the evaluation
    report, rollouts): the last ``METRIC_PERIODS`` reference periods of a trace at the times
    ``t``, both ends included, t_end − 3T ≤ t ≤ t_end (the whole trace if it is shorter)."""
    return t >= t[-1] - METRIC_PERIODS * period_s - 1e-9


def whole_periods(t: np.ndarray, period_s: float) -> slice:
    """:func:`metric_window` less its first sample, for a trace sampled evenly: exactly
    ``METRIC_PERIODS`` periods of N = round(T / Δt) samples each, which the robustness sweep's
    periodic/aperiodic split needs (it averages the periods sample by sample)."""
    n = len(t)
    per = round(period_s / ((t[-1] - t[0]) / (n - 1))) if n > 1 else 1
    return slice(max(0, n - METRIC_PERIODS * per), n)


DT_MIN_S, DT_MAX_S = 1e-4, 0.1  # [s] RK4 steps of `simulate` (shortest: 300,000 for 30 s)


class SimulationError(RuntimeError):
    """The plant left the region where the model is defined (NaN state); results so far kept."""

    def __init__(self, msg: str, partial: SimulationResult | None = None) -> None:
        super().__init__(msg)
        self.partial = partial


@dataclass(frozen=True)
class SimulationResult:
    scenario: Scenario
    t: np.ndarray  # [s]
    x: np.ndarray  # [m] X
    v: np.ndarray  # [m/s] V
    x_ref: np.ndarray  # [m] X̂
    pressure_cmd: np.ndarray  # [Pa] (P'_e, P'_f) commanded, shape (n, 2)
    pressure: np.ndarray  # [Pa] (P'_e, P'_f) acting on the plant, shape (n, 2)
    f_ext: np.ndarray  # [N] external force on the hip

    @property
    def error(self) -> np.ndarray:
        """[m] X − X̂."""
        return self.x - self.x_ref

    def metric_window(self) -> np.ndarray:
        """Mask of the last three periods (:func:`metric_window`)."""
        return metric_window(self.t, self.scenario.reference.period)

    @property
    def rmse_m(self) -> float:
        e = self.error[self.metric_window()]
        return float(np.sqrt(np.mean(e**2)))

    @property
    def max_abs_err_m(self) -> float:
        return float(np.max(np.abs(self.error[self.metric_window()])))

    def to_json(self) -> dict[str, Any]:
        """The `mpa-gym simulate --json` object (docs/design.md#cli)."""
        return {
            "scenario": self.scenario.name,
            "rmse_m": self.rmse_m,
            "max_abs_err_m": self.max_abs_err_m,
            "t": self.t.tolist(),
            "x": self.x.tolist(),
            "x_ref": self.x_ref.tolist(),
            "v": self.v.tolist(),
            "pe_bar": (self.pressure[:, 0] / BAR).tolist(),
            "pf_bar": (self.pressure[:, 1] / BAR).tolist(),
        }


def _time_grid(duration: float, dt: float, breakpoints: list[float]) -> np.ndarray:
    n = round(duration / dt)
    base = np.linspace(0.0, n * dt, n + 1)
    if abs(n * dt - duration) > 1e-9:
        base = np.append(base[base < duration], duration)
    grid = np.union1d(base, [b for b in breakpoints if 0.0 < b < duration])
    # drop points closer than 1e-9 s to a neighbour (a breakpoint already on the grid)
    keep = np.concatenate([[True], np.diff(grid) > 1e-9])
    return grid[keep]


def _external_force(sc: Scenario, t: np.ndarray, side: str) -> np.ndarray:
    """Impulse forces at times t; at an edge, ``side`` picks the value just after ("right")
    or just before ("left") it, so each RK4 step sees the force of its own interval."""
    f = np.zeros_like(t)
    for d in sc.disturbances:
        a, b = d.t_s, d.t_s + d.duration_s
        on = (t >= a) & (t < b) if side == "right" else (t > a) & (t <= b)
        f += np.where(on, d.force_N, 0.0)
    return f


def simulate(
    scenario: str | dict[str, Any] | Scenario,
    params: Params = DEFAULT_PARAMS,
    *,
    dt: float = DT_DEFAULT,
    output_dt: float | None = 0.01,
    method: str = "rk4",
) -> SimulationResult:
    """Run the scenario's nominal feedforward against its true plant.

    Parameters
    ----------
    scenario : a name in configs/scenarios, a YAML path, a dict or a Scenario.
    params : the nominal (design) model; the plant is it plus the scenario's overrides.
    dt : RK4 step [s].
    output_dt : spacing of the returned samples [s] (a multiple of dt); None keeps every step.
        Metrics are computed on what is returned.
    method : "rk4" (fixed step) or "reference" (scipy DOP853, rtol 1e-10, for accuracy checks).
    """
    sc = load_scenario(scenario)
    check_range("dt", dt, DT_MIN_S, DT_MAX_S, unit="s")
    if method not in ("rk4", "reference"):
        raise ValueError(f"method={method!r} must be 'rk4' or 'reference'")
    # an infeasible design (pressures outside [0, p_max], MPA lengths outside their domain)
    # would be simulated with pressures no regulator gives: refuse it with design's report
    try:
        design = sc.design(params).require_feasible(p_max=sc.inputs.p_max_bar * BAR)
    except InfeasibleDesignError as e:
        raise InfeasibleDesignError(f"scenario {sc.name!r}: the feedforward design is {e}"
                                    ) from None
    plant = sc.plant_params(params)
    reg = plant.regulator
    # A slew limit without a lag has no smooth ODE (dP'/dt = r sign(c − P')): RK4 then takes the
    # pressures from the rate limiter's solution over each step, P'_n + clip(c(t) − P'_n, ±r s),
    # exact while the command moves monotonically within a step, and integrates (X, V) alone.
    limiter = reg.lag == 0.0 and reg.slew > 0.0
    lag = has_pressure_state(plant)  # P' is part of the state
    mech = dataclasses.replace(plant, regulator=RegulatorParams()) if limiter else plant
    # the grid holds every impulse edge and the end of the dead time (where the delayed command
    # starts to move: a kink of the input)
    breaks = sorted({e for d in sc.disturbances for e in (d.t_s, d.t_s + d.duration_s)}
                    | ({reg.dead_time} if reg.dead_time > 0.0 else set()))
    grid = _time_grid(sc.duration_s, dt, breaks)
    x0, v0 = sc.start_state()
    u_start = design.pressures(0.0)
    y0 = np.array([x0, v0, *u_start] if lag else [x0, v0])

    if output_dt is None:
        keep = np.ones(grid.size, dtype=bool)
    else:
        check_range("output_dt", output_dt, dt, sc.duration_s, unit="s")
        k = output_dt / dt
        ratio = round(k)
        if abs(k - ratio) > 1e-9:
            raise ValueError(f"output_dt={output_dt} must be a whole multiple of dt={dt}")
        steps = np.round(grid / dt)
        keep = (np.abs(grid / dt - steps) < 1e-6) & (steps % ratio == 0)

    dead = sc.plant.pressure_dead_time_s

    def u_at(t: np.ndarray, side: str) -> np.ndarray:
        cmd = design.pressures(np.maximum(t - dead, 0.0))  # a dead time delays the command
        return np.concatenate([cmd, _external_force(sc, t, side)[..., None]], axis=-1)

    if method == "reference":
        if limiter:
            raise ValueError("method='reference' needs pressure_lag_s > 0 when "
                             "pressure_slew_bar_per_s is set (a pure rate limiter has no "
                             "smooth ODE for solve_ivp)")

        def rhs(t: float, y: np.ndarray) -> np.ndarray:
            return plant_rhs(y, u_at(np.array([t]), "right")[0], plant)

        ys = integrate_reference(rhs, grid, y0, breakpoints=tuple(breaks))
    else:
        h = np.diff(grid)
        u0 = u_at(grid[:-1], "right")
        um = u_at(grid[:-1] + 0.5 * h, "right")
        u1 = u_at(grid[1:], "left")
        ys = np.empty((grid.size, y0.size))
        ys[0] = y = y0

        def f(y: np.ndarray, u: np.ndarray) -> np.ndarray:
            return plant_rhs(y, u, mech)

        for i in range(h.size):
            if limiter:  # the rate limiter's pressures at the stage times, from P'_n
                hi = float(h[i])
                a0 = regulator_pressure(y[2:], u0[i, :2], 0.0, plant)
                am = regulator_pressure(y[2:], um[i, :2], 0.5 * hi, plant)
                a1 = regulator_pressure(y[2:], u1[i, :2], hi, plant)
                xv = rk4_step_u(f, y[:2], np.append(a0, u0[i, 2]), np.append(am, um[i, 2]),
                                np.append(a1, u1[i, 2]), hi)
                y = np.concatenate([xv, a1])
            else:
                y = rk4_step_u(f, y, u0[i], um[i], u1[i], float(h[i]))
            if not np.all(np.isfinite(y)):
                part = _result(sc, design, grid[: i + 1], ys[: i + 1], lag, keep[: i + 1])
                # what the scenario changed: the disturbances so far and the plant's overrides
                kicks = [f"disturbances[{j}] (force_N={d.force_N:g} N from t_s={d.t_s:g} s "
                         f"for {d.duration_s:g} s)" for j, d in enumerate(sc.disturbances)
                         if d.t_s <= grid[i + 1]]
                kicks += [f"plant.{f.name}={getattr(sc.plant, f.name)!r}"
                          for f in dataclasses.fields(sc.plant)
                          if getattr(sc.plant, f.name) != f.default]
                raise SimulationError(
                    f"scenario {sc.name!r}: the state left the model's domain at t = "
                    f"{grid[i + 1]:.4f} s (last state X = {ys[i, 0]:.5f} m, V = {ys[i, 1]:.4f} "
                    f"m/s)" + (f" under {', '.join(kicks)}" if kicks else "")
                    + f"; the {i + 1} steps before it are in .partial", part)
            ys[i + 1] = y
    return _result(sc, design, grid, ys, lag, keep)


def _result(sc: Scenario, design: Any, grid: np.ndarray, ys: np.ndarray, lag: bool,
            keep: np.ndarray) -> SimulationResult:
    t = grid[keep]
    ys = ys[keep]
    cmd = design.pressures(np.maximum(t - sc.plant.pressure_dead_time_s, 0.0))
    applied = ys[:, 2:4] if lag else cmd
    return SimulationResult(sc, t, ys[:, 0], ys[:, 1], design.reference.position(t), cmd,
                            applied, _external_force(sc, t, "right"))
