"""Identify the plant from a rig log: ``mpa-gym identify --log LOG [--out FILE.yaml] [--json]``.

The log of a rollout (best: ``mpa-gym rollout --policy excite``) holds, every control period,
the pressure command, the measured pressures and the measured hip height. A log appended to by
several rollouts holds several sessions, each starting with its header: the fit uses one, the
newest by default (``session``), and its control rate from the header. The log is checked
first (``episodes_of``): a step without a finite ``x_m``, ``pressure_bar`` or
``pressure_cmd_bar``, time stamps that do not increase, or a header rate the stamps contradict is
refused, naming the step; each step's period is the loop's measured ``period_s`` (else the step
of ``t_s``), so a stalled or jittery loop is fitted as it ran. The fit is split in two, each a
``scipy.optimize.least_squares`` problem:

1. **Regulator** (lag τ, dead time d, slew limit r, shared by both MPAs): the measured
   pressures against the commands through the regulator of ``RegulatorParams`` (first-order
   lag, rate-limited at r) driven by the command delayed by d (exact solution, the held command
   switching inside a period when d is not a whole number of periods). r shows only where a
   step exceeds r τ (``excite``'s slew probe); otherwise it is kept at 0 (unlimited) and its
   interval is the log's lower bound or unlimited.
2. **Mechanics** (total mass m, γ, C1, C2, and the fidelity effects: braid friction ratio μ_b,
   slider Coulomb F_c and viscous c_s friction): the measured positions against Eq. (15) (with
   the friction of ``mpa.force`` and ``dynamics.slider_friction``, through the packed constants
   of ``fast.pack``) driven by the *measured* pressures (linear between samples), so the two
   fits do not trade errors. c_s V and γ (G_e² + G_f²) V both damp the hip: their sum is well
   determined, their split only through how G_e, G_f vary along the log (the intervals show
   it as wide, correlated ranges of γ and c_s).
   Prediction error over segments: the log is cut into ``segment_s`` pieces, each simulated from
   its own initial state (X0, V0), which are fitted too. Why segments rather than one simulation
   of the whole log (single shooting): the leg is lightly damped (ζ ≈ 0.05), so over a long
   horizon a small parameter error becomes a phase slip and the cost surface fills with local
   minima; a segment shorter than the decay time keeps the cost close to quadratic in the
   parameters, and the free initial states absorb the unknown velocity (the log has none) and
   any slow drift. Each segment's states touch only its own residuals, so the Jacobian is sparse
   and finite differences cost a handful of simulations.

Intervals (``intervals`` in the report, at ``sigmas``, default 2 σ): what the log allows, not a
point. The residuals of both fits are correlated in time (model error: a real loop's timing, the
friction's shape, a segment's drift), so an s² (JᵀJ)⁻¹ covariance, which assumes them independent,
is many times too narrow. The mechanics' intervals are ± sigmas σ of the sandwich covariance with
Newey–West scores over ``HAC_WINDOW_S`` (``_std``), stretched to reach the estimate less its
model bias (``model_bias``: the fit's own error on the log's exact twin, a systematic error the
residuals do not show); the regulator's are profile likelihoods
(``fit_regulator``), which also span what the samples cannot resolve (a dead time between two
sampling instants when there is no lag; a slew limit that no step reached: "r ≥ r_min or
unlimited"), and the dead time's reaches the link's delay below the fit (``link_delay_s``). A
parameter the log does not identify shows as an interval wider than its value, and is named in
the notes. The bladder thickness t is not identifiable apart from C1 and C2 (the model's rubber
term is V_r(t)·(C1 …, C2 …)): it is kept at its nominal value and C1, C2 absorb it (their
intervals are those at the nominal thickness). ``mpa-gym identify --coverage N``
(``agents/rig/coverage.py``) checks the intervals against random emulated rigs.

Validation: the last ``holdout`` fraction of the log is left out of both fits; the identified
model (regulator from the logged commands, then mechanics) is simulated over it from an initial
state fitted to its first ``settle_s``, and the position RMSE over the rest is reported and
plotted against the log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numba
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from mpa_gym.agents.rig.rollout import read_log
from mpa_gym.analysis.scenario import PLANT_RANGES, RANDOMIZABLE, Plant, Scenario, load_scenario
from mpa_gym.model import fast
from mpa_gym.model.jit import JIT
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_range
from mpa_gym.task.config import TaskConfig

MECH = ("mass_kg", "gamma_Ns_per_m", "C1_Pa", "C2_Pa")  # fitted plant keys, mechanics (scaled)
# fitted plant keys, mechanics, the fidelity effects (0 for the paper's plant): (key, scale, upper
# bound); their nominal value is 0, so they are scaled by a typical size instead
FRICTION = (("braid_friction_ratio", 0.01, 0.5), ("slider_friction_N", 1.0, 100.0),
            ("slider_viscous_Ns_per_m", 1.0, 100.0))
REG = ("pressure_lag_s", "pressure_dead_time_s", "pressure_slew_bar_per_s")  # regulator keys
# [s] the span over which the fits' residuals are taken as correlated (``_std``): a segment of
# the mechanics fit, several regulator time constants
HAC_WINDOW_S = 0.5
# The mechanics fit's own resolution: what it gets wrong on a noise-free log of the exact plant
# (its model of the pressures between samples, the friction's smoothing), which no covariance of
# the residuals sees. Measured on noise-free sim logs of six plants (the emulated test rig and
# five random training rigs): about three times the error on the plants whose covariance
# interval was narrowest (mass 3.5e-4 kg, γ 0.62 N s/m, C1 and C2 67 Pa, braid 8e-4, slider
# 0.011 N and 0.08 N s/m); it is added in quadrature to sigmas × σ (``mechanics_intervals``).
# Without it those intervals excluded the truth on 4 of the 42 (plant, value) pairs (a
# friction-free leg's mass to ±0.03 g, 0.09 g off).
# That floor stays; what the fit's model gets wrong on a given log is also measured on the log
# itself (``model_bias``): the sim logs had whole-period dead times, and a dead time that falls
# between samples pulls C1 and C2 apart by up to several kPa, more than 2 σ.
RESOLUTION = {"mass_kg": 1e-3, "gamma_Ns_per_m": 2.0, "C1_Pa": 300.0, "C2_Pa": 300.0,
              "braid_friction_ratio": 2.5e-3, "slider_friction_N": 0.03,
              "slider_viscous_Ns_per_m": 0.25}
# [s] the exact twin's longest RK4 step (``simulate_exact``; the device emulator's is 1 ms)
EXACT_STEP_S = 5e-4


@dataclass(frozen=True)
class LogData:
    """One episode of a rollout log: command j sent at ``t_cmd[j]`` and held until
    ``t_cmd[j + 1]``, the pressures [Pa] and position [m] measured at ``t_meas[j]``."""

    dt: float  # [s] nominal control period
    t_cmd: np.ndarray  # [s] (n + 1,)
    t_meas: np.ndarray  # [s] (n,)
    x: np.ndarray  # (n,)
    p: np.ndarray  # (n, 2)
    cmd: np.ndarray  # (n, 2)
    # [s] the link's delay the time stamps do not show (``link_delay_s``; 0: none, a sim's log)
    link_s: float = 0.0

    def part(self, a: int, b: int) -> LogData:
        """Samples a … b − 1."""
        return LogData(self.dt, self.t_cmd[a:b + 1], self.t_meas[a:b], self.x[a:b],
                       self.p[a:b], self.cmd[a:b], self.link_s)


def _timing(rows: list[dict[str, Any]], t: np.ndarray, dt: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """(command times, measurement times) [s] of a log's steps, from the first command.

    A rig's log says when each command went out and when the telemetry frame its step
    observed arrived (``command_sent_s``, ``telemetry_arrived_s``: ``mpa_gym.hardware.env``'s
    ``LINK_INFO_KEYS``): those are the times. A step's command goes out when the controller
    answers, after its compute, and the newest frame at the period's end is up to one telemetry
    period old, so timed by the schedule (a command at each period's start, its observation a
    period later) the fit would read both as regulator dead time (1.3 ms on the emulated rigs
    of ``mpa-gym identify --coverage``, whose intervals then missed the true dead time). A step
    that sent no command (a stale observation: the device held the last one) holds it on.

    A log without them (a simulation's, or an older rig log), or whose times contradict each
    other (a frame before its command), is timed by the schedule: a
    step's period (start to start) is the loop's measured ``period_s`` where the log has it,
    else the step of the time stamps ``t_s``: a late step (a stall, jitter) held its
    predecessor's command longer, and the fit must see that rather than the nominal period. A
    step's telemetry is read at its deadline, a period ``dt`` after its start, or at the next
    start if that came sooner."""
    n = len(rows)
    sent = np.array([r.get("command_sent_s", math.nan) for r in rows], dtype=float)
    arrived = np.array([r.get("telemetry_arrived_s", math.nan) for r in rows], dtype=float)
    if np.isfinite(arrived).all() and np.isfinite(sent[0]):
        t_cmd = np.empty(n + 1)
        t_cmd[0] = sent[0]
        for j in range(1, n):  # a step that sent nothing held the last command: any time
            # between the frames before and after it times that alike
            t_cmd[j] = sent[j] if np.isfinite(sent[j]) else 0.5 * (arrived[j - 1] + arrived[j])
        t_cmd[n] = max(t_cmd[n - 1], arrived[-1]) + dt
        if np.all(np.diff(t_cmd) > 0) and np.all((arrived >= t_cmd[:-1])
                                                  & (arrived <= t_cmd[1:])):
            return t_cmd - sent[0], arrived - sent[0]
    period = np.array([r.get("period_s", math.nan) for r in rows], dtype=float)[1:]
    period = np.where(np.isfinite(period) & (period > 0), period, np.diff(t))
    t_cmd = np.concatenate([[0.0], np.cumsum(period), [0.0]])
    t_cmd[n] = t_cmd[n - 1] + dt
    return t_cmd, np.minimum(t_cmd[:-1] + dt, t_cmd[1:])


@dataclass(frozen=True)
class Session:
    """One rollout session of a log: its ``{"event": "session"}`` header (None for records
    before any header, e.g. a log written by another tool) and its step records."""

    header: dict[str, Any] | None
    steps: list[dict[str, Any]]


class Sessions(list):  # type: ignore[type-arg]
    """The sessions of a rollout log; ``skipped``: its torn lines (``read_log``) left out."""

    skipped: int = 0


def read_sessions(path: str | Path) -> Sessions:
    """The sessions of a rollout log, oldest first. ``mpa_gym.agents.rig.rollout`` appends to its
    log and starts each session with a header, and episodes are numbered from 0 in each: the header,
    not the episode number, is where one session's steps end and the next one's begin."""

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--log {path}: no such file")
    out = Sessions()
    header: dict[str, Any] | None = None
    steps: list[dict[str, Any]] = []
    started = False  # records (of any kind) before the first header make a session too
    records = read_log(path)
    out.skipped = records.skipped
    for r in records:
        if r.get("event") == "session":
            if started:
                out.append(Session(header, steps))
            header, steps, started = r, [], True
            continue
        started = True
        if "t_s" in r and "event" not in r:
            steps.append(r)
    if started:
        out.append(Session(header, steps))
    return out


def pick_session(sessions: list[Session], session: int | None, path: str | Path
                 ) -> tuple[int, Session]:
    """(index, session): ``session`` counted from 0 (negative: from the end); None: the newest
    session with step records."""
    n = len(sessions)
    if session is None:
        with_steps = [i for i, s in enumerate(sessions) if s.steps]
        if not with_steps:
            raise ValueError(f"--log {path}: no step records (a rollout log has one per control "
                             "period, with t_s, x_m, pressure_bar and pressure_cmd_bar)")
        return with_steps[-1], sessions[with_steps[-1]]
    if isinstance(session, bool) or not isinstance(session, int) or not -n <= session < n:
        raise ValueError(f"--session={session!r}: the log {path} holds {n} session(s); give a "
                         f"whole number in [{-n}, {n - 1}] (negative: counted from the newest)")
    i = session % n
    if not sessions[i].steps:
        raise ValueError(f"--session={session}: session {i} of {path} has no step records "
                         "(stopped before its first episode?)")
    return i, sessions[i]


STEP_KEYS = ("t_s", "x_m", "pressure_bar", "pressure_cmd_bar")  # what the fit reads of a step
RATE_TOLERANCE = 0.01  # relative disagreement of the header's control_hz and the stamps refused


def _column(er: list[dict[str, Any]], key: str, width: int, where: str) -> np.ndarray:
    """The finite numbers of ``key`` in each step (``width`` per step, 0: a scalar); a step
    without it, or with a value that is not ``width`` finite numbers, is named."""
    out = np.full((len(er), max(width, 1)), math.nan)
    for i, r in enumerate(er):
        v = r.get(key)
        try:
            a = np.asarray(v, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            a = np.empty(0)
        if a.size == max(width, 1) and np.all(np.isfinite(a)):
            out[i] = a
            continue
        what = "no " + key if key not in r else f"{key}={v!r}"
        shape = f"{width} finite numbers" if width else "a finite number"
        raise ValueError(f"--log {where}: step {i} (t_s={r.get('t_s')!r}) has {what}; the "
                         f"fit needs {shape} there (a rollout log's steps hold "
                         f"{', '.join(STEP_KEYS)})")
    return out if width else out[:, 0]


def link_delay_s(rows: list[dict[str, Any]]) -> float:
    """[s] How much later than the log's time stamps say the device may have applied a
    command and sampled what it reports: the 95th percentile of the loop's measured command
    latency (``latency_s``: command sent to the telemetry acknowledging it, a round trip that
    holds both), 0 for a log without it (a simulation's)."""
    lat = np.array([r.get("latency_s", math.nan) for r in rows], dtype=float)
    lat = lat[np.isfinite(lat) & (lat >= 0)]
    return float(np.percentile(lat, 95)) if lat.size else 0.0


def episodes_of(s: Session, path: str | Path) -> list[LogData]:
    """The episodes of one session, checked: every step holds ``STEP_KEYS`` as finite numbers,
    the time stamps ``t_s`` increase, and the header's ``control_hz`` (the control period; else
    the median step of ``t_s``) agrees with them within ``RATE_TOLERANCE``. A log that fails
    is refused with the step that fails, not fitted."""
    rate = (s.header or {}).get("control_hz")
    out = []
    for ep in sorted({r.get("episode", 0) for r in s.steps}):
        er = [r for r in s.steps if r.get("episode", 0) == ep]
        where = f"{path} episode {ep}"
        t = _column(er, "t_s", 0, where)
        if t.size < 3:
            continue
        back = np.flatnonzero(np.diff(t) <= 0.0)
        if back.size:
            k = int(back[0]) + 1
            raise ValueError(f"--log {where}: the time stamps do not increase at step {k} "
                             f"(t_s={float(t[k - 1])!r} then {float(t[k])!r}); the fit needs "
                             "the steps in the order they ran (a shuffled or merged log?)")
        step = float(np.median(np.diff(t)))
        if rate:
            dt = 1.0 / float(rate)
            if abs(step - dt) > RATE_TOLERANCE * dt:
                raise ValueError(f"--log {where}: the session header's control_hz={rate!r} "
                                 f"disagrees with the time stamps t_s (median step {step:.6g} "
                                 f"s, i.e. {1.0 / step:.6g} Hz); the fit needs the rate the "
                                 "steps ran at")
        else:
            dt = step
        out.append(LogData(dt, *_timing(er, t, dt), _column(er, "x_m", 0, where),
                           _column(er, "pressure_bar", 2, where) * BAR,
                           _column(er, "pressure_cmd_bar", 2, where) * BAR, link_delay_s(er)))
    if not out:
        raise ValueError(f"--log {path}: no episode with 3 or more steps")
    return out


def load_log(path: str | Path, session: int | None = None) -> list[LogData]:
    """The episodes of one session of a rollout log (``mpa_gym.agents.rig.rollout.read_log`` records
    with ``t_s``): ``session`` as in ``pick_session`` (default the newest with step records)."""
    return episodes_of(pick_session(read_sessions(path), session, path)[1], path)


# ----------------------------------------------------------------------------- regulator
@numba.njit(**JIT)
def _ramp_time(P, u, h, lag, slew):
    """[s] of the next ``h`` that the regulator spends slew-limited from P' = P under u."""
    if slew <= 0.0:
        return 0.0
    return min(max((abs(u - P) - slew * lag) / slew, 0.0), h)


@numba.njit(**JIT)
def simulate_pressure(cmd, t_cmd, t_meas, p_start, lag, dead, slew=0.0, ramp=None):
    """Measured-pressure model: the regulator of ``RegulatorParams`` (first-order lag ``lag``
    with the rate limit ``slew`` [Pa/s], 0: none) driven by the command delayed by ``dead``;
    command j is held from ``t_cmd[j]`` to ``t_cmd[j + 1]``. Exact between switches
    (``fast.regulator_pressure``). ``p_start`` (2,) is the pressure (and the command held)
    before the first command. Returns (n, 2) pressures at the measurement times ``t_meas``;
    ``ramp`` (1,), if given, receives the seconds spent slew-limited (both MPAs)."""
    n = cmd.shape[0]
    out = np.empty((n, 2))
    ramped = 0.0
    for m in range(2):
        P, u, t, k = p_start[m], p_start[m], t_cmd[0], 0
        for j in range(n):
            target = t_meas[j]
            while k < n and t_cmd[k] + dead < target:  # the delayed command switches
                w = t_cmd[k] + dead
                if w > t:
                    ramped += _ramp_time(P, u, w - t, lag, slew)
                    P = fast.regulator_pressure(P, u, w - t, lag, slew)
                    t = w
                u = cmd[k, m]
                k += 1
            if target > t:
                ramped += _ramp_time(P, u, target - t, lag, slew)
                P = fast.regulator_pressure(P, u, target - t, lag, slew)
                t = target
            out[j, m] = P
    if ramp is not None:
        ramp[0] = ramped
    return out


def _slew_Pa(inv_slew: float) -> float:
    """[Pa/s] the slew of its inverse [s/bar] (0: unlimited)."""
    return BAR / inv_slew if inv_slew > 1e-12 else 0.0


@dataclass(frozen=True)
class RegulatorFit:
    """The regulator stage's result (``fit_regulator``)."""

    values: dict[str, float]  # REG keys: lag [s], dead time [s], slew [bar/s] (0: unlimited)
    intervals: dict[str, list[float | None]]  # [low, high]; high None: unbounded (slew)
    std: dict[str, float | None]  # 1 σ from ``_std`` (None: the slew, not identified)
    rmse_bar: float  # [bar] pressure RMSE of the fit
    notes: list[str]


def _kappa(r: np.ndarray, lags: int) -> float:
    """Long-run variance over variance of a residual series (Bartlett weights over ``lags``):
    how many samples count as one independent one (1 for white residuals)."""
    r = r - r.mean()
    v = float(r @ r)
    if v == 0.0:
        return 1.0
    k = 1.0
    for lag in range(1, min(lags, r.size - 1) + 1):
        k += 2.0 * (1.0 - lag / (lags + 1.0)) * float(r[lag:] @ r[:-lag]) / v
    return max(k, 1.0)


def fit_regulator(logs: list[LogData], sigmas: float = 2.0) -> RegulatorFit:
    """Lag τ [s], dead time d [s] and slew r [bar/s] of the regulator, with profile-likelihood
    intervals at ``sigmas``.

    The slew limit is fitted as its inverse ρ = 1/r [s/bar], so that "unlimited" (ρ = 0) is an
    ordinary point of a smooth cost. It shows in the log only where a command step exceeds r τ
    (the ramp phase of ``fast.regulator_pressure``); where the log does not rule out an
    unlimited regulator (ρ's profile interval reaches 0), the slew is reported as 0
    (unlimited) and its interval says what the log allows: r ≥ a bound, or unlimited.

    Intervals: each parameter's profile (the others refitted) is followed out from the optimum
    while the sum of squares stays within sigmas² s² κ of its least value, s² the residual
    variance and κ (``_kappa``) the residuals' long-run variance over their variance, so that
    correlated residuals count for what they are worth. A profile follows the cost where a
    Jacobian cannot: with no lag, a dead time anywhere between two sampling instants fits the
    log equally well (a flat cost, a zero derivative), and its interval is that whole stretch.
    The log's time stamps are the PC's: the device applied a command, and sampled the pressure
    it reports, up to the link's delay later than they say; the dead time cannot be told from
    that delay, so its interval reaches ``link_s`` below the profile's (``link_delay_s``), and
    a slew ramp's duration read off the stamps is uncertain by as much (ρ's interval widened by
    ``link_s`` over the log's largest command step); the samples' jittering age smooths an edge
    like a lag would, so the lag's interval also reaches ``link_s`` below."""
    def sim(theta, d, ramp=None):
        return simulate_pressure(d.cmd, d.t_cmd, d.t_meas, d.p[0], theta[0], theta[1],
                                 _slew_Pa(theta[2]), ramp)

    weights = [np.ones((d.x.size, 2)) for d in logs]

    def residuals(theta):
        return np.concatenate([(w * (sim(theta, d) - d.p) / BAR)[1:].ravel()
                               for d, w in zip(logs, weights, strict=True)])

    lo_b, hi_b = np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 10.0])
    # coarse grid first: the cost is piecewise smooth in the dead time (a kink per period)
    grid = [(lag, dead, rho) for lag in (0.0, 0.01, 0.02, 0.04, 0.08, 0.16)
            for dead in np.arange(0.0, 0.101, 0.005) for rho in (0.0, 0.02, 0.05, 0.2)]
    best = min(grid, key=lambda th: float(np.sum(residuals(np.array(th)) ** 2)))
    sol = least_squares(residuals, np.array(best, dtype=float), bounds=(lo_b, hi_b),
                        diff_step=1e-3, x_scale=[0.01, 0.01, 0.01])
    link = max(d.link_s for d in logs)
    if link > 0.0:
        # the time stamps are uncertain by about the link's delay: a sample on a fast edge
        # (slope Ṗ) is uncertain by Ṗ·link on top of the noise, so it counts for less
        # (effective variance); else the few edge samples, where the slew limit shows, would
        # fit the loop's timing error as a slew limit, with a confident, wrong interval
        noise = float(np.std(sol.fun))
        for i, d in enumerate(logs):
            slope = np.gradient(d.p / BAR, d.t_meas, axis=0)
            weights[i] = np.sqrt(noise**2 / (noise**2 + (slope * link) ** 2))
        sol = least_squares(residuals, sol.x, bounds=(lo_b, hi_b), diff_step=1e-3,
                            x_scale=[0.01, 0.01, 0.01])
    theta = sol.x.copy()
    sd = _std(sol, _times([np.repeat(np.arange(d.x.size - 1), 2) for d in logs]),
              _lags(logs))
    ssr = float(sol.fun @ sol.fun)
    # per channel, so that the two MPAs' interleaved rows do not read as one series
    kappa = max(_kappa(sol.fun[m::2], _lags(logs)) for m in range(2))
    limit = ssr + sigmas**2 * ssr / sol.fun.size * kappa

    def profile(i: int, step: float) -> tuple[float, float]:
        """The stretch of θ_i around the optimum whose profile cost stays within ``limit``,
        to ``step``: steps doubling outward from the optimum until the cost leaves the limit
        (or θ_i its bound), then halving back onto the crossing. Conservative: each end is the
        first value found outside, or the bound."""
        free = [j for j in range(3) if j != i]

        def cost(v: float, start: np.ndarray) -> tuple[float, np.ndarray]:
            th = theta.copy()
            th[i] = v

            def res(z):
                th[free] = z
                return residuals(th)

            z = least_squares(res, start, bounds=(lo_b[free], hi_b[free]), diff_step=1e-3,
                              x_scale=0.01, max_nfev=50)
            return float(z.fun @ z.fun), z.x

        ends = []
        for sign in (-1.0, 1.0):
            inside, start, h = theta[i], theta[free], step
            outside = None
            while outside is None:
                v = min(max(inside + sign * h, lo_b[i]), hi_b[i])
                if v == inside:
                    break  # at the bound: the interval reaches it
                c, z = cost(v, start)
                if c > limit:
                    outside = v
                else:
                    inside, start, h = v, z, 2.0 * h
            while outside is not None and abs(outside - inside) > step:
                v = 0.5 * (inside + outside)
                c, z = cost(v, start)
                if c > limit:
                    outside = v
                else:
                    inside, start = v, z
            ends.append(inside if outside is None else outside)
        return ends[0], ends[1]

    lag, dead, rho = (float(v) for v in theta)
    lag_iv = profile(0, 5e-4)
    dead_iv = profile(1, 2.5e-4)
    rho_iv = profile(2, 2e-3)
    # ρ is the ramp's time per bar; its duration, read off the time stamps, is uncertain by the
    # link's delay, so ρ is by link / (the log's largest command step) either way
    step = max(float(np.max(np.abs(np.diff(d.cmd, axis=0)))) for d in logs) / BAR
    if link > 0.0 and step > 0.0:
        rho_iv = (max(0.0, rho_iv[0] - link / step), rho_iv[1] + link / step)
    notes = []
    if link > 0.0:
        notes.append(f"pressure_dead_time_s, pressure_lag_s: the intervals reach {link * 1e3:.2f} "
                     "ms below the fit, the link's delay the log's time stamps do not show "
                     "(it cannot be told from them); the slew's is widened by as much of a ramp")
    est = {"pressure_lag_s": lag, "pressure_dead_time_s": dead, "pressure_slew_bar_per_s": 0.0}
    std: dict[str, float | None] = {"pressure_lag_s": float(sd[0]),
                                    "pressure_dead_time_s": float(sd[1]),
                                    "pressure_slew_bar_per_s": None}
    # r = 1/ρ: ρ's interval [a, b] is r in [1/b, 1/a], and a = 0 admits an unlimited regulator
    slew_iv: list[float | None] = [1.0 / rho_iv[1] if rho_iv[1] > 0 else math.inf,
                                   1.0 / rho_iv[0] if rho_iv[0] > 0 else None]
    if rho_iv[0] > 0.0:  # the interval excludes an unlimited regulator
        est["pressure_slew_bar_per_s"] = 1.0 / rho
        std["pressure_slew_bar_per_s"] = float(sd[2]) / rho**2  # delta method, r = 1/ρ
    else:
        notes.append(f"pressure_slew_bar_per_s is kept at 0 (unlimited): no command step of the "
                     f"log reached the slew limit (largest step {step:.3g} bar); the log says "
                     f"r ≥ {slew_iv[0]:.3g} bar/s or unlimited; excite with larger steps "
                     "(excite.slew_step_bar) to identify it")
    intervals: dict[str, list[float | None]] = {
        "pressure_lag_s": [max(0.0, lag_iv[0] - link), lag_iv[1]],
        "pressure_dead_time_s": [max(0.0, dead_iv[0] - link), dead_iv[1]],
        "pressure_slew_bar_per_s": slew_iv}
    err = np.concatenate([((sim(theta, d) - d.p) / BAR)[1:].ravel() for d in logs])
    return RegulatorFit(est, intervals, std, float(np.sqrt(np.mean(err**2))), notes)


