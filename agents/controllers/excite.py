"""A safe excitation for system identification: ``mpa-gym rollout --policy excite``.

On top of the analytic feedforward (``MPALegResidual-v0``'s zero action) it adds pressure
perturbations that make every parameter of the plant show in the log:

- extensor: half a logarithmic chirp (``chirp_f0_hz`` → ``chirp_f1_hz`` over ``chirp_period_s``,
  repeated), which sweeps the leg's resonance (mass against stiffness, the damping γ at its peak),
  plus half a random binary sequence;
- flexor: a random binary sequence of its own: steps held for a random ``prbs_hold_s`` range, whose
  edges show the regulators' lag and dead time and whose levels load the muscles statically (C1,
  C2 against the weight);
- both: a slew probe, ``slew_step_bar`` on the extensor and on the flexor the step that cancels
  its force on the nominal model (so the leg hardly moves: both MPAs stiffen), held
  ``slew_hold_s`` once every ``slew_every_s``. A regulator's slew limit r shows only on a step
  larger than r τ (its ramp phase); the ±``amplitude_bar`` steps are too small for most rigs.

Each perturbation but the probe is bounded by ``amplitude_bar``. The leg is lightly damped (ζ ≈
0.05), so a sweep through its resonance would swing it by centimetres: a velocity feedback on
the extensor, −``damping_bar_s_per_m`` · V (bounded by ``amplitude_bar`` too), damps it to ζ ≈
0.3; it does not hide anything from the identification, which uses the measured pressures,
whatever set them. For the same reason a slow integral of X̂ − X (``centering_bar_per_m_s``, its
crossover well below the chirp's lowest frequency) takes out the sag of a leg heavier than the
model, so the excitation runs around the reference; it starts (bumplessly) at the correction the
rig's homing left: the measured extensor pressure minus the feedforward's at the first step. A
position guard fades the perturbation out (over ``guard_fade_s``) while |X − X̂| exceeds
``guard_m`` and back in once it is below half of it, so the leg stays near the reference on any
plausible rig; the env's safety layer (slew limit, pressure clip, position bounds) still applies
on top. The sequence is a function of the seed and the step count only, so a rollout is
repeatable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, check_range
from mpa_gym.task.contract import OBS_PE as OPE
from mpa_gym.task.contract import OBS_V as OV
from mpa_gym.task.contract import OBS_X as OX
from mpa_gym.task.contract import OBS_XREF as OXR
from mpa_gym.task.plan import TaskPlan


@dataclass(frozen=True)
class ExciteConfig:
    """Settings of the excitation (module docstring)."""

    amplitude_bar: float = 0.1  # [bar] bound of each MPA's perturbation
    damping_bar_s_per_m: float = 1.5  # [bar s/m] velocity feedback on the extensor
    centering_bar_per_m_s: float = 10.0  # [bar/(m s)] slow integral of X̂ − X on the extensor
    centering_max_bar: float = 2.0  # [bar] bound of the centering correction
    chirp_f0_hz: float = 0.3  # [Hz] chirp start frequency
    chirp_f1_hz: float = 5.0  # [Hz] chirp end frequency
    chirp_period_s: float = 8.0  # [s] one sweep; then it starts again
    prbs_min_hold_s: float = 0.05  # [s] shortest level of the random binary sequences
    prbs_max_hold_s: float = 0.5  # [s] longest level
    slew_step_bar: float = 0.6  # [bar] the slew probe: extensor stepped up by this much …
    slew_hold_s: float = 0.15  # [s] … for this long …
    slew_every_s: float = 2.0  # [s] … once in this period (0 height: no probe)
    guard_m: float = 0.015  # [m] |X − X̂| beyond which the perturbation fades out
    guard_fade_s: float = 0.2  # [s] fade-out / fade-in time
    seed: int = 0  # the random sequences' seed

    def __post_init__(self) -> None:
        check_range("excite.amplitude_bar", self.amplitude_bar, 0.0, 1.0, low_open=True,
                    unit="bar")
        check_range("excite.damping_bar_s_per_m", self.damping_bar_s_per_m, 0.0, 20.0,
                    unit="bar s/m")
        check_range("excite.centering_bar_per_m_s", self.centering_bar_per_m_s, 0.0, 100.0,
                    unit="bar/(m s)")
        check_range("excite.centering_max_bar", self.centering_max_bar, 0.0, 5.0, unit="bar")
        check_range("excite.chirp_f0_hz", self.chirp_f0_hz, 0.0, 20.0, low_open=True, unit="Hz")
        check_range("excite.chirp_f1_hz", self.chirp_f1_hz, self.chirp_f0_hz, 20.0, unit="Hz")
        check_range("excite.chirp_period_s", self.chirp_period_s, 0.5, 600.0, unit="s")
        check_range("excite.prbs_min_hold_s", self.prbs_min_hold_s, 1e-3, 10.0, unit="s")
        check_range("excite.prbs_max_hold_s", self.prbs_max_hold_s, self.prbs_min_hold_s, 10.0,
                    unit="s")
        check_range("excite.slew_step_bar", self.slew_step_bar, 0.0, 1.0, unit="bar")
        check_range("excite.slew_every_s", self.slew_every_s, 0.1, 600.0, unit="s")
        check_range("excite.slew_hold_s", self.slew_hold_s, 0.0, self.slew_every_s / 2,
                    unit="s")
        check_range("excite.guard_m", self.guard_m, 1e-3, 0.05, unit="m")
        check_range("excite.guard_fade_s", self.guard_fade_s, 1e-3, 5.0, unit="s")


class ExcitePolicy:
    """The excitation behind the baselines' ``predict`` (one observation at a time)."""

    def __init__(self, plan: TaskPlan, cfg: ExciteConfig | None = None) -> None:
        self.plan = plan
        self.task = plan.cfg
        self.cfg = cfg or ExciteConfig()
        # the slew probe's steps (extensor, flexor) [bar]: slew_step_bar on the extensor and
        # on the flexor what cancels its force at the start of the reference (nominal model)
        c = fast.pack(DEFAULT_PARAMS)
        x0, (pe, pf) = plan.x_ref[0], plan.p0
        f0 = fast.force_and_stiffness(x0, 0.0, pe, pf, c)[0]
        dfe = fast.force_and_stiffness(x0, 0.0, pe + BAR, pf, c)[0] - f0
        dff = fast.force_and_stiffness(x0, 0.0, pe, pf + BAR, c)[0] - f0
        self._probe_bar = self.cfg.slew_step_bar * np.array([1.0, -dfe / dff])
        self.reset()

    def reset(self) -> None:
        self._k = 0
        self._gain = 1.0
        self._integ = 0.0
        self._rng = np.random.default_rng(self.cfg.seed)
        self._levels = np.zeros(2)
        self._until = np.zeros(2)  # [s] when each sequence's level changes

    def perturbation_bar(self, t: float) -> np.ndarray:
        """[bar] (extensor, flexor) perturbation at time t (advance t monotonically)."""
        c = self.cfg
        for m in range(2):
            while t >= self._until[m]:
                self._levels[m] = self._rng.choice((-1.0, 1.0))
                self._until[m] += self._rng.uniform(c.prbs_min_hold_s, c.prbs_max_hold_s)
        tau = math.fmod(t, c.chirp_period_s)
        k = math.log(c.chirp_f1_hz / c.chirp_f0_hz) / c.chirp_period_s
        phase = 2 * math.pi * c.chirp_f0_hz * (math.expm1(k * tau) / k if k > 0 else tau)
        a = c.amplitude_bar
        on = math.fmod(t, c.slew_every_s) < c.slew_hold_s
        probe = self._probe_bar if on else np.zeros(2)
        return np.array([0.5 * a * (math.sin(phase) + self._levels[0]),
                         a * self._levels[1]]) + probe

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation, dtype=float)
        if obs.ndim != 1:
            raise ValueError(f"observation has shape {obs.shape}; the excitation takes one")
        dt, c = self.task.dt_s, self.cfg
        if state is None or (episode_start is not None and bool(np.any(episode_start))):
            self.reset()
            if c.centering_bar_per_m_s > 0.0:  # bumpless: start at what holds the leg now
                held = obs[OPE] - self.plan.ff[0, 0] / BAR
                self._integ = min(max(held, -c.centering_max_bar), c.centering_max_bar) \
                    / c.centering_bar_per_m_s
        err = abs(obs[OX] - obs[OXR])
        if err > c.guard_m:
            self._gain = max(0.0, self._gain - dt / c.guard_fade_s)
        elif err < 0.5 * c.guard_m:
            self._gain = min(1.0, self._gain + dt / c.guard_fade_s)
        dp = self._gain * self.perturbation_bar(self._k * dt)
        a, cm = c.amplitude_bar, c.centering_max_bar
        dp[0] += min(max(-c.damping_bar_s_per_m * obs[OV], -a), a)
        if c.centering_bar_per_m_s > 0.0:
            self._integ = min(max(self._integ + (obs[OXR] - obs[OX]) * dt,
                                  -cm / c.centering_bar_per_m_s), cm / c.centering_bar_per_m_s)
            dp[0] += c.centering_bar_per_m_s * self._integ
        self._k += 1
        return np.clip(dp / self.task.residual_scale_bar, -1.0, 1.0), self._k
