"""Controller-side features and action coordinates for learned policies.

Observation: the env observes X and X̂ separately; a network has to subtract two numbers that each
vary by centimetres to see a sub-millimetre error, and a memoryless policy can only answer an
unknown static load with a proportional correction, so a steady sag remains (a PID has its
integrator for that). ``TrackingErrorObservation`` appends e = X̂ − X, ė = V̂ − V and the integrals

    I_0 = ∫ e dt,   I_sh = ∫ e sin(hφ) dt,   I_ch = ∫ e cos(hφ) dt   (h = 1 … ``harmonics``),

each clipped to ±``limit_m_s`` (anti-windup), φ the reference phase the env observes. I_0 is a
PID's integrator; the harmonic pairs are the internal model of a periodic reference (a resonant
controller's integrators): they hold whatever periodic correction the plant needs, so a policy can
cancel a periodic error — and the in-phase part, a force error that follows X̂ − X_0, is a
stiffness error the policy can correct. ``mask_pressures`` zeroes the measured pressures (the
layout stays): they echo the policy's own last command, and a policy that learned to overdrive
lagging regulators through them chatters on a lag-free one. ``previous_action`` appends the
action the env was last given instead, the other way to tell the command from the lag;
``fine_error_m`` appends the error clipped to ±δ, which VecNormalize then scales to the sub-
millimetre band (the plain error's running std is set by millimetre transients). All are
what a controller computes from its measurements and its own commands, never a plant parameter.

``errors_only`` leaves the env's observation out: the policy sees the error features alone, so it
is a feedback law. Given X, X̂ or the phase, a policy trained on randomised plants learns the
training distribution's average correction as a function of the phase and holds it on every
plant, a periodic bias that its feedback then has to fight, even on the nominal plant where the
feedforward alone is exact. Without the phase, though, the harmonic integrals cannot be
turned back into a periodic correction; ``remodulate`` does that for the policy, appending per
harmonic the resonant controller's output and its quadrature,

    R_h = I_sh sin(hφ) + I_ch cos(hφ),   Q_h = I_sh cos(hφ) − I_ch sin(hφ),

which after integrating e = c₁ sin φ + c₂ cos φ over a period T are (T/2) e(φ) and (T/2) e(φ + π/2):
an infinite-gain loop at the reference frequency whose phase the policy sets by weighing R
against Q, and zero while the integrals are zero, so no bias. (The raw I_sh, I_ch stay in the
observation: their in-phase part tells a stiffness error, which the policy answers with a_k.)

Action: ``ForceStiffnessAction`` lets the policy act in the coordinates the task is posed in: a
ground-force correction ΔF = a_F · ``force_N`` and a stiffness correction Δk = a_k ·
``stiffness_rel`` · k̂. Both are affine in the two pressures (``affine_in_pressures``), so on the
nominal model at the reference position the pressure correction is one 2×2 solve; it is applied
as the env's residual action (clipped to [−1, 1]). a = 0 is the feedforward expert, and a force
correction alone leaves the nominal stiffness at k̂ — the redundancy the paper's design uses.
``rate_penalty`` w subtracts w·|a_t − a_{t−1}|² from the reward (a_{−1} = 0 each episode), the
action-rate term of legged-robot RL, against high-frequency corrections that a lagging regulator
turns into a limit cycle; it shapes training only, so a trained policy runs without it.

``stiffness_adapt_s`` τ replaces the policy's a_k by an estimate. On a plant whose muscles are
not the model's (bladder C1, C2, thickness), a force correction that tracks X̂ has to cancel
the plant's force deficit along the motion. Its slope against X̂ is then the stiffness excess
k − k̂ at the applied pressures, less Δm ω² for a mass error (4.4 N/m per kg at the 3 s
period; k̂ is ~545 N/m). The estimator low-passes (time constant τ) the means of X̂ and of the
applied ΔF, their covariance c and X̂'s variance v. It low-passes the slope c / (v + v₀) once
more, clipped to ±``stiffness_rel`` k̂, and answers â_k = −slope / (``stiffness_rel`` k̂).
Each update's weight is 1 / (1 + (e / 1 mm)²), so a start's or a kick's transient barely
moves it. An update pairs X̂ with the ΔF applied one control step earlier (this step's is not
known until â_k is): a lag dt that scales the slope by cos(ω dt), 0.9998 at the 3 s period.
Off the training plants, a_k learned from the error features went the wrong way on some
plants; the estimate needs no learning. It is a controller's computation from its own commands
and the reference, like the features, never a plant parameter. The action space stays (a_F,
a_k), so a config switches the estimator on or off without another network; the policy's a_k
is then ignored, and its Gaussian adds noise, not bias, to PPO's gradient.

Single-env wrappers are what an rl-zoo config names as ``env_wrapper``; the ``…Vector…`` ones wrap
the native vector env (same-step autoreset). Both use the module's functions, so they agree.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numba
import numpy as np
from gymnasium import spaces
from gymnasium.vector import VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_range
from mpa_gym.task.contract import OBS_COS as OCOS
from mpa_gym.task.contract import OBS_KREF as OK
from mpa_gym.task.contract import OBS_KREF_SCALE, check_action
from mpa_gym.task.contract import OBS_PE as OPE
from mpa_gym.task.contract import OBS_PF as OPF
from mpa_gym.task.contract import OBS_SIN as OSIN
from mpa_gym.task.contract import OBS_V as OV
from mpa_gym.task.contract import OBS_VREF as OVR
from mpa_gym.task.contract import OBS_X as OX
from mpa_gym.task.contract import OBS_XREF as OXR

MAX_HARMONICS = 5


@dataclass(frozen=True)
class FeatureSpec:
    """What ``TrackingErrorObservation`` appends (its kwargs; module docstring)."""

    limit_m_s: float = 0.02  # [m s] anti-windup bound of the integrals
    harmonics: int = 0  # harmonic integral pairs
    previous_action: bool = False  # append the action the env was last given
    mask_pressures: bool = False  # zero the measured pressures
    fine_error_m: float | None = None  # [m] also append clip(X̂ − X, ±this)
    errors_only: bool = False  # drop the env observation: the features alone
    remodulate: bool = False  # append each harmonic pair's resonant output and its quadrature

    def __post_init__(self) -> None:
        lim = self.limit_m_s
        if isinstance(lim, bool) or not isinstance(lim, int | float) or not 0 < lim <= 1.0:
            raise ValueError(f"limit_m_s={lim!r} must be a number in (0, 1] m s")
        h = self.harmonics
        if isinstance(h, bool) or not isinstance(h, int) or not 0 <= h <= MAX_HARMONICS:
            raise ValueError(f"harmonics={h!r} must be a whole number in [0, {MAX_HARMONICS}]")
        for name in ("previous_action", "mask_pressures", "errors_only", "remodulate"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}={getattr(self, name)!r} must be true or false")
        f = self.fine_error_m
        if f is not None and (isinstance(f, bool) or not isinstance(f, int | float) or
                              not 0 < f <= 0.1):
            raise ValueError(f"fine_error_m={f!r} must be null or a number in (0, 0.1] m")
        if self.remodulate and not self.harmonics:
            raise ValueError("remodulate=True needs harmonics >= 1 (it remodulates their "
                             "integrals)")

    @property
    def n_integrals(self) -> int:
        """Number of integral features: I_0 and one (sin, cos) pair per harmonic."""
        return 1 + 2 * self.harmonics

    def space(self, space: spaces.Box) -> spaces.Box:
        """The observation space with the features appended."""
        m, lim = self.n_integrals, self.limit_m_s
        lo = [-1.0, -20.0] + [-lim] * m + [-1.0] * (2 * self.previous_action)
        hi = [1.0, 20.0] + [lim] * m + [1.0] * (2 * self.previous_action)
        if self.fine_error_m is not None:
            lo.append(-self.fine_error_m)
            hi.append(self.fine_error_m)
        if self.remodulate:
            bound = np.sqrt(2) * lim * (1 + 1e-6)  # |R|, |Q| ≤ |(I_s, I_c)|; float32 rounding
            lo += [-bound] * (2 * self.harmonics)
            hi += [bound] * (2 * self.harmonics)
        base_lo, base_hi = (([], []) if self.errors_only else (space.low, space.high))
        return spaces.Box(np.concatenate([base_lo, lo]).astype(np.float32),
                          np.concatenate([base_hi, hi]).astype(np.float32), dtype=np.float32)

    def features(self, obs: np.ndarray, integ: np.ndarray, prev_action: np.ndarray
                 ) -> np.ndarray:
        """obs (n, d), integrals (n, m), previous action (n, 2) → the features (n, d + … or …):
        [obs (pressures zeroed if masked; left out if errors_only), X̂ − X, V̂ − V, I…, (a_prev),
        (fine error), (R_1…R_h, Q_1…Q_h if remodulate)], float32. Masking keeps the layout."""
        n = obs.shape[0]
        if self.mask_pressures:
            obs = obs.copy()
            obs[:, OPE:OPF + 1] = 0.0
        e = obs[:, OXR] - obs[:, OX]
        cols = [e[:, None], (obs[:, OVR] - obs[:, OV])[:, None], np.reshape(integ, (n, -1))]
        if not self.errors_only:
            cols.insert(0, obs)
        if self.previous_action:
            cols.append(np.reshape(prev_action, (n, 2)))
        if self.fine_error_m is not None:
            cols.append(np.clip(e, -self.fine_error_m, self.fine_error_m)[:, None])
        if self.remodulate:
            basis = harmonic_basis(obs, self.harmonics)
            i = np.reshape(integ, (n, -1))
            s_, c_ = basis[:, 1::2], basis[:, 2::2]
            i_s, i_c = i[:, 1::2], i[:, 2::2]
            cols += [i_s * s_ + i_c * c_, i_s * c_ - i_c * s_]
        return np.concatenate(cols, axis=1).astype(np.float32)


@dataclass(frozen=True)
class ActionSpec:
    """How ``ForceStiffnessAction`` maps its actions (its kwargs; module docstring)."""

    force_N: float = 20.0  # [N] ground-force correction ΔF at a_F = ±1
    stiffness_rel: float = 0.3  # [-] stiffness correction Δk at a_k = ±1, as a share of k̂
    rate_penalty: float = 0.0  # weight of |a_t − a_{t−1}|² taken off the training reward
    # [s] time constant of the stiffness estimator whose a_k replaces the policy's (module
    # docs); None: the policy's own a_k
    stiffness_adapt_s: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "stiffness_adapt_s",
                           adapt_time_constant(self.stiffness_adapt_s))
        for name, lo, hi in (("force_N", None, 200.0), ("stiffness_rel", None, 1.0),
                             ("rate_penalty", 0.0, 100.0)):
            value = getattr(self, name)
            ok = isinstance(value, int | float) and not isinstance(value, bool) and \
                (lo <= value if lo is not None else 0 < value) and value <= hi
            if not ok:
                interval = f"[{lo:g}, {hi:g}]" if lo is not None else f"(0, {hi:g}]"
                raise ValueError(f"{name}={value!r} must be a number in {interval}")
            object.__setattr__(self, name, float(value))


def harmonic_basis(obs: np.ndarray, harmonics: int) -> np.ndarray:
    """(…, 1 + 2h): [1, sin φ, cos φ, sin 2φ, cos 2φ, …] from the observed (sin φ, cos φ)."""
    z1 = obs[..., OCOS] + 1j * obs[..., OSIN]
    cols = [np.ones(obs.shape[:-1])]
    z = np.ones(obs.shape[:-1], dtype=complex)
    for _ in range(harmonics):
        z = z * z1
        cols += [z.imag, z.real]
    return np.stack(cols, axis=-1)


def integral_step(integ: np.ndarray, obs: np.ndarray, dt: float, limit: float) -> np.ndarray:
    """I ← clip(I + (X̂ − X) · basis(φ) · dt, ±limit) for one observation or a batch.

    ``integ`` has the integrals on its last axis (1 + 2h of them); h follows from its length."""
    integ = np.asarray(integ, dtype=float)
    basis = harmonic_basis(obs, (integ.shape[-1] - 1) // 2)
    e = obs[..., OXR] - obs[..., OX]
    return np.clip(integ + e[..., None] * basis * dt, -limit, limit)


class TrackingErrorObservation(gym.Wrapper):
    """Single env: [observation (left out if errors_only), X̂ − X, V̂ − V, I_0, (I_sh, I_ch)…,
    (a_prev), (fine error), (R_h…, Q_h… if remodulate)]; integrals and previous action restart
    at 0; ``env_obs`` keeps the env's own last observation. kwargs: the fields of
    ``FeatureSpec``."""

    def __init__(self, env: gym.Env, **kwargs: Any) -> None:
        super().__init__(env)
        self.feature_spec = FeatureSpec(**kwargs)
        self.dt = float(env.unwrapped.cfg.dt_s)
        self.observation_space = self.feature_spec.space(env.observation_space)
        self.integ = np.zeros(self.feature_spec.n_integrals)
        self.prev = np.zeros(2)
        self.env_obs: np.ndarray | None = None  # the env's own last observation

    def _features(self, obs: np.ndarray) -> np.ndarray:
        return self.feature_spec.features(obs[None], self.integ[None], self.prev[None])[0]

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.integ = np.zeros(self.feature_spec.n_integrals)
        self.prev = np.zeros(2)
        self.env_obs = obs
        return self._features(obs), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, r, te, tr, info = self.env.step(action)
        self.prev = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)  # as the env applied it
        self.integ = integral_step(self.integ, obs, self.dt, self.feature_spec.limit_m_s)
        self.env_obs = obs
        return self._features(obs), r, te, tr, info


class TrackingErrorVectorObservation(VectorWrapper):
    """Native vector env (same-step autoreset): the features of ``TrackingErrorObservation``."""

    def __init__(self, env: VectorEnv, **kwargs: Any) -> None:
        super().__init__(env)
        self.feature_spec = FeatureSpec(**kwargs)
        self.dt = float(env.unwrapped.cfg.dt_s)
        self.single_observation_space = self.feature_spec.space(env.single_observation_space)
        self.observation_space = batch_space(self.single_observation_space, env.num_envs)
        self.integ = np.zeros((env.num_envs, self.feature_spec.n_integrals))
        self.prev = np.zeros((env.num_envs, 2))
        self.env_obs: np.ndarray | None = None  # the env's own last observations

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.integ[:] = 0.0
        self.prev[:] = 0.0
        self.env_obs = obs
        return self.feature_spec.features(obs, self.integ, self.prev), info

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        obs, r, te, tr, info = self.env.step(actions)
        self.prev = np.clip(np.asarray(actions, dtype=float).reshape(self.num_envs, 2), -1, 1)
        spec = self.feature_spec
        limit = spec.limit_m_s
        done = te | tr
        if done.any():  # the finished episodes' features go with their final observation
            final = info["final_obs"].copy()  # an object array, None where not done
            for i in np.flatnonzero(done):
                last = integral_step(self.integ[i], final[i], self.dt, limit)
                final[i] = spec.features(final[i][None], last[None], self.prev[i][None])[0]
            info["final_obs"] = final
        self.integ = integral_step(self.integ, obs, self.dt, limit)
        self.integ[done] = 0.0  # the returned obs of a finished env starts a new episode
        self.prev[done] = 0.0
        self.env_obs = obs
        return self.feature_spec.features(obs, self.integ, self.prev), r, te, tr, info


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _force_stiffness_kernel(a, x_ref, k_ref, force_N, stiffness_rel, scale_pa, c, out):
    for i in range(a.shape[0]):
        x = x_ref[i]
        F0, k0 = fast.force_and_stiffness(x, 0.0, 0.0, 0.0, c)
        Fe, ke = fast.force_and_stiffness(x, 0.0, BAR, 0.0, c)
        Ff, kf = fast.force_and_stiffness(x, 0.0, 0.0, BAR, c)
        j11, j12, j21, j22 = (Fe - F0) / BAR, (Ff - F0) / BAR, (ke - k0) / BAR, (kf - k0) / BAR
        dF = min(max(a[i, 0], -1.0), 1.0) * force_N
        dk = min(max(a[i, 1], -1.0), 1.0) * stiffness_rel * k_ref[i]
        det = j11 * j22 - j12 * j21
        out[i, 0] = min(max((dF * j22 - j12 * dk) / det / scale_pa, -1.0), 1.0)
        out[i, 1] = min(max((j11 * dk - j21 * dF) / det / scale_pa, -1.0), 1.0)


# The stiffness estimator (ActionSpec.stiffness_adapt_s; module docs)
ADAPT_MAX_S = 60.0  # [s] its longest time constant: twenty reference periods, two episodes
ADAPT_ERROR_M = 1e-3  # [m] tracking error at which an update's weight halves: a start's or a
#                       kick's transient says nothing about the plant's stiffness
ADAPT_VAR_M2 = 1e-5  # [m²] regulariser of X̂'s variance, (3.2 mm)², a twentieth of the 20 mm
#                      reference's A²/2: a reference that barely moves gives no estimate
ADAPT_STATE = 7  # an estimator's state: means of X̂ and ΔF, their covariance, X̂'s variance,
#                  the slope, the last ΔF applied, started (0 until its first observation)
ADAPT_DF, ADAPT_STARTED = 5, 6  # its columns that the callers write


def adapt_time_constant(tau: Any, force_stiffness: bool = True) -> float | None:
    """``stiffness_adapt_s`` checked: None (no estimator) or a time constant in
    (0, ``ADAPT_MAX_S``] s, for a policy in force–stiffness coordinates (``force_stiffness``)."""
    if tau is None:
        return None
    tau = check_range("stiffness_adapt_s", tau, 0.0, ADAPT_MAX_S, low_open=True, unit="s",
                      note="or null: no estimator")
    if not force_stiffness:
        raise ValueError("stiffness_adapt_s needs force_stiffness (the estimator replaces "
                         "the stiffness coordinate of ForceStiffnessAction)")
    return tau


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _adapt_row(s, x_ref, e, k_ref, dt, tau, stiffness_rel):
    """One step of one row's stiffness estimator (state ``s`` updated in place) → its a_k."""
    if s[ADAPT_STARTED] == 0.0:
        for j in range(ADAPT_STARTED):
            s[j] = 0.0
        s[0], s[ADAPT_STARTED] = x_ref, 1.0
    al = dt / tau / (1.0 + (e / ADAPT_ERROR_M) ** 2)
    s[0] += al * (x_ref - s[0])
    s[1] += al * (s[ADAPT_DF] - s[1])
    dx, dF = x_ref - s[0], s[ADAPT_DF] - s[1]
    s[2] += al * (dF * dx - s[2])
    s[3] += al * (dx * dx - s[3])
    span = stiffness_rel * abs(k_ref)
    if span <= 0.0:
        return 0.0
    s[4] += al * (min(max(s[2] / (s[3] + ADAPT_VAR_M2), -span), span) - s[4])
    return min(max(-s[4] / span, -1.0), 1.0)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _adapt_commit(s, a_F, force_N):
    """The force correction ΔF applied this step, which the estimator's next update pairs
    with the next X̂ (module docs)."""
    s[ADAPT_DF] = min(max(a_F, -1.0), 1.0) * force_N


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _adapt_kernel(a, x_ref, x, k_ref, state, dt, tau, stiffness_rel, force_N, out):
    for i in range(a.shape[0]):
        out[i, 0] = a[i, 0]
        out[i, 1] = _adapt_row(state[i], x_ref[i], x_ref[i] - x[i], k_ref[i], dt, tau,
                               stiffness_rel)
        _adapt_commit(state[i], a[i, 0], force_N)


