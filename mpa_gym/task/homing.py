"""Closed-loop homing: bring the leg from wherever it rests to the episode's start and hold it.

Shared by the hardware env's ``reset`` and the sim envs' ``reset(options={"homing": ...})``, so a
sim episode can start as a rig episode does. The law, every control period dt:

- a setpoint s moves from the measured start position toward X_start at ``approach_mps``;
- feedforward: the extensor pressure that holds the *nominal* leg at rest at s with the flexor at
  its start pressure P'_f(0) (Eq. 5 at V = 0, F = m g; F is affine in P'_e, so one division);
- feedback on the extensor: ΔP'_e = k_p (s − X) + k_i ∫(s − X) dt − k_d V, bounded by
  ±``max_correction_bar`` (the integral is frozen, not wound up, while the bound is hit): the
  integral absorbs what the nominal model gets wrong (load, mass, muscles, friction), the
  velocity term damps the lightly damped leg (ζ ≈ 0.05 at X = 0.8 m);
- the flexor goes to P'_f(0); both commands are slew-limited to ``slew_bar_per_s`` and clipped to
  [0, p_max], so homing never jerks the leg.

It is done when s has reached X_start and the leg has stayed within ``tolerance_m`` of X_start
and ``velocity_tolerance_mps`` of rest for ``hold_s``; it fails after ``timeout_s``. The last
command is the one the episode's safety layer starts from (its slew limit counts from there),
so the hand-over has no step of its own.

The gains are conservative for the nominal leg (k_p adds 160 N/m to the leg's ~460 N/m at
X = 0.8 m, the integral settles in ~0.5 s, k_d adds ~24 N s/m of damping); in simulation they home
every leg of mass −20 … +50 % and C1 ±20 % from its vented rest within 7 s, with regulator lags
up to 40 ms plus dead times up to 30 ms (``tests/test_homing.py`` checks corners of that box; a
longer dead time needs a smaller ``kd_bar_s_per_m``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mpa_gym.design.feedforward import P_MAX_DEFAULT
from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_keys, check_range
from mpa_gym.task.config import END_STOPS_M


class HomingError(RuntimeError):
    """Homing did not bring the leg to the start in time; the message names what was measured."""


@dataclass(frozen=True)
class HomingConfig:
    """Settings of the homing controller (module docstring)."""

    tolerance_m: float = 0.001  # [m] |X − X_start| that counts as arrived
    velocity_tolerance_mps: float = 0.01  # [m/s] |V| that counts as at rest
    hold_s: float = 0.3  # [s] how long the leg must stay within both tolerances
    timeout_s: float = 20.0  # [s] give up (and vent, on the rig) after this long
    approach_mps: float = 0.05  # [m/s] speed of the setpoint from the rest position to X_start
    kp_bar_per_m: float = 10.0  # [bar/m] proportional gain on the extensor
    ki_bar_per_m_s: float = 50.0  # [bar/(m s)] integral gain
    kd_bar_s_per_m: float = 1.5  # [bar s/m] velocity (damping) gain
    max_correction_bar: float = 3.0  # [bar] bound of the feedback correction (anti-windup)
    slew_bar_per_s: float = 10.0  # [bar/s] largest command change per second while homing
    # [s] telemetry age that stops homing on the rig (the slow, slew-limited law tolerates more
    # than an episode's stale_s; the device's watchdog still vents if commands stop)
    stale_s: float = 0.1

    def __post_init__(self) -> None:
        check_range("homing.tolerance_m", self.tolerance_m, 0.0, 0.02, low_open=True, unit="m")
        check_range("homing.velocity_tolerance_mps", self.velocity_tolerance_mps, 0.0, 0.5,
                    low_open=True, unit="m/s")
        check_range("homing.hold_s", self.hold_s, 0.0, 10.0, unit="s")
        check_range("homing.timeout_s", self.timeout_s, 0.1, 600.0, unit="s")
        check_range("homing.approach_mps", self.approach_mps, 0.0, 0.5, low_open=True,
                    unit="m/s")
        check_range("homing.kp_bar_per_m", self.kp_bar_per_m, 0.0, 200.0, unit="bar/m")
        check_range("homing.ki_bar_per_m_s", self.ki_bar_per_m_s, 0.0, 500.0, unit="bar/(m s)")
        check_range("homing.kd_bar_s_per_m", self.kd_bar_s_per_m, 0.0, 50.0, unit="bar s/m")
        check_range("homing.max_correction_bar", self.max_correction_bar, 0.0, P_MAX_DEFAULT / BAR,
                    unit="bar")
        check_range("homing.slew_bar_per_s", self.slew_bar_per_s, 0.0, 100.0, low_open=True,
                    unit="bar/s")
        check_range("homing.stale_s", self.stale_s, 1e-3, 1.0, unit="s")

    @classmethod
    def from_option(cls, option: Any) -> HomingConfig | None:
        """``True`` → the defaults, a dict → those fields, ``False`` / ``None`` → no homing."""
        if option is None or option is False:
            return None
        if option is True:
            return cls()
        if isinstance(option, HomingConfig):
            return option
        if isinstance(option, dict):
            check_keys("homing", option, [f.name for f in dataclasses.fields(cls)])
            return cls(**option)
        raise ValueError(f"homing={option!r} must be true, false or a dict of "
                         f"{[f.name for f in dataclasses.fields(cls)]}")


class HomingController:
    """The homing law (module docstring) for one leg; no I/O: ``command`` per control period."""

    def __init__(self, cfg: HomingConfig, x_start: float, p_start: np.ndarray, dt: float,
                 p_max_Pa: float, params: Params = DEFAULT_PARAMS) -> None:
        self.cfg, self.x_start, self.dt, self.p_max = cfg, float(x_start), float(dt), p_max_Pa
        self.pf = float(p_start[1])
        self.consts = fast.pack(params)
        self.weight = params.leg.m * params.leg.g
        self.t = 0.0
        self.integ = 0.0
        self.setpoint = math.nan
        self.cmd = np.zeros(2)
        self.at_rest_s = 0.0
        self.done = False

    def holding_pressure(self, x: float) -> float:
        """[Pa] extensor pressure holding the nominal leg at rest at X = x (flexor at P'_f(0));
        may be negative where the muscles alone hold more than the weight."""
        f0 = fast.ground_force(x, 0.0, 0.0, self.pf, self.consts)
        f1 = fast.ground_force(x, 0.0, BAR, self.pf, self.consts)
        return (self.weight - f0) / (f1 - f0) * BAR

    def start(self, x: float, pressures: np.ndarray) -> None:
        """Begin from the measured position and pressures (the commands start there)."""
        self.setpoint = float(x)
        self.cmd = np.clip(np.asarray(pressures, dtype=float), 0.0, self.p_max)
        self.t, self.integ, self.at_rest_s, self.done = 0.0, 0.0, 0.0, False

    def arrived(self, x: float, v: float) -> bool:
        """Whether (x, v) is at the start within the tolerances (and the ramp has reached it).
        The envs hand over only at a state that is, after :attr:`done`: the state after the
        last homing command may have left the tolerance the decision was made in."""
        c = self.cfg
        return self.setpoint == self.x_start and abs(x - self.x_start) < c.tolerance_m and \
            abs(v) < c.velocity_tolerance_mps

    def command(self, x: float, v: float) -> np.ndarray:
        """[Pa] (extensor, flexor) command for this period, from the measured X, V; updates
        ``done``. Raises ``HomingError`` past the timeout."""
        c, dt = self.cfg, self.dt
        self.t += dt
        step = c.approach_mps * dt
        self.setpoint += min(max(self.x_start - self.setpoint, -step), step)
        e = self.setpoint - x
        bound = c.max_correction_bar
        corr_p = c.kp_bar_per_m * e - c.kd_bar_s_per_m * v
        integ = self.integ + e * dt
        corr = corr_p + c.ki_bar_per_m_s * integ
        if abs(corr) <= bound:  # anti-windup: integrate only while the correction is free
            self.integ = integ
        corr = min(max(corr_p + c.ki_bar_per_m_s * self.integ, -bound), bound)
        target = np.array([self.holding_pressure(self.setpoint) + corr * BAR, self.pf])
        d = c.slew_bar_per_s * BAR * dt
        self.cmd = np.clip(np.clip(target, self.cmd - d, self.cmd + d), 0.0, self.p_max)
        arrived = self.arrived(x, v)
        self.at_rest_s = self.at_rest_s + dt if arrived else 0.0
        self.done = arrived and self.at_rest_s >= c.hold_s
        if not self.done and self.t > c.timeout_s:
            raise HomingError(
                f"homing: the leg did not settle at X = {self.x_start:.4f} m within "
                f"{c.timeout_s:g} s (measured X = {x:.4f} m, V = {v:+.4f} m/s, commanding "
                f"({self.cmd[0] / BAR:.2f}, {self.cmd[1] / BAR:.2f}) bar, feedback correction "
                f"{corr:+.2f} bar of ±{bound:g}; tolerance {c.tolerance_m * 1e3:g} mm, "
                f"{c.velocity_tolerance_mps:g} m/s); check the supply pressure, the load and "
                "the leg")
        return self.cmd


def home(cfg: HomingConfig, plan: Any, task: Any, params: Params, x: float, v: float,
         pressures: np.ndarray, period: Callable[[np.ndarray], tuple[float, float]]
         ) -> HomingController:
    """Home one leg: the homing loop of the sim envs' and the rig's reset, written once.

    From the measured (``x``, ``v``) and ``pressures`` [Pa], every control period the law
    (:class:`HomingController`, toward the plan's X̂(0), flexor to its P'_f(0)) gives a command
    and ``period(command)`` applies it for one period, returning the newest measured (X, V):
    the sim steps its plant there, the rig sends the command and reads its telemetry (either may
    raise to stop). The loop ends when the law is done and the newest state is within the
    tolerances too (the hand-over rule of :meth:`HomingController.arrived`). Returns the
    controller: ``cmd`` is the last command (the one the episode's slew limit starts from), ``t``
    the time homing took. Raises ``HomingError`` past the timeout.
    """
    ctrl = HomingController(cfg, float(plan.x_ref[0]), plan.p0, task.dt_s, task.p_max_bar * BAR,
                            params)
    ctrl.start(x, pressures)
    while True:
        x, v = period(ctrl.command(x, v))
        if ctrl.done and ctrl.arrived(x, v):
            return ctrl


def vented_rest(consts: np.ndarray) -> float:
    """[m] where a leg with both MPAs vented rests: the static equilibrium F(X, 0, 0, 0) = m g
    inside the task's reach (the rubber holds the knee), else the lower end stop."""
    from scipy.optimize import brentq

    m, g = consts[fast.M], consts[fast.G]
    f = lambda x: fast.ground_force(x, 0.0, 0.0, 0.0, consts) - m * g  # noqa: E731
    lo, hi = 0.69, 0.86  # F(X) is monotonic here; below, the model leaves its length domain
    if f(lo) > 0.0 > f(hi):
        return float(brentq(f, lo, hi, xtol=1e-9))
    return END_STOPS_M[0]
