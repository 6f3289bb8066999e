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
- ``AdaptiveFeedforward`` (``afc``): feedforward + adaptive feedforward cancellation of the
  periodic error (Bodson, Sacks and Khosla, "Harmonic generation in adaptive feedforward
  cancellation schemes", IEEE TAC 1994): the error's mean and first harmonic at the
  reference's frequency ω₀ are integrated into an antagonistic correction (+u, −u) that learns
  the periodic command the feedforward lacks. It adapts over seconds, so it acts at ω₀ alone,
  where the regulator's dead time is a small phase (40 ms is 4.8° at 1/3 Hz): the averaged
  loop is stable while the plant's phase at ω₀ stays within ±90°, a delay margin of ~0.75 s,
  where pid's and mbfb's bandwidth limits them to ~30 ms. It is the supervisor's last resort
  (``mpa_gym.agents.controllers.supervisor``), not a tracking controller: it is slow and knows
  only ω₀.
- ``RepetitiveControl`` (``rc``): feedforward + pid + a plug-in repetitive controller (Hara,
  Yamamoto, Omata and Nakano, "Repetitive control system", IEEE TAC 1988; Tomizuka, Tsao and
  Chew's discrete-time prototype, 1989): a delay line of one reference period that learns, period
  by period, the error that repeats with the reference, every harmonic within its robustness
  filter's band, and shifts the error pid sees by it. Its lead and filter are designed from the
  nominal model (``repetitive_design``).

Both PID laws are what a control engineer would field: the derivative acts on the measured
velocity error through a first-order low-pass filter (time constant ``tf_s``; 0: unfiltered), and
the integrator is clamped against windup (conditional integration: while the last output was
saturated — the residual clip or the pressure limits — the integrator does not integrate an
error that pushes further into the saturation). Their gains are tuned by
``mpa_gym.agents.training.tune_baselines`` (Optuna TPE) on the training plants of the PPO config;
``TUNED_ON`` says on what and with which budget, and the evaluation report repeats it.

A baseline adds at most ``AUTHORITY_BAR`` to each feedforward pressure, whatever env it acts
in: the residual env's default scale, in which the baselines are tuned and evaluated. A
supervisor's fallback acts in the learned policy's env, whose scale is the run's (the default
config's is 2 bar). With the env's scale as its clip, the rc a supervisor started was not the
rc of the report's column: on random rig 22 it tracked at 1.36 mm against the column's 2.62,
on rig 38 at 2.28 against 1.91. With its own authority it is the same controller, so a figure
the report marks as a fallback's is that baseline's.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np

from mpa_gym.design.feedforward import FeedforwardDesign, affine_in_pressures
from mpa_gym.model.dynamics import force_terms
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_range
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.contract import OBS_COS as OCOS
from mpa_gym.task.contract import OBS_KREF as OK
from mpa_gym.task.contract import OBS_KREF_SCALE, obs_names
from mpa_gym.task.contract import OBS_SIN as OSIN
from mpa_gym.task.contract import OBS_V as OV
from mpa_gym.task.contract import OBS_VREF as OVR
from mpa_gym.task.contract import OBS_X as OX
from mpa_gym.task.contract import OBS_XREF as OXR
from mpa_gym.task.plan import TaskPlan, make_plan

# [bar] the largest correction a baseline adds to each feedforward pressure (module docs):
# the residual env's default scale, whatever env the baseline acts in
AUTHORITY_BAR = TaskConfig().residual_scale_bar


class Policy(Protocol):
    """What evaluation needs of a controller: SB3's ``predict``."""

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]: ...


# A repetitive controller's memory must contract from one period to the next by at least this
# factor at every frequency above half the reference's, on the nominal model and every delay of
# its margin (``repetitive_design``): below 1 for convergence, with room for the model's error.
CONTRACTION_MAX = 0.95


@dataclass
class _PlanPolicy:
    """A controller that knows the env's plan (reference and nominal feedforward)."""

    plan: TaskPlan
    params: Params = field(default_factory=lambda: DEFAULT_PARAMS)
    # A stack of controllers of one kind (:func:`stack`): row i of every batch follows
    # row_plans[i]; empty: every row follows ``plan``.
    row_plans: tuple[TaskPlan, ...] = ()

    @property
    def cfg(self) -> TaskConfig:
        return self.plan.cfg

    @property
    def action_limit(self) -> float:
        """The largest residual action it gives, in the env's [−1, 1] units: ``AUTHORITY_BAR``
        over the env's scale (1 where the env's scale is smaller)."""
        return min(AUTHORITY_BAR / self.cfg.residual_scale_bar, 1.0)

    def _within_authority(self, actions: np.ndarray) -> np.ndarray:
        """A policy's ``actions`` (env units) clipped to what this controller may command
        (``action_limit``; NaN kept): a take-over continues the part of the held command it
        can make, so its integrator does not start wound up past its own clip."""
        return np.clip(actions, -self.action_limit, self.action_limit)

    @classmethod
    def stack_rows(cls, policies: list[_PlanPolicy]) -> _PlanPolicy:
        """:func:`stack`: one set of gains and task config, row i following policy i's plan."""
        first = policies[0]
        if any(p.row_plans for p in policies):
            raise ValueError("stack: a stack of controllers does not stack again")

        def gains(p: _PlanPolicy) -> dict[str, Any]:
            return {k: v for k, v in vars(p).items() if k not in ("plan", "row_plans")}

        if any(p.cfg != first.cfg or gains(p) != gains(first) for p in policies):
            raise ValueError("stack: controllers of one kind, gains and task config only")
        return dataclasses.replace(first, row_plans=tuple(p.plan for p in policies))

    def _check_rows(self, n: int) -> None:
        if self.row_plans and n != len(self.row_plans):
            raise ValueError(f"a stack of {len(self.row_plans)} controllers got a batch of {n} "
                             "observations; row i is controller i's")

    def _plan_rows(self, n: int) -> list[tuple[TaskPlan, Any]]:
        """(plan, rows) pairs covering a batch of n rows; rows whose plans have equal designs
        (most scenarios differ only in the plant) share one pair."""
        self._check_rows(n)
        if not self.row_plans:
            return [(self.plan, slice(None))]
        groups: dict[Any, tuple[TaskPlan, list[int]]] = {}
        for i, p in enumerate(self.row_plans):
            groups.setdefault(p.design, (p, []))[1].append(i)
        return [(p, np.array(rows)) for p, rows in groups.values()]

    def _per_row(self, n: int, value: Any) -> Any:
        """value(plan) for each row: a scalar (one plan) or an (n,) array."""
        self._check_rows(n)
        if not self.row_plans:
            return value(self.plan)
        return np.array([value(p) for p in self.row_plans])

    def _time(self, obs: np.ndarray) -> np.ndarray:
        """[s] time within the period, from the observed phase."""
        T = self._per_row(obs.shape[0], lambda p: p.design.reference.period)
        return np.mod(np.arctan2(obs[:, OSIN], obs[:, OCOS]) / (2 * math.pi) * T, T)

    def _feedforward(self, obs: np.ndarray) -> np.ndarray:
        """[Pa] (n, 2): the command the env's feedforward applies over this step (mid-step),
        the design's pressures at the observed time plus half a period: looked up in a table
        of one reference period (``_period_feedforward``) when the observed time is a step
        of the control grid, as every env's is, else evaluated."""
        dt = self.cfg.dt_s
        t = self._time(obs)
        out = np.empty((obs.shape[0], 2))
        for plan, rows in self._plan_rows(obs.shape[0]):
            table = _period_feedforward(plan.design, dt)
            steps = t[rows] / dt
            j = np.rint(steps)
            if table is not None and np.all(np.abs(steps - j) < 1e-3):
                out[rows] = table[j.astype(np.int64) % len(table)]
            else:
                out[rows] = plan.design.pressures(t[rows] + 0.5 * dt)
        return out

    def _pid(self, obs: np.ndarray, state: Any, episode_start: np.ndarray | None, kp: float,
             ki: float, kd: float, tf: float, offset: np.ndarray | float = 0.0
             ) -> tuple[np.ndarray, np.ndarray]:
        """(Kp e + Ki ∫e + Kd ė_f, state) for e = X̂ − X + ``offset`` [m] (a repetitive
        controller's correction of the reference; the derivative acts on the measurement
        alone), ė_f the measured V̂ − V low-pass filtered with time constant ``tf`` [s].

        The state, one row per observation, is (∫e, ė_f, s): s ∈ {−1, 0, 1} is the direction
        the last output saturated in (``_saturated`` sets it), and ∫e stops integrating errors
        of that sign while it is non-zero (anti-windup by clamping).
        """
        n = obs.shape[0]
        fresh = np.ones(n, dtype=bool) if state is None else np.zeros(n, dtype=bool)
        st = np.zeros((n, 3)) if state is None else np.array(state, dtype=float).reshape(n, 3)
        if episode_start is not None:
            fresh |= np.asarray(episode_start, dtype=bool).reshape(-1)
        st[fresh] = 0.0
        e = obs[:, OXR] - obs[:, OX] + offset
        de = obs[:, OVR] - obs[:, OV]
        st[:, 0] += np.where(self._winding(st, e), 0.0, e * self.cfg.dt_s)
        alpha = self.cfg.dt_s / (tf + self.cfg.dt_s)
        st[:, 1] = np.where(fresh, de, st[:, 1] + alpha * (de - st[:, 1]))
        return kp * e + ki * st[:, 0] + kd * st[:, 1], st

    def _hold(self, observation: np.ndarray, state: Any, rows: np.ndarray, output: np.ndarray,
              ki: float) -> np.ndarray:
        """``state`` (zeros if None) with ``rows`` set to continue ``output`` (n,): ∫e such that
        Ki ∫e = output, the derivative filter at the measured V̂ − V, no saturation."""
        obs = np.asarray(observation, dtype=np.float64).reshape(len(rows), -1)
        n = obs.shape[0]
        st = np.zeros((n, 3)) if state is None else np.array(state, dtype=float).reshape(n, 3)
        st[rows] = np.stack([output / ki, obs[:, OVR] - obs[:, OV], np.zeros(n)],
                            axis=-1)[rows]
        return st

    def _antagonistic(self, u: np.ndarray, st: np.ndarray, single: bool
                      ) -> tuple[np.ndarray, np.ndarray]:
        """(action, state) of an antagonistic correction ``u`` (n,) [bar]: the residual
        (+u, −u) in the env's [−1, 1] units, clipped, the clipping recorded in ``st``
        (``_saturated``); one row unbatched if ``single``."""
        raw = np.stack([u, -u], axis=-1) / self.cfg.residual_scale_bar
        lim = self.action_limit
        a = np.clip(raw, -lim, lim).astype(np.float32)
        self._saturated(st, u, np.abs(raw[:, 0]) > lim)
        return (a[0] if single else a), st

    @staticmethod
    def _saturated(st: np.ndarray, u: np.ndarray, clipped: np.ndarray) -> None:
        """Record in the state's last column where the output ``u`` was clipped, in u's
        direction."""
        st[:, -1] = np.where(clipped, np.sign(u), 0.0)

    @staticmethod
    def _winding(st: np.ndarray, e: np.ndarray) -> np.ndarray:
        """Rows where the error ``e`` would drive the output deeper into the saturation the
        state's last column records (anti-windup by clamping: not integrated there)."""
        return np.sign(e) * st[:, -1] > 0.0


@functools.lru_cache(maxsize=64)
def _period_feedforward(design: FeedforwardDesign, dt: float) -> np.ndarray | None:
    """[Pa] (N, 2) the design's pressures at j dt + dt / 2, j = 0 … N − 1, over one reference
    period of N whole control periods (None if the period is not a whole number of them): the
    values ``task.plan`` gives the env's steps, computed once instead of at every step (they
    cost a controller on the rig ~0.4 ms a call, the Eq. 25 designs more)."""
    n = design.period / dt
    N = round(n)
    if N < 1 or abs(n - N) > 1e-9 * n:
        return None
    return design.pressures(np.arange(N) * dt + 0.5 * dt)


def _batch(observation: np.ndarray) -> tuple[np.ndarray, bool]:
    obs = np.asarray(observation, dtype=np.float64)
    single = obs.ndim == 1
    obs = obs.reshape(1, -1) if single else obs
    if obs.shape[1] != (n := len(obs_names(residual=True))):
        raise ValueError(f"observation has {obs.shape[1]} entries; these controllers need "
                         f"MPALegResidual-v0's {n}")
    return obs, single


class ZeroResidual:
    """The feedforward expert: a zero residual applies Eq. (16) / Eq. (25) exactly."""

    @classmethod
    def stack_rows(cls, policies: list[ZeroResidual]) -> ZeroResidual:
        """:func:`stack`: zero on every row is one of them (not a subclass's: it may act)."""
        if cls is not ZeroResidual:
            raise ValueError(f"stack: {cls.__name__} does not stack (a subclass of "
                             "ZeroResidual may act per row)")
        return policies[0]

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs, single = _batch(observation)
        a = np.zeros((obs.shape[0], 2), dtype=np.float32)
        return (a[0] if single else a), state


@dataclass
class PIDResidual(_PlanPolicy):
    """Feedforward + PID: u = Kp e + Ki ∫e + Kd ė_f [bar], e = X̂ − X; residual (+u, −u)."""

    # gains from `mpa-gym tune-baselines` (TUNED_ON["pid"])
    kp_bar_per_m: float = 5.522
    ki_bar_per_m_s: float = 127.0
    kd_bar_s_per_m: float = 2.152
    tf_s: float = 9.320e-4  # [s] derivative filter time constant

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs, single = _batch(observation)
        u, st = self._pid(obs, state, episode_start, self.kp_bar_per_m, self.ki_bar_per_m_s,
                          self.kd_bar_s_per_m, self.tf_s)
        return self._antagonistic(u, st, single)

    def take_over(self, observation: np.ndarray, held: np.ndarray, state: Any,
                  rows: np.ndarray, history: np.ndarray | None = None) -> np.ndarray:
        """The state from which this controller continues the residual ``held`` (n, 2) on
        ``rows`` (a bumpless transfer, ``mpa_gym.agents.controllers.supervisor``): the integrator
        gives the antagonistic part u = (a_e − a_f) / 2 of the held command, the derivative filter
        starts at the measured error rate; other rows keep ``state``. The common part of the
        command (a stiffness change) has no place in this controller and is dropped."""
        held = self._within_authority(held)
        return self._hold(observation, state, rows, 0.5 * (held[:, 0] - held[:, 1])
                          * self.cfg.residual_scale_bar, self.ki_bar_per_m_s)


@dataclass
class AdaptiveFeedforward(_PlanPolicy):
    """Feedforward + adaptive feedforward cancellation (module docstring):
    u = θ₀ + θ_s sin ω₀t + θ_c cos ω₀t [bar], residual (+u, −u), with
    dθ/dt = (e / G) (1, 2 sin ω₀t, 2 cos ω₀t) / τ, e = X̂ − X.

    G [m/bar] is the gain from u to X on the nominal model along the reference, dF/du / k̂ (the
    force per bar of u at X̂ over the reference stiffness; in phase at ω₀, whose period is far
    below the leg's natural frequency): it varies ~2× over a period with k̂. Averaged over a
    period, on a plant whose gain is G, e / G = d / G − u for the error d the feedforward
    leaves, so each coefficient obeys dθ/dt = (d̄ − θ) / τ, d̄ the mean or harmonic of d / G:
    the mean and first harmonic of e / G decay as exp(−t / τ). τ is ``adapt_periods``
    reference periods: at one period the averaging does not hold on this leg (the mean and the
    harmonic couple through the muscles' nonlinearity) and the loop left its bounds on a
    0.5 kg load.

    State, one row per observation: (θ₀, θ_s, θ_c, s), s ∈ {−1, 0, 1} the direction the last
    output saturated in (anti-windup by clamping, as ``_pid``)."""

    adapt_periods: float = 2.0  # τ, the averaged adaptation's time constant [reference periods]

    def gain(self, obs: np.ndarray) -> np.ndarray:
        """[m/bar] (n,) G at the observed reference (NaN where the model has no answer)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            c = affine_in_pressures(obs[:, OXR], obs[:, OVR], self.params)
            return (c.J[:, 0, 0] - c.J[:, 0, 1]) * BAR / (obs[:, OK] * OBS_KREF_SCALE)

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs, single = _batch(observation)
        n = obs.shape[0]
        tau = self.adapt_periods * self._per_row(n, lambda p: p.design.reference.period)
        st = np.zeros((n, 4)) if state is None else np.array(state, dtype=float).reshape(n, 4)
        if episode_start is not None:
            st[np.broadcast_to(np.asarray(episode_start, dtype=bool).reshape(-1), (n,))] = 0.0
        e = obs[:, OXR] - obs[:, OX]
        phase = np.arctan2(obs[:, OSIN], obs[:, OCOS])
        basis = np.stack([np.ones(n), np.sin(phase), np.cos(phase)], axis=-1)
        gain = self.gain(obs)
        usable = np.isfinite(gain) & (gain > 0.0)  # else no update: the model has no answer
        with np.errstate(invalid="ignore", divide="ignore"):
            rate = np.where(self._winding(st, e) | ~usable, 0.0,
                            e * self.cfg.dt_s / (tau * gain))
        st[:, :3] += rate[:, None] * basis * np.array([1.0, 2.0, 2.0])
        u = np.einsum("ij,ij->i", st[:, :3], basis)
        return self._antagonistic(u, st, single)

    def take_over(self, observation: np.ndarray, held: np.ndarray, state: Any,
                  rows: np.ndarray, history: np.ndarray | None = None) -> np.ndarray:
        """The state from which this controller continues the policy's command on ``rows`` (a
        bumpless transfer, ``mpa_gym.agents.controllers.supervisor``): θ is the projection of
        the antagonistic part u = (a_e − a_f) / 2 of the policy's actions over the last
        reference period (``history`` (n, 2, N), oldest first, the newest at this step's
        phase; NaN where the episode is younger than a period) on (1, sin ω₀t, cos ω₀t): its
        mean and first harmonic, what afc converges to where that correction tracks, so a load
        and a periodic correction the policy carried stay carried. A row without a whole
        period starts from the mean ``held`` alone; other rows keep ``state``."""
        obs, _ = _batch(observation)
        n = obs.shape[0]
        st = np.zeros((n, 4)) if state is None else np.array(state, dtype=float).reshape(n, 4)
        scale = self.cfg.residual_scale_bar
        held = self._within_authority(held)
        theta = np.zeros((n, 3))
        theta[:, 0] = 0.5 * (held[:, 0] - held[:, 1]) * scale
        if history is not None:
            history = self._within_authority(history)
            u = 0.5 * (history[:, 0] - history[:, 1]) * scale
            N = u.shape[-1]
            whole = np.isfinite(u).all(axis=-1)
            now = np.arctan2(obs[:, OSIN], obs[:, OCOS])
            phase = now[:, None] - 2.0 * math.pi * np.arange(N - 1, -1, -1) / N
            with np.errstate(invalid="ignore"):
                harmonics = np.stack([u.mean(-1), 2.0 * (u * np.sin(phase)).mean(-1),
                                      2.0 * (u * np.cos(phase)).mean(-1)], axis=-1)
            theta[whole] = harmonics[whole]
        st[rows, :3] = theta[rows]
        st[rows, 3] = 0.0
        return st


class RepetitiveDesign(NamedTuple):
    """What :func:`repetitive_design` derives for one plan: the delay line and its filters."""

    period_steps: int  # N = T / dt, the delay line's length (one reference period)
    lead_steps: int  # m, the phase lead: e is taken m steps later in the past period
    taps: np.ndarray  # (2q + 1,) Q's zero-phase FIR weights, i = −q … q (sum 1, all > 0)
    gain: float  # k_r [m/m]
    worst_contraction: float  # max over ω ≥ ω₀/2 and the delay margin of |Q (1 − k_r z^m H)|


@functools.lru_cache(maxsize=64)
def repetitive_design(design: FeedforwardDesign, dt: float, params: Params, learn: float,
                      delay_margin_s: float, pid: tuple[float, float, float, float]
                      ) -> RepetitiveDesign:
    """The lead m and the robustness filter Q of :class:`RepetitiveControl`, from the nominal
    model alone (what the rig knows).

    The model: the leg linearised along the reference and averaged over a period,
    m δẌ = −k̄ δX − c̄ δV + Ḡ u (m the nominal mass, k̄ the mean of Eq. 23's stiffness at the
    design's pressures, c̄ = −∂F/∂V, Ḡ = ∂F/∂u for the antagonistic u [bar]), held over each
    control period (zero-order hold: the one-step delay from command to measurement: P(z)), in
    the loop of the PID law ``pid`` = (Kp, Ki, Kd, t_f) (C(z)). The RC's correction r shifts the
    error the PID's proportional and integral terms see, so it reaches the tracking error
    through H = P C_PI / (1 + P C), C_PI = Kp + Ki dt / (1 − z⁻¹): near 1 in phase and gain
    over the PID's bandwidth. From one period to the next the memory obeys
    r_{j+1} = Q (1 − k_r z^m H) r_j + (the periodic error it learns), so it converges where
    |Q (1 − k_r z^m H)| < 1 at every frequency (Tomizuka, Tsao & Chew, "Analysis and synthesis
    of discrete-time repetitive controllers", J. Dyn. Sys. Meas. Control 1989; Hara et al.,
    "Repetitive control system", IEEE TAC 1988).

    - k_r = ``learn`` / |H(ω₀)|: the share of the fundamental's error learned per period.
    - Q: a Gaussian FIR, weights ∝ exp(−i² / 2σ²), i = −q … q, q = ⌈3σ⌉, centred on the
      delayed sample (zero phase: it acts on samples of the past period). All weights are
      positive and sum to 1, so |Q| ≤ 1 at every frequency, with equality only at ω = 0.
    - The plant's delay is not the model's: a rig's regulator adds dead time and lag. The
      contraction is required for every extra dead time τ in [0, ``delay_margin_s``] (P
      replaced by P e^{−jωτ}, in H's numerator and in its loop).
    - m and σ: over the leads m = 0 … min(N/4, N − q − 1) (every sample Q and the lead ask for
      lies in the past period) and σ on a geometric grid from half a step to N/8 steps, the
      smallest σ (the widest band: the most harmonics learned) for which the worst case of
      the contraction over ω ≥ ω₀/2 and the delays stays below ``CONTRACTION_MAX``; for it, the
      m with the smallest worst case. The lead compensates the phase H loses to the model's
      and the margin's delays over Q's band.

    Raises ValueError (naming the fields) when no (m, σ) meets the bound.
    """
    from scipy import signal

    N = round(design.period / dt)
    if N < 8 or abs(design.period / dt - N) > 1e-9 * N:
        raise ValueError(f"rc: the reference period {design.period:g} s is not a whole number "
                         f"(>= 8) of control periods dt_s={dt:g} s; a repetitive controller's "
                         "delay line is one period long")
    t = np.arange(N) * dt
    s = design.sample(t)
    pr = design.pressures(t)
    c = affine_in_pressures(s.x_ref, s.v_ref, params)
    k = float(np.mean(c.k0 + np.einsum("ij,ij->i", c.J[:, 1, :], pr)))
    gain = float(np.mean(c.J[:, 0, 0] - c.J[:, 0, 1])) * BAR  # [N/bar]
    damp = float(np.mean(-force_terms(s.x_ref, s.v_ref, pr[:, 0], pr[:, 1], params).dF_dV))
    num, den, _ = signal.cont2discrete(([gain], [params.leg.m, damp, k]), dt, method="zoh")
    w0 = 2 * math.pi / design.period
    w = np.concatenate([[w0], np.linspace(0.5 * w0, math.pi / dt, 1024)])  # [rad/s]
    z = np.exp(1j * w * dt)
    P = np.polyval(np.ravel(num), z) / np.polyval(den, z)  # [m/bar]
    kp, ki, kd, tf = pid
    alpha = dt / (tf + dt)
    c_pi = kp + ki * dt / (1.0 - 1.0 / z)
    C = c_pi + kd * 1j * w * alpha / (1.0 - (1.0 - alpha) / z)
    Pd = P[None, :] * np.exp(-1j * np.outer(np.linspace(0.0, delay_margin_s, 7), w))
    H = Pd * c_pi / (1.0 + Pd * C)  # (delays, frequencies); row 0 the nominal model
    if not abs(H[0, 0]) > 0.0:
        raise ValueError("rc: with kp_bar_per_m=0 and ki_bar_per_m_s=0 the correction has no "
                         "way into the loop; a repetitive controller needs the PID's P or I")
    kr = learn / abs(H[0, 0])
    for sigma in np.geomspace(0.5, N / 8, 48):
        q = math.ceil(3 * sigma)
        i = np.arange(-q, q + 1)
        taps = np.exp(-0.5 * (i / sigma) ** 2)
        taps /= taps.sum()
        Q = taps @ np.cos(np.outer(i, w * dt))  # zero phase: real
        leads = np.arange(0, min(N // 4, N - q - 1) + 1)
        factor = Q * (1.0 - kr * np.exp(1j * np.outer(leads, w * dt))[:, None, :]
                      * H[None])  # (leads, delays, frequencies)
        worst = np.abs(factor).max(axis=(1, 2))
        if leads.size and worst.min() < CONTRACTION_MAX:
            m = int(np.argmin(worst))
            return RepetitiveDesign(N, int(leads[m]), taps, kr, float(worst[m]))
    raise ValueError(f"rc: no lead and robustness filter keep the repetitive loop contracting "
                     f"with learn={learn:g} and delay_margin_s={delay_margin_s:g} s on the "
                     "nominal model; lower learn or delay_margin_s")


@dataclass
class RepetitiveControl(PIDResidual):
    """Feedforward + PID + a plug-in repetitive controller (internal-model principle: a delay
    line of one reference period; Hara et al. 1988, Tomizuka's discrete-time prototype).

    The PID (the pid baseline's gains, inherited) acts on e + r, r [m] the RC's correction of
    the error its proportional and integral terms see (the plug-in form: the RC leaves the
    loop the PID closed as it is, and so its damping of the leg's 1.9 Hz resonance and its
    rejection of what does not repeat, a kick or noise, which the delay line cannot):

        r[k] = Σ_i Q_i (r[k − N + i] + k_r e[k − N + m + i]),  i = −q … q,

    N = T / dt steps, e = X̂ − X; the residual is (+u, −u) for the PID's u [bar]. Period by
    period it learns the periodic error the feedforward and the PID leave (the sag and lag of
    a load, a mismatched gain, a periodic disturbance) and cancels every harmonic of the
    reference inside Q's band, not only the first as ``afc`` does. The lead m and Q are
    designed from the nominal model and the PID gains (:func:`repetitive_design`); every
    sample they use lies in the past period.

    Anti-windup as ``_pid``: while the output is saturated, the memory does not learn an
    increment that pushes further into the saturation.

    State, one row per observation: (∫e, ė_f, k, r ring of L, e ring of L, s), k the steps
    since the episode began, L = N + q + 1 (the longest over a stack's rows), s the direction
    the last output saturated in."""

    # gains from `mpa-gym tune-baselines` (TUNED_ON["rc"])
    learn: float = 0.3414  # share of the fundamental's error learned per period, k_r |H(ω₀)|
    delay_margin_s: float = 0.1084  # [s] extra dead time Q keeps the memory contracting for

    def __post_init__(self) -> None:
        check_range("rc.learn", self.learn, 0.0, 2.0, low_open=True, high_open=True)
        check_range("rc.delay_margin_s", self.delay_margin_s, 0.0, 0.2, unit="s")
        for p in self.row_plans or (self.plan,):
            self.design_of(p)

    def design_of(self, plan: TaskPlan) -> RepetitiveDesign:
        """The delay line, lead and filter for rows following ``plan``."""
        return repetitive_design(plan.design, self.cfg.dt_s, self.params, float(self.learn),
                                 float(self.delay_margin_s),
                                 (self.kp_bar_per_m, self.ki_bar_per_m_s, self.kd_bar_s_per_m,
                                  self.tf_s))

    def _width(self) -> int:
        """The state's columns: 4 + 2 L, L the longest of the rows' N + q + 1."""
        return 4 + 2 * max(d.period_steps + len(d.taps) // 2 + 1
                           for d in map(self.design_of, self.row_plans or (self.plan,)))

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs, single = _batch(observation)
        n, width = obs.shape[0], self._width()
        L = (width - 4) // 2
        st = np.zeros((n, width)) if state is None else np.array(state, dtype=float).reshape(
            n, width)
        if episode_start is not None:
            st[np.broadcast_to(np.asarray(episode_start, dtype=bool).reshape(-1), (n,))] = 0.0
        k = st[:, 2].astype(np.int64)
        e = obs[:, OXR] - obs[:, OX]
        r = np.zeros(n)
        R, E = st[:, 3:3 + L], st[:, 3 + L:3 + 2 * L]  # views
        for plan, rows in self._plan_rows(n):
            d = self.design_of(plan)
            i = np.arange(n)[rows]
            q = len(d.taps) // 2
            ring = d.period_steps + q + 1
            back = k[i, None] - d.period_steps + np.arange(-q, q + 1)[None, :]
            learned = d.gain * (E[i[:, None], (back + d.lead_steps) % ring] @ d.taps)
            learned = np.where(self._winding(st[i], learned), 0.0, learned)
            r[i] = R[i[:, None], back % ring] @ d.taps + learned
            R[i, k[i] % ring] = r[i]
            E[i, k[i] % ring] = e[i]
        st[:, 2] += 1
        pid = [0, 1, width - 1]
        u, st[:, pid] = self._pid(obs, None if state is None else st[:, pid], episode_start,
                                  self.kp_bar_per_m, self.ki_bar_per_m_s, self.kd_bar_s_per_m,
                                  self.tf_s, r)
        return self._antagonistic(u, st, single)

    def take_over(self, observation: np.ndarray, held: np.ndarray, state: Any,
                  rows: np.ndarray, history: np.ndarray | None = None) -> np.ndarray:
        """The state from which this controller continues the residual ``held`` (n, 2) on
        ``rows`` (a bumpless transfer, ``mpa_gym.agents.controllers.supervisor``): the PID's as
        ``PIDResidual.take_over`` (its integrator holds the antagonistic part of the command),
        the delay line empty (no correction until it has a period to learn from)."""
        n, width = len(rows), self._width()
        st = np.zeros((n, width)) if state is None else np.array(state, dtype=float).reshape(
            n, width)
        pid = [0, 1, width - 1]
        held_st = super().take_over(observation, held, st[:, pid], rows)
        st[rows] = 0.0
        st[np.ix_(rows, pid)] = held_st[rows]
        return st


@dataclass
class StiffnessFeedback(_PlanPolicy):
    """Model-based, stiffness-preserving feedback (module docstring).

    Force law: F* = m (dV̂/dt + g) + Kp e + Ki ∫e + Kd ė on the nominal m; pressures from
    F(X, V, P') = F* and k(X, V, P') = k̂ at the measured (X, V), both affine in P'.
    """

    # gains from `mpa-gym tune-baselines` (TUNED_ON["mbfb"])
    kp_N_per_m: float = 682.4
    ki_N_per_m_s: float = 3346.0
    kd_N_s_per_m: float = 73.36
    tf_s: float = 4.724e-3  # [s] derivative filter time constant

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs, single = _batch(observation)
        correction, st = self._pid(obs, state, episode_start, self.kp_N_per_m,
                                   self.ki_N_per_m_s, self.kd_N_s_per_m, self.tf_s)
        x, v = obs[:, OX], obs[:, OV]
        p = self.params
        f_star = self._force_target(obs) + correction
        k_star = obs[:, OK] * OBS_KREF_SCALE
        with np.errstate(invalid="ignore"):
            c = affine_in_pressures(x, v, p)
        A = c.J
        rhs = np.stack([f_star - c.F0, k_star - c.k0], axis=-1)
        with np.errstate(invalid="ignore"):  # outside the model's domain: NaN, handled below
            pressures = np.linalg.solve(A, rhs[..., None])[..., 0]
        limited = np.clip(pressures, 0.0, self.cfg.p_max_bar * BAR)
        raw = (limited - self._feedforward(obs)) / (self.cfg.residual_scale_bar * BAR)
        lim = self.action_limit
        a = np.clip(raw, -lim, lim).astype(np.float32)
        with np.errstate(invalid="ignore"):
            clipped = np.any((limited != pressures) | (np.abs(raw) > lim), axis=-1)
        a[~np.isfinite(a)] = 0.0  # no model answer (state outside its domain): feedforward only
        self._saturated(st, correction, clipped)
        return (a[0] if single else a), st

    def _force_target(self, obs: np.ndarray) -> np.ndarray:
        """[N] m (dV̂/dt + g) on the nominal m: the force law without its correction."""
        n = obs.shape[0]
        omega = self._per_row(n, lambda p: p.design.reference.omega)
        a_ref = -omega**2 * (obs[:, OXR] - self._per_row(n, lambda p: p.design.reference.x0))
        return self.params.leg.m * (a_ref + self.params.leg.g)

    def take_over(self, observation: np.ndarray, held: np.ndarray, state: Any,
                  rows: np.ndarray, history: np.ndarray | None = None) -> np.ndarray:
        """The state from which this controller continues the residual ``held`` (n, 2) on
        ``rows`` (a bumpless transfer, ``mpa_gym.agents.controllers.supervisor``): the integrator
        gives the force correction that the held pressures (feedforward + residual) make, on the
        nominal model at the measured state, beyond m (dV̂/dt + g); other rows keep ``state``."""
        obs = np.asarray(observation, dtype=np.float64).reshape(len(rows), -1)
        pressures = (self._feedforward(obs)
                     + self._within_authority(held) * self.cfg.residual_scale_bar * BAR)
        with np.errstate(invalid="ignore"):
            c = affine_in_pressures(obs[:, OX], obs[:, OV], self.params)
            force = c.F0 + np.einsum("...j,...j->...", c.J[..., 0, :], pressures)
        correction = np.nan_to_num(force - self._force_target(obs))  # outside the model: 0
        return self._hold(obs, state, rows, correction, self.ki_N_per_m_s)


BASELINES = {"ff": "ZeroResidual", "pid": "PIDResidual", "mbfb": "StiffnessFeedback",
             "afc": "AdaptiveFeedforward", "rc": "RepetitiveControl"}

# What each baseline's defaults were tuned on (``mpa-gym tune-baselines``; the report shows it).
TUNED_ON = {
    "ff": "nothing: the paper's feedforward (Eq. 16 / 25) designed on the nominal model",
    "pid": "`mpa-gym tune-baselines --n-trials 200 --n-plants 32`: 200 Optuna TPE trials (seed 0) "
           "minimising the mean position RMSE (last 3 of 5 periods; an unstable or terminated "
           "plant counts 100 mm) over 32 plants drawn (seed 0) from the training ranges of "
           "configs/ppo_residual.yaml, every effect on in every draw, and their 32 undamped "
           "twins; 1.37 mm, the gains of the first trial (no other trial beat them)",
    "mbfb": "`mpa-gym tune-baselines --n-trials 120 --n-plants 32`: 120 Optuna TPE trials (seed "
            "0) minimising the mean position RMSE (last 3 of 5 periods; an unstable or "
            "terminated plant counts 100 mm) over 32 plants drawn (seed 0) from the training "
            "ranges of configs/ppo_residual.yaml, every effect on in every draw, and their 32 "
            "undamped twins; 9.91 mm (the first trial's gains: 11.6 mm)",
    "rc": "`mpa-gym tune-baselines --policy rc --n-trials 60 --n-plants 32 --episode-s 30`: "
          "60 Optuna TPE trials (seed 0) of learn and delay_margin_s on pid's tuned loop, "
          "minimising the mean position RMSE (last 3 of 10 periods: the memory learns period "
          "by period; an unstable or terminated plant counts 100 mm) over 32 plants drawn "
          "(seed 0) from the training ranges of configs/ppo_residual.yaml, every effect on in "
          "every draw, and their 32 undamped twins; 0.278 mm (pid on the same 30 s episodes: "
          "1.37 mm; the first trial, learn 0.5 and delay_margin_s 0.03: 27.3 mm, unstable on "
          "heavy legs behind slow regulators)",
    "afc": f"nothing: its adaptation's time constant is {AdaptiveFeedforward.adapt_periods:g} "
           "reference periods (the nominal model's gain normalises it); the supervisor's last "
           "resort",
}


def stack(policies: list[Policy]) -> Policy:
    """One controller for a batch whose row i is ``policies[i]``'s: a report's scenarios, a
    sweep's cells or a model's plants in one call per step, with each row's numbers as its own
    controller gives them. The controllers must be of one class that stacks (a
    ``stack_rows`` classmethod: the baselines here, a learned policy and a supervised one;
    one kind, gains and task config, each its own plan, delays told or start)."""
    if not policies:
        raise ValueError("stack: no controllers")
    kind = type(policies[0])
    if not hasattr(kind, "stack_rows"):
        raise ValueError(f"stack: {kind.__name__} does not stack (no stack_rows)")
    if any(type(p) is not kind for p in policies):
        raise ValueError("stack: controllers of one kind only")
    return kind.stack_rows(policies)


def stacked(policies: list[Policy]) -> Policy | None:
    """:func:`stack` of ``policies``, or None where they do not stack (of several kinds, gains
    or task configs, or not a kind that stacks: your own): then each runs its own rows."""
    try:
        return stack(policies)
    except (ValueError, TypeError):
        return None


def make_baseline(name: str, scenario: Any = "nominal", stiffness: Any = None,
                  task: dict[str, Any] | TaskConfig | None = None,
                  params: Params = DEFAULT_PARAMS, gains: dict[str, float] | None = None
                  ) -> Policy:
    """A baseline by name for an env made with the same (scenario, stiffness, task);
    ``gains``: its fields other than the defaults (``mpa_gym.agents.controllers.gains``)."""
    if name not in BASELINES:
        raise ValueError(f"policy={name!r} is not a baseline; choose one of {sorted(BASELINES)} "
                         "or a run folder")
    if name == "ff":
        return ZeroResidual()
    cfg = task if isinstance(task, TaskConfig) else TaskConfig.from_kwargs(task)
    plan = make_plan(scenario, stiffness, cfg, params)
    return globals()[BASELINES[name]](plan, params, **(gains or {}))