def adapt_stiffness(action: np.ndarray, obs: np.ndarray, state: np.ndarray, dt: float,
                    tau: float, stiffness_rel: float, force_N: float) -> np.ndarray:
    """(n, 2) (a_F, a_k) → (a_F, â_k): the stiffness output replaced by the estimator's for
    the observations ``obs`` (n, d), each row's state (n, ``ADAPT_STATE``, zeros at an
    episode's start) updated in place; ``tau`` its time constant [s] (module docs)."""
    a = np.asarray(action, dtype=np.float64).reshape(-1, 2)
    out = np.empty_like(a)
    _adapt_kernel(a, np.asarray(obs[:, OXR], dtype=np.float64),
                  np.asarray(obs[:, OX], dtype=np.float64),
                  np.asarray(obs[:, OK], dtype=np.float64) * OBS_KREF_SCALE, state,
                  float(dt), float(tau), float(stiffness_rel), float(force_N), out)
    return out


def force_stiffness_to_residual(action: np.ndarray, obs: np.ndarray, force_N: float,
                                stiffness_rel: float, scale_bar: float,
                                params: Params = DEFAULT_PARAMS) -> np.ndarray:
    """(n, 2) (a_F, a_k) in [−1, 1] → the residual action (a_e, a_f) of ``MPALegResidual-v0``.

    Solves J(X̂) ΔP = (a_F · force_N, a_k · stiffness_rel · k̂) on the nominal model, at the
    observed reference position (noise-free, and where the feedforward holds the leg), with J the
    coefficients of ``affine_in_pressures`` (compiled here: it runs every control step), and
    returns ΔP / residual scale clipped to [−1, 1]."""
    a = np.asarray(action, dtype=np.float64).reshape(-1, 2)
    out = np.empty((a.shape[0], 2))
    _force_stiffness_kernel(a, np.asarray(obs[:, OXR], dtype=np.float64),
                            np.asarray(obs[:, OK], dtype=np.float64) * OBS_KREF_SCALE,
                            float(force_N), float(stiffness_rel), float(scale_bar) * BAR,
                            _constants(params), out)
    return out.astype(np.float32)