# ----------------------------------------------------------------------------- mechanics
@numba.njit(**JIT)
def simulate_segments(states, starts, length, t, p, consts, substeps, out):
    """Eq. (15) over each segment from its own initial state (X0, V0) = ``states[s]`` at the
    sample times ``t``, the pressures linear between the measured samples; writes the simulated
    X at the segment's samples into ``out`` (the segment's first sample is X0 itself)."""
    for s in range(starts.shape[0]):
        i0 = starts[s]
        X, V = states[s, 0], states[s, 1]
        out[i0] = X
        for j in range(i0, min(i0 + length, t.shape[0]) - 1):
            h = (t[j + 1] - t[j]) / substeps
            for k in range(substeps):
                a0 = k / substeps
                am, a1 = a0 + 0.5 / substeps, a0 + 1.0 / substeps
                pe0 = p[j, 0] + a0 * (p[j + 1, 0] - p[j, 0])
                pf0 = p[j, 1] + a0 * (p[j + 1, 1] - p[j, 1])
                pem = p[j, 0] + am * (p[j + 1, 0] - p[j, 0])
                pfm = p[j, 1] + am * (p[j + 1, 1] - p[j, 1])
                pe1 = p[j, 0] + a1 * (p[j + 1, 0] - p[j, 0])
                pf1 = p[j, 1] + a1 * (p[j + 1, 1] - p[j, 1])
                X, V = fast._rk4(X, V, pe0, pf0, pem, pfm, pe1, pf1, 0.0, h, consts)
            out[j + 1] = X