@functools.lru_cache(maxsize=8)
def _constants(params: Params) -> np.ndarray:
    return fast.pack(params)


class _ForceStiffnessMap:
    """What both force–stiffness wrappers share: the settings, the last observation (X̂ and k̂
    for the map), the last action (for the rate penalty) and the reset that records them."""

    env: Any
    _obs: np.ndarray | None
    _prev: np.ndarray

    def _setup(self, env: Any, spec: ActionSpec, n: int) -> None:
        self.action_spec = spec
        self.force_N, self.stiffness_rel, self.rate_penalty = (
            spec.force_N, spec.stiffness_rel, spec.rate_penalty)
        if not getattr(env.unwrapped, "residual", False):
            raise ValueError("ForceStiffnessAction needs MPALegResidual-v0 (residual actions and "
                             "the k̂ observation)")
        self.scale_bar = float(env.unwrapped.cfg.residual_scale_bar)
        # X̂ and k̂ come from the observation beneath when it is the env's own, else from the
        # TrackingErrorObservation directly beneath, which keeps the env's (its features may
        # leave it out: errors_only)
        self._from_features = hasattr(env, "env_obs")
        own, seen = env.unwrapped.observation_space, env.observation_space
        if not self._from_features and seen != own:
            raise ValueError(f"ForceStiffnessAction needs the env's observation (X̂ in column "
                             f"{OXR}, k̂ in column {OK}) but the observation beneath has shape "
                             f"{seen.shape}, not {own.shape}: wrap a TrackingErrorObservation "
                             "directly, or the env itself")
        self._obs = None
        self._prev = np.zeros((n, 2))
        self.dt = float(env.unwrapped.cfg.dt_s)
        self._adapt = np.zeros((n, ADAPT_STATE))  # the stiffness estimators, one per env

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._obs = self._env_obs(obs)
        self._prev[:] = 0.0
        self._adapt[:] = 0.0
        return obs, info

    def _env_obs(self, obs: Any) -> np.ndarray:
        """The env's own observation, for the map's X̂ and k̂ (``_setup``)."""
        return np.asarray(self.env.env_obs if self._from_features else obs)

    def _rate_cost(self, a: np.ndarray, done: np.ndarray) -> np.ndarray:
        """rate_penalty · |a − a_prev|² per env (a_prev = 0 at an episode's first step); then
        ``a`` becomes the previous action, except where an episode just ended."""
        cost = self.rate_penalty * np.sum((a - self._prev) ** 2, axis=1)
        self._prev[:] = a
        self._prev[done] = 0.0
        return cost

    def _residual(self, a: np.ndarray) -> np.ndarray:
        """(n, 2) validated (a_F, a_k) → the residual action for the last observation."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        obs = self._obs.reshape(a.shape[0], -1)
        tau = self.action_spec.stiffness_adapt_s
        if tau is not None:
            a = adapt_stiffness(a, obs, self._adapt, self.dt, tau, self.stiffness_rel,
                                self.force_N)
        return force_stiffness_to_residual(a, obs, self.force_N, self.stiffness_rel,
                                           self.scale_bar)


class ForceStiffnessAction(_ForceStiffnessMap, gym.Wrapper):
    """Single residual env: actions (a_F, a_k) in force–stiffness coordinates (module docs).
    kwargs: the fields of ``ActionSpec``."""

    def __init__(self, env: gym.Env, **kwargs: Any) -> None:
        gym.Wrapper.__init__(self, env)
        self._setup(env, ActionSpec(**kwargs), 1)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        a = np.clip(check_action(action)[None], -1.0, 1.0)
        residual = self._residual(a)[0]
        obs, r, te, tr, info = self.env.step(residual)
        self._obs = self._env_obs(obs)
        if self.rate_penalty:
            r = float(r - self._rate_cost(a, np.array([te or tr]))[0])
        return obs, r, te, tr, info


class ForceStiffnessVectorAction(_ForceStiffnessMap, VectorWrapper):
    """Native vector env: the action coordinates of ``ForceStiffnessAction``. kwargs: the
    fields of ``ActionSpec``."""

    def __init__(self, env: VectorEnv, **kwargs: Any) -> None:
        VectorWrapper.__init__(self, env)
        self._setup(env, ActionSpec(**kwargs), env.num_envs)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        a = np.clip(check_action(actions, self.num_envs), -1.0, 1.0)
        residual = self._residual(a)
        obs, r, te, tr, info = self.env.step(residual)
        self._obs = self._env_obs(obs)  # same-step autoreset: a new episode's first observation
        done = np.logical_or(te, tr)
        self._adapt[done] = 0.0
        if self.rate_penalty:
            r = r - self._rate_cost(a, done)
        return obs, r, te, tr, info