def plant_of(values: dict[str, float]) -> Plant:
    """The scenario ``Plant`` of identified values (plant keys)."""
    return Plant(**values)


def consts_of(values: dict[str, float], params: Params = DEFAULT_PARAMS) -> np.ndarray:
    """The compiled model's constants for identified plant values."""
    return fast.pack(Scenario("fit").plant_params(params, plant_of(values)))


def _segments(n: int, length: int) -> np.ndarray:
    return np.arange(0, max(n - 2, 1), length, dtype=np.int64)


def _initial_states(d: LogData, starts: np.ndarray) -> np.ndarray:
    """(X0, V0) guesses: the measured X and a central difference of it."""
    v = np.gradient(d.x, d.t_meas)
    return np.stack([d.x[starts], v[starts]], axis=1)


def fit_mechanics(logs: list[LogData], nominal: dict[str, float], segment_s: float,
                  substeps: int = 2, params: Params = DEFAULT_PARAMS
                  ) -> tuple[dict[str, float], dict[str, float], float]:
    """Fitted (m, γ, C1, C2, braid friction μ_b, slider friction F_c and c_s), their standard
    deviations, and the fit's position RMSE [m]. The friction terms reach the kernel through
    the packed constants (``fast.pack``: mu_b, F_c, c_s) like the others."""
    keys = MECH + tuple(k for k, _, _ in FRICTION)
    npar = len(keys)
    scale = np.array([nominal[k] for k in MECH] + [s for _, s, _ in FRICTION])
    parts = []  # (log, segment starts, segment length)
    for d in logs:
        length = max(3, round(segment_s / d.dt))
        parts.append((d, _segments(d.x.size, length), length))
    n_states = 2 * sum(s.size for _, s, _ in parts)
    n_res = sum(d.x.size for d, _, _ in parts)
    bufs = [np.empty(d.x.size) for d, _, _ in parts]

    def unpack(z):
        return dict(zip(keys, (float(v) for v in z[:npar] * scale), strict=True))

    def residuals(z):
        c = consts_of(unpack(z), params)
        out, k = [], npar
        for (d, starts, length), buf in zip(parts, bufs, strict=True):
            st = z[k:k + 2 * starts.size].reshape(-1, 2)
            k += 2 * starts.size
            simulate_segments(st, starts, length, d.t_meas, d.p, c, substeps, buf)
            out.append(buf - d.x)
        r = np.concatenate(out)
        return np.where(np.isfinite(r), r, 1.0)  # a diverged segment: a large, finite cost

    # the friction terms start just inside their lower bound 0 (the paper's plant)
    z0 = np.concatenate([np.ones(len(MECH)), np.full(len(FRICTION), 0.1)]
                        + [_initial_states(d, s).ravel() for d, s, _ in parts])
    sparsity = lil_matrix((n_res, npar + n_states), dtype=int)
    sparsity[:, :npar] = 1
    row, col = 0, npar
    for d, starts, length in parts:
        for i0 in starts:
            stop = min(i0 + length, d.x.size)
            sparsity[row + i0:row + stop, col:col + 2] = 1
            col += 2
        row += d.x.size
    lo = np.concatenate([[0.2, 0.0, 0.2, 0.0], np.zeros(len(FRICTION)),
                         np.full(n_states, -np.inf)])
    hi = np.concatenate([[5.0, 20.0, 5.0, 50.0], [h / s for _, s, h in FRICTION],
                         np.full(n_states, np.inf)])
    x_scale = np.concatenate([np.full(npar, 0.1), np.tile([1e-3, 1e-2], n_states // 2)])
    sol = least_squares(residuals, z0, bounds=(lo, hi), jac_sparsity=sparsity, x_scale=x_scale,
                        method="trf", xtol=1e-10, ftol=1e-10, max_nfev=200)
    sd = _std(sol, _times([np.arange(d.x.size) for d, _, _ in parts]), _lags(logs))[:npar] \
        * scale
    est = unpack(sol.x)
    return est, dict(zip(keys, (float(v) for v in sd), strict=True)), \
        float(np.sqrt(np.mean(sol.fun ** 2)))


def _times(per_log: list[np.ndarray]) -> np.ndarray:
    """The sample index of each residual row over logs placed one after the other."""
    out, offset = [], 0
    for t in per_log:
        out.append(t + offset)
        offset += int(t[-1]) + 1 if t.size else 0
    return np.concatenate(out)


def _lags(logs: list[LogData]) -> int:
    """Newey–West lags: ``HAC_WINDOW_S`` in samples."""
    return max(1, round(HAC_WINDOW_S / min(d.dt for d in logs)))


def _std(sol: Any, times: np.ndarray, lags: int) -> np.ndarray:
    """Standard deviations of the fitted values from the sandwich covariance
    (JᵀJ)⁻¹ S (JᵀJ)⁻¹, with S the Newey–West estimate (Bartlett weights over ``lags`` samples)
    of the long-run covariance of the scores g_t = Σ_{rows at sample t} J_row r_row.

    Why not s² (JᵀJ)⁻¹: that assumes independent residuals, and a fit's residuals are anything
    but (model error: the timing of a real loop, the friction's shape, a segment's drift, are
    correlated over tens of samples); on emulated rigs it gave intervals ten times too narrow,
    excluding the true values. The sandwich form holds under residuals correlated over up to
    ``lags`` samples and still reduces to s² (JᵀJ)⁻¹ for white ones. ``times``: the sample index
    of each residual row (non-decreasing)."""
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    g = J * sol.fun[:, None]
    G = np.zeros((int(times[-1]) + 1, J.shape[1]))
    np.add.at(G, times, g)
    S = G.T @ G
    for lag in range(1, min(lags, G.shape[0] - 1) + 1):
        gamma = G[lag:].T @ G[:-lag]
        S += (1.0 - lag / (lags + 1.0)) * (gamma + gamma.T)
    A = np.linalg.pinv(J.T @ J)
    return np.sqrt(np.clip(np.diag(A @ S @ A), 0.0, None))


# ----------------------------------------------------------------------------- validation
def simulate_full(d: LogData, values: dict[str, float], x0: float, v0: float, substeps: int = 2,
                  params: Params = DEFAULT_PARAMS) -> tuple[np.ndarray, np.ndarray]:
    """The identified model over a log stretch from the logged commands: (X, pressures)."""
    p = simulate_pressure(d.cmd, d.t_cmd, d.t_meas, d.p[0], values["pressure_lag_s"],
                          values["pressure_dead_time_s"],
                          values.get("pressure_slew_bar_per_s", 0.0) * BAR)
    x = np.empty(d.x.size)
    simulate_segments(np.array([[x0, v0]]), np.zeros(1, dtype=np.int64), d.x.size, d.t_meas, p,
                      consts_of(values, params), substeps, x)
    return x, p


@numba.njit(**JIT)
def _simulate_exact(cmd, t_cmd, t_meas, x0, v0, p0, dead, consts, out_x, out_p):
    X, V, Pe, Pf = x0, v0, p0[0], p0[1]
    ce, cf = p0[0], p0[1]
    t, k, n = t_cmd[0], 0, cmd.shape[0]
    for j in range(t_meas.shape[0]):
        target = t_meas[j]
        while t < target:
            stop = target
            if k < n and t_cmd[k] + dead <= target:
                stop = max(t_cmd[k] + dead, t)
            h = stop - t
            if h > 0.0:
                X, V, Pe, Pf = fast.plant_step(X, V, Pe, Pf, ce, cf, ce, cf, 0.0, 0.0, h, consts,
                                               max(1, int(np.ceil(h / EXACT_STEP_S))))
                t = stop
            if k < n and t_cmd[k] + dead <= t:  # the delayed command reaches the regulator
                ce, cf = cmd[k, 0], cmd[k, 1]
                k += 1
        out_x[j] = X
        out_p[j, 0], out_p[j, 1] = Pe, Pf


def simulate_exact(d: LogData, values: dict[str, float], params: Params = DEFAULT_PARAMS
                   ) -> LogData:
    """The log ``d`` would be from a rig that is exactly ``values``: the plant run
    continuously from the log's first state, its regulator driven by the logged commands at
    the logged times (command j from ``t_cmd[j]`` + dead time, switching between samples
    where the dead time says), the pressures exact between samples (``fast.plant_step``, RK4
    steps of at most ``EXACT_STEP_S`` split at every switch), sampled at the log's times,
    noise-free. ``fit_mechanics`` sees the pressures only at the samples (linear between
    them); what it then gets wrong on this twin is its model's error on this log
    (``model_bias``)."""
    x = np.empty(d.x.size)
    p = np.empty((d.x.size, 2))
    x0, v0 = _initial_states(d, np.zeros(1, dtype=np.int64))[0]
    _simulate_exact(d.cmd, d.t_cmd, d.t_meas, float(x0), float(v0), d.p[0].astype(float),
                    float(values["pressure_dead_time_s"]), consts_of(values, params), x, p)
    return replace(d, x=x, p=p)


def model_bias(logs: list[LogData], values: dict[str, float], nominal: dict[str, float],
               segment_s: float, params: Params = DEFAULT_PARAMS) -> dict[str, float]:
    """Per mechanics value, how far ``fit_mechanics`` lands from ``values`` on the logs'
    exact twins (``simulate_exact``): the pull of the fit's own model of the pressures
    between samples on these logs, a systematic error no covariance of the residuals sees.
    On emulated rigs (``identify --coverage``) the twins of the true plants reproduced most
    of the fit's error: C1 by −2.6, −5.7 and −13.3 kPa where the emulator's logs gave −4.9,
    −6.9 and −14.9 kPa, beyond 2 σ."""
    twins = [simulate_exact(d, values, params) for d in logs]
    est, _, _ = fit_mechanics(twins, nominal, segment_s, params=params)
    return {k: est[k] - values[k] for k in est}


def validate(d: LogData, values: dict[str, float], settle_s: float,
             params: Params = DEFAULT_PARAMS) -> tuple[float, np.ndarray, np.ndarray, int]:
    """(position RMSE after the first ``settle_s``, simulated X, simulated pressures, index
    where the RMSE window starts) of the identified model over the held-out stretch ``d``."""
    k = max(3, round(settle_s / d.dt))
    guess = _initial_states(d, np.zeros(1, dtype=np.int64))[0]

    def res(s):
        return (simulate_full(d, values, s[0], s[1], params=params)[0] - d.x)[:k]

    s0 = least_squares(res, guess, x_scale=[1e-3, 1e-2]).x
    x, p = simulate_full(d, values, s0[0], s0[1], params=params)
    return float(np.sqrt(np.mean((x - d.x)[k:] ** 2))), x, p, k


def _split(d: LogData, frac: float) -> tuple[LogData, LogData]:
    cut = round(d.x.size * (1.0 - frac))
    return d.part(0, cut), d.part(cut, d.x.size)


def identify(log: str | Path, out: str | Path | None = None, scenario: Any = "nominal",
             plot: str | Path | None = None, holdout: float = 0.2, segment_s: float = 0.5,
             settle_s: float = 0.3, sigmas: float = 2.0,
             params: Params = DEFAULT_PARAMS, session: int | None = None) -> dict[str, Any]:
    """Fit the plant to a rollout log (module docstring); returns the report of
    ``mpa-gym identify --json``. ``out``: write a scenario YAML (``scenario``'s reference and
    inputs, the estimate as its plant, ``randomize`` over the intervals at ``sigmas``).
    ``session``: which session of the log to fit (index, negative from the end; default the
    newest with step records): a log appended to by several rollouts holds several."""
    check_range("--holdout", holdout, 0.05, 0.5)
    check_range("segment_s", segment_s, 0.05, 10.0, unit="s")
    sessions = read_sessions(log)
    index, chosen = pick_session(sessions, session, log)
    logs = episodes_of(chosen, log)
    longest = max(range(len(logs)), key=lambda i: logs[i].x.size)
    fit_logs = list(logs)
    fit_logs[longest], held = _split(logs[longest], holdout)
    if held.x.size * held.dt < 2 * settle_s or fit_logs[longest].x.size * held.dt < 2:
        raise ValueError(f"--log {log}: {logs[longest].x.size * held.dt:.2f} s of steps is too "
                         "short to fit and validate; log at least 10 s (mpa-gym rollout --policy "
                         "excite --episode-s 30)")
    base = load_scenario(scenario)
    nom_p = base.plant_params(params)
    nominal = {"mass_kg": nom_p.leg.m, "gamma_Ns_per_m": nom_p.mpa.gamma, "C1_Pa": nom_p.mpa.C1,
               "C2_Pa": max(nom_p.mpa.C2, 100.0)}
    reg = fit_regulator(fit_logs, sigmas)
    mech, mech_sd, fit_rmse = fit_mechanics(fit_logs, nominal, segment_s, params=params)
    values = {**mech, **reg.values}
    unc: dict[str, float | None] = {**mech_sd, **reg.std, "thickness_m": None}
    bias = model_bias(fit_logs, values, nominal, segment_s, params)
    intervals = {**mechanics_intervals(mech, mech_sd, sigmas, bias), **reg.intervals}
    rmse, x_sim, p_sim, k = validate(held, values, settle_s, params)
    plant = {"extra_mass_kg": 0.0, **{k_: float(v) for k_, v in values.items()},
             "thickness_m": float(nom_p.mpa.thickness)}
    weak = [k_ for k_ in MECH if intervals[k_][1] - intervals[k_][0] > abs(plant[k_])]
    report: dict[str, Any] = {
        "plant": plant, "uncertainty": unc, "intervals": intervals, "sigmas": sigmas,
        "model_bias": bias,
        "validation_rmse_m": rmse, "scenario_yaml": None, "fit_rmse_m": fit_rmse,
        "pressure_fit_rmse_bar": reg.rmse_bar, "holdout_s": held.x.size * held.dt,
        "session": {"index": index, "sessions": len(sessions),
                    **{k: (chosen.header or {}).get(k) for k in ("started_utc", "policy",
                                                                 "control_hz")}},
        "notes": ["thickness_m is kept nominal: only V_r(t)·C1 and V_r(t)·C2 are identifiable "
                  "(C1_Pa, C2_Pa are the values at the nominal thickness)",
                  f"intervals: ± {sigmas:g} σ of the sandwich covariance with correlated "
                  f"residuals (mechanics; reaching the estimate less its model bias, the fit's "
                  f"error on the log's exact twin), the profile likelihood at {sigmas:g} σ "
                  f"(regulator)",
                  *reg.notes],
    }
    if weak:
        report["notes"].append(f"not identified by this log (interval wider than the value): "
                               f"{', '.join(weak)}")
    report["skipped_lines"] = sessions.skipped
    if sessions.skipped:
        report["notes"].insert(0, f"{sessions.skipped} torn line(s) of the log skipped (a "
                               "rollout killed mid-write)")
    if len(sessions) > 1:
        report["notes"].insert(0, f"the log holds {len(sessions)} sessions; fitted session "
                               f"{index} ({_describe(chosen)}), the others left out")
    if plot is None:
        plot = Path(log).with_suffix(".identify.png")
    report["plot"] = str(_plot(held, x_sim, p_sim, k, rmse, Path(plot)))
    if out is not None:
        report["scenario_yaml"] = str(write_scenario(out, base, plant, intervals))
    return report


def _describe(s: Session) -> str:
    h = s.header
    if h is None:
        return f"{len(s.steps)} steps before the first session header"
    return (f"policy {h.get('policy', '?')}, started {h.get('started_utc', '?')}, "
            f"{len(s.steps)} steps")


def mechanics_intervals(est: dict[str, float], sd: dict[str, float], sigmas: float,
                        bias: dict[str, float] | None = None) -> dict[str, list[float | None]]:
    """[low, high] = the stretch from the estimate to the estimate less its model bias
    (``model_bias``; none: 0), widened by √((``sigmas`` σ)² + resolution²)
    (``RESOLUTION``) each way, inside each field's allowed range. The estimate is the fit's;
    the interval reaches the value the bias says the rig more likely has."""
    out: dict[str, list[float | None]] = {}
    for key, v in est.items():
        lo_ok, hi_ok, _, _ = PLANT_RANGES[key]
        half = math.hypot(sigmas * sd[key], RESOLUTION[key])
        corrected = v - (bias or {}).get(key, 0.0)
        out[key] = [max(min(v, corrected) - half, lo_ok), min(max(v, corrected) + half, hi_ok)]
    return out


def write_scenario(out: str | Path, base: Scenario, plant: dict[str, float],
                   intervals: dict[str, list[float | None]]) -> Path:
    """A scenario YAML: ``base``'s reference, inputs and duration, the estimate as the plant,
    ``randomize`` drawing each identified field from its interval (inside the field's range).
    A slew the log bounds only below (interval [r_min, None]: r ≥ r_min or unlimited) is drawn
    from [r_min, the task's command slew limit] in half the episodes and left unlimited (the
    plant's 0) in the others."""
    import yaml

    d = base.to_dict()
    d["name"] = Path(out).stem
    d["description"] = "identified from a rig log (mpa-gym identify)"
    d["plant"] = {**{k: v for k, v in d.get("plant", {}).items()
                     if k not in plant and k not in ("mass_kg",)}, **plant}
    rnd: dict[str, Any] = {}
    for key, (lo, hi) in intervals.items():
        if key not in RANDOMIZABLE:
            continue
        lo_ok, hi_ok, low_open, _ = PLANT_RANGES[key]
        lo = max(float(lo), lo_ok + (1e-9 * max(abs(plant[key]), 1.0) if low_open else 0.0))
        if hi is None:
            hi = max(lo, TaskConfig().slew_bar_per_s)
            rnd[key] = {"range": [lo, min(float(hi), hi_ok)], "p_off": 0.5}
        else:
            rnd[key] = [lo, max(lo, min(float(hi), hi_ok))]
    d["randomize"] = rnd
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    load_scenario(path)  # it must load as written
    return path


def _plot(held: LogData, x_sim: np.ndarray, p_sim: np.ndarray, k: int, rmse: float,
          path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = held.t_meas - held.t_cmd[0]
    fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    ax[0].plot(t, held.x * 1e3, label="logged X", lw=1.2)
    ax[0].plot(t, x_sim * 1e3, "--", label="identified model", lw=1.2)
    ax[0].axvspan(0, t[k], color="0.9", label="initial-state fit")
    ax[0].set_ylabel("X [mm]")
    ax[0].set_title(f"held-out segment: position RMSE {rmse * 1e3:.3f} mm")
    ax[0].legend(loc="upper right")
    for m, name in enumerate(("P'_e", "P'_f")):
        ax[1].plot(t, held.p[:, m] / BAR, lw=1.0, label=f"logged {name}")
        ax[1].plot(t, p_sim[:, m] / BAR, "--", lw=1.0, label=f"model {name}")
    ax[1].set_ylabel("pressure [bar]")
    ax[1].set_xlabel("t [s] (from the start of the held-out segment)")
    ax[1].legend(loc="upper right", ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def show(o: dict[str, Any]) -> str:
    lines = [f"identified plant (estimate, interval at {o['sigmas']:g} σ):"]
    for k, v in o["plant"].items():
        iv = o["intervals"].get(k)
        if iv is None:
            lines.append(f"  {k:<24} {v:12.6g}  (kept)")
            continue
        hi = "unlimited" if iv[1] is None else f"{iv[1]:.6g}"
        lines.append(f"  {k:<24} {v:12.6g}  [{iv[0]:.6g}, {hi}]")
    lines.append(f"fit: position RMSE {o['fit_rmse_m'] * 1e3:.3f} mm, pressure RMSE "
                 f"{o['pressure_fit_rmse_bar'] * 1e3:.2f} mbar")
    lines.append(f"validation on the held-out {o['holdout_s']:.1f} s: position RMSE "
                 f"{o['validation_rmse_m'] * 1e3:.3f} mm (plot: {o['plot']})")
    if o["scenario_yaml"]:
        lines.append(f"scenario: {o['scenario_yaml']}")
    lines += [f"note: {n}" for n in o["notes"]]
    return "\n".join(lines)


__all__ = ["LogData", "Session", "Sessions", "identify", "load_log", "read_sessions",
           "simulate_pressure", "simulate_segments"]
