"""The controller front-end of a learned policy: its observation features, its action map and
its per-episode state, defined once. The training wrappers (``mpa_gym.agents.learned.wrappers``),
the loaded policy (``mpa_gym.agents.learned.policies.LearnedPolicy``) and the compiled deployed path
(``mpa_gym.agents.learned.inference.DeployedPolicy``) all call the row kernels below, so what a
policy saw in training is what it sees when deployed, by construction; only the network and the
normaliser differ between the paths (SB3's torch in float32, the compiled one in float64).

Structure, in the sim engine's style (``mpa_gym.envs.sim``): compiled kernels over one row —
``observe_row`` (features), ``act_row`` (harmonic force correction, stiffness estimator,
force–stiffness map, the record of the applied action) — over one named, typed per-episode
record (``STATE``, a numpy structured dtype; an episode starts from the zero record) and one
settings record (``SETTINGS``, packed by name from ``FeatureSpec`` and ``ActionSpec`` by
``pack_settings``); ``Frontend`` loops them over a batch for the Python callers.

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
``action_history`` H appends the last H actions the env was given, newest first: with a
regulator dead time and lag, the commands of the last (dead time + lag) / dt steps are still
on their way to the muscles, and a delayed loop is an undelayed one whose state holds the
actions in flight (Katsikopoulos & Engelbrecht 2003; rtgym sizes the buffer to the worst total
delay), so H is sized to the worst dead time + lag trained on (``previous_action`` is H = 1);
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
Each update's weight is w = 1 / (1 + (e / 1 mm)²), so a start's or a kick's transient barely
moves the regression; the rest of the update's rate, (1 − w) dt / τ, returns the estimate
towards zero, the design's own stiffness. A leg that does not track says nothing about its
stiffness, and a correction held while it does not can be what stops it tracking: a load's force
correction settling after the start correlates with X̂ until the low-passed mean of ΔF catches
up, and read as a stiffness excess of 50-80 N/m on the nominal muscles with 1.6 kg (the true
slope is −Δm ω², −7 N/m); under 40 ms of regulator dead time the stiffness it took off tipped
the loop into a 4 Hz limit cycle whose error held the weights down, and the frozen estimate
stayed (CHANGELOG.md, issue 36). The price is a shrink where the leg tracks with a steady error:
the settled estimate is the fit times the mean weight (0.70 of it under a 1 mm·|sin φ| error,
0.99 before; the held-out plants, tracked within 0.03 mm, do not see it). Only the estimate
returns; the regression's statistics keep what they learned at the low weight, so a false read
can come back for a few seconds once the leg tracks again, until new updates replace it. With
``stiffness_adapt_velocity`` the slope is X̂'s coefficient in a regression of ΔF on X̂ and V̂
together (their low-passed covariances, a 2×2 solve, V̂'s variance regularised by v₀ᵥ). Over
whole periods X̂ and V̂ are orthogonal, but the weights are not uniform over a period where the
error is not (friction and slew make it largest at the reversals), and then the part of ΔF that
follows V̂ (the friction, damping and delay corrections) leaks into X̂'s slope: on
``configs/rigs/offnominal.yaml`` (C1 −10 %) an X̂-only estimate settled near 0 N/m where about
−40 N/m corrects the stiffness, and left an 8 % stiffness error (CHANGELOG.md, issue 36). An
update pairs X̂ with the ΔF applied one control step earlier (this step's is not known until â_k
is): a lag dt that scales the slope by cos(ω dt), 0.9998 at the 3 s period, and turns a part
c·V̂ of ΔF into an X̂ slope of c·ω²·dt (4.4 N/m for c = 100 N s/m).
``stiffness_adapt_relative`` fits the excess as a share ρ of k̂, k − k̂ = ρ k̂, instead of a
number of N/m. The designed k̂ is not constant along the motion: on the 20 mm, 3 s reference it
spans 409–821 N/m, a function of X̂. A plant whose muscles are not the model's is stiffer or
softer by a share of it (rc on heldout_bladder leaves 6.0 % of stiffness error, with 0.007 %
per mm of slope against X̂), and a constant Δk leaves a relative error that varies with X̂ as
k̂ does. The estimator then regresses ΔF on the path coordinate z = ∫ k̂ dX̂ (summed from the
episode's first observation by the trapezoid rule; k̂ is a function of X̂ on the paper's
designs, so z returns to within 0.06 N of its 18-21 N swing each period, where a stiffness
profile in time would let it drift and the low-passed mean follow) in place of X̂: the force
deficit of a plant ρ stiffer is ρ z, its slope against z is ρ, and â_k = −ρ /
``stiffness_rel``, so Δk = −ρ k̂ follows k̂. v₀ becomes v₀ k̂² and the clip ±``stiffness_rel``.
With k̂ constant, z = k̂ (X̂ − X̂₀) and the two estimators apply the same correction. While a
muscle's measured pressure is at its floor (under ``ADAPT_FLOOR_BAR``) the pressures the map
asks for are not realised, so the ΔF applied is not the force the regression assumes; learning
on it winds up (on load_1kg_kmin, whose design holds the flexor at 0 bar over 15 % of the
period, the estimate lowered the stiffness until the flexor stayed at 0 bar and ran to its
clip). There nothing is learned, so the whole of each step's rate dt / τ returns the estimate
to zero (whatever the error: the rule above with a weight of zero), and nothing else is
updated. A pressure held at its upper limit, or by the regulator's slew limit,
is not realised either; the rule covers the floor only, where the kmin design puts the flexor.
The estimate that follows k̂ moves the pressures along the motion, and on a plant that is not
the model that moves the force too (CHANGELOG.md, issue 36: the held-out stiffness error falls
by up to two thirds and the position error grows).
Off the training plants, an a_k learned from the error features can go the wrong way
(CHANGELOG.md, 0.1.0, e2e9a73); the estimate needs no learning. It is a controller's
computation from its own commands and the reference, like the features, never a plant
parameter. The action space stays (a_F, a_k), so a config switches the estimator on or off
without another network; the policy's a_k is then ignored, and its Gaussian adds noise, not
bias, to PPO's gradient.

``harmonic_force_N`` adds a harmonic force correction to the policy's ΔF: an integral action
at the reference's 2nd and 3rd harmonics (``HARMONIC_FIRST`` … ``HARMONIC_LAST``), the
repetitive controller's internal model where the policy's own features stop (its harmonic
pair is the first harmonic's). Each step it integrates

    J_sh += w e sin(hφ) dt,   J_ch += w e cos(hφ) dt,   w = 1 / (1 + (ê / 3 mm)²),

each clipped to ±``HARMONIC_LIMIT_M_S``, and adds ΔF_h = g Σ_h (J_sh sin hφ + J_ch cos hφ),
clipped to ±``harmonic_force_N``, with g = ``HARMONIC_GAIN``. For an error e = A sin(hφ),
J_sh grows by w A/2 per second, so on the nominal leg (dynamic stiffness k̂ − m (hω)² ≈ 475
N/m at h = 2 on the 3 s reference) the loop closes with a time constant 2 · 475 / g ≈ 2 s;
the policy's own feedback makes the leg stiffer to ΔF and the time constant longer. It has
no phase lead: it converges where the loop beneath keeps its phase at 2ω and 3ω within 90°
of a spring's (70 ms of regulator delay costs 0.44 rad at 3ω). The trained policies' loops
do (CHANGELOG.md); a loop beneath with a resonance near these harmonics may not, as for rc.
ê is the envelope of |e| (it follows a rise at once and falls with ``HARMONIC_RELEASE_S``):
a start's or a kick's transient of 5-30 mm charges the integrals at w = 0.26-0.01. On a rig,
friction and the regulator's slew leave a steady periodic error with peaks of 1.5-2 mm at the
reversals (``configs/rigs/offnominal.yaml``), the error this correction is for, and the weight's
scale ``HARMONIC_ERROR_M`` = 3 mm lets it learn that at w = 0.7-0.8. At the estimator's 1 mm
(w = 0.2 at 2 mm) it learned there at a fifth of the rate and was still rising after 30 s. The
price is the kick of a few millimetres the paper's impulse scenario gives, which charges the
integrals nearly as if unweighted; a 4th power in place of the square (w = 0.84 at 2 mm, 0.11 at
5 mm) halved that charge, but its networks held fewer delayed plants (CHANGELOG.md, issue 36).
The estimator's weight, of e itself, would not do here: w e is then a saturating function of e,
and a first-harmonic error of the weight's scale feeds the third harmonic's integrals through
it (ff alone on heldout_bladder at 1 mm: 0.17 mm of third-harmonic error from 0.02). ê changes
little over a period (it falls by 14 % between two peaks), so w e stays nearly linear in e:
the leak is about a seventh of the e-weighted one's (tests/test_wrappers.py). On the held-out
plants, the error the policy leaves is at these harmonics (heldout_a: 0.035 mm of 0.045 at the
2nd, 0.009 at the 3rd), which a first-harmonic pair cannot hold; features for them
(``harmonics: 2`` or 3) let the network learn the same correction but cost the paper's
transients and the friction cells (CHANGELOG.md, issue 36). Like the estimator, it is a
controller's computation from its own measurements and the reference, and runs in training, in
the loaded policy and in the compiled rig path alike; the estimator pairs X̂ with the whole ΔF
applied, this correction included.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from gymnasium import spaces

from mpa_gym.model import fast
from mpa_gym.model.jit import JIT
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_range
from mpa_gym.task.contract import OBS_COS as OCOS
from mpa_gym.task.contract import OBS_KREF as OK
from mpa_gym.task.contract import OBS_KREF_SCALE
from mpa_gym.task.contract import OBS_PE as OPE
from mpa_gym.task.contract import OBS_PF as OPF
from mpa_gym.task.contract import OBS_SIN as OSIN
from mpa_gym.task.contract import OBS_V as OV
from mpa_gym.task.contract import OBS_VREF as OVR
from mpa_gym.task.contract import OBS_X as OX
from mpa_gym.task.contract import OBS_XREF as OXR

MAX_HARMONICS = 5
MAX_DELAY_S = 1.0  # [s] the bound of the observed dead time and lag
MAX_ACTION_HISTORY = 16  # actions a front-end may keep: 160 ms at 100 Hz, beyond any trained delay


@dataclass(frozen=True)
class FeatureSpec:
    """The observation features (``TrackingErrorObservation``'s kwargs; module docstring)."""

    limit_m_s: float = 0.02  # [m s] anti-windup bound of the integrals
    harmonics: int = 0  # harmonic integral pairs
    previous_action: bool = False  # append the action the env was last given
    mask_pressures: bool = False  # zero the measured pressures
    fine_error_m: float | None = None  # [m] also append clip(X̂ − X, ±this)
    errors_only: bool = False  # drop the env observation: the features alone
    remodulate: bool = False  # append each harmonic pair's resonant output and its quadrature
    # append the last H actions the env was given, newest first (previous_action: H = 1)
    action_history: int = 0
    # append the rig's regulator dead time and lag [s] (the plant's in training; identified
    # or nominal when deployed: Frontend.known_delay_s)
    delay_observation: bool = False

    def __post_init__(self) -> None:
        lim = self.limit_m_s
        if isinstance(lim, bool) or not isinstance(lim, int | float) or not 0 < lim <= 1.0:
            raise ValueError(f"limit_m_s={lim!r} must be a number in (0, 1] m s")
        h = self.harmonics
        if isinstance(h, bool) or not isinstance(h, int) or not 0 <= h <= MAX_HARMONICS:
            raise ValueError(f"harmonics={h!r} must be a whole number in [0, {MAX_HARMONICS}]")
        for name in ("previous_action", "mask_pressures", "errors_only", "remodulate",
                     "delay_observation"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}={getattr(self, name)!r} must be true or false")
        n = self.action_history
        if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= MAX_ACTION_HISTORY:
            raise ValueError(f"action_history={n!r} must be a whole number in "
                             f"[0, {MAX_ACTION_HISTORY}]")
        if self.previous_action and n:
            raise ValueError(f"previous_action=True and action_history={n}: previous_action is "
                             "action_history: 1; give one of them")
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

    @property
    def n_actions(self) -> int:
        """Number of past actions in the features (``previous_action`` is one)."""
        return self.action_history or int(self.previous_action)

    def space(self, space: spaces.Box) -> spaces.Box:
        """The observation space with the features appended, in ``observe_row``'s order."""
        m, lim = self.n_integrals, self.limit_m_s
        lo = [-1.0, -20.0] + [-lim] * m + [-1.0] * (2 * self.n_actions)
        hi = [1.0, 20.0] + [lim] * m + [1.0] * (2 * self.n_actions)
        if self.fine_error_m is not None:
            lo.append(-self.fine_error_m)
            hi.append(self.fine_error_m)
        if self.delay_observation:
            lo += [0.0, 0.0]
            hi += [MAX_DELAY_S, MAX_DELAY_S]
        if self.remodulate:
            bound = np.sqrt(2) * lim * (1 + 1e-6)  # |R|, |Q| ≤ |(I_s, I_c)|; float32 rounding
            lo += [-bound] * (2 * self.harmonics)
            hi += [bound] * (2 * self.harmonics)
        base_lo, base_hi = (([], []) if self.errors_only else (space.low, space.high))
        return spaces.Box(np.concatenate([base_lo, lo]).astype(np.float32),
                          np.concatenate([base_hi, hi]).astype(np.float32), dtype=np.float32)


# The harmonic force correction (ActionSpec.harmonic_force_N; module docs)
HARMONIC_FIRST, HARMONIC_LAST = 2, 3  # the reference harmonics it corrects
HARMONIC_GAIN = 500.0  # [N/(m s)] g: a time constant of ~2 s on the nominal leg at the 2nd
#                        harmonic; at 160 heldout_a kept 0.016 mm of its 0.035 mm 2nd-harmonic
#                        error after 30 s, at 400–1000 under 0.006, at 2500 the noise grew
# [m s] bound of its integrals (the features' default). Its output saturates sooner, at
# harmonic_force_N / g (0.002 m s at 1 N), so the integrals can wind up past that by up to
# ten times: a bound against divergence, not an anti-windup at the output's saturation
HARMONIC_LIMIT_M_S = 0.02
HARMONIC_RELEASE_S = 10.0  # [s] release time of the error's envelope ê: over the half period
#                            between two peaks of a steady error (1.5 s) ê falls by 14 %
HARMONIC_ERROR_M = 3e-3  # [m] envelope at which an update's weight halves: a start's or a
#                          kick's transient (5-30 mm) charges the integrals at 0.26-0.01 of the
#                          full rate, a rig's steady periodic error (friction and slew at the
#                          reversals: peaks of 1.5-2 mm on configs/rigs/offnominal.yaml) at 0.7-0.8
HARMONIC_MAX_N = 30.0  # [N] largest harmonic_force_N: the default config's force_N

# The stiffness estimator (ActionSpec.stiffness_adapt_s; module docs)
ADAPT_MAX_S = 60.0  # [s] its longest time constant: twenty reference periods, two episodes
ADAPT_ERROR_M = 1e-3  # [m] tracking error at which an update's weight halves: a start's or a
#                       kick's transient says nothing about the plant's stiffness
ADAPT_VAR_M2 = 1e-5  # [m²] regulariser of X̂'s variance, (3.2 mm)², a twentieth of the 20 mm
#                      reference's A²/2: a reference that barely moves gives no estimate
ADAPT_FLOOR_BAR = 0.02  # [bar] a muscle's measured pressure below this is at its floor
ADAPT_VAR_V2 = 4.4e-5  # [m²/s²] v₀ᵥ, regulariser of V̂'s variance, a twentieth of the 20 mm,
#                        3 s reference's (Aω)²/2


def adapt_time_constant(tau: Any, dt_s: float | None = None) -> float | None:
    """``stiffness_adapt_s`` checked: None (no estimator) or a time constant in
    (0, ``ADAPT_MAX_S``] s; given the control period ``dt_s``, in [``dt_s``,
    ``ADAPT_MAX_S``]: an update's weight dt/τ above 1 can turn the low-passed variances
    negative."""
    if tau is None:
        return None
    if dt_s is None:
        tau = check_range("stiffness_adapt_s", tau, 0.0, ADAPT_MAX_S, low_open=True, unit="s",
                          note="or null: no estimator")
    else:
        tau = check_range("stiffness_adapt_s", tau, dt_s, ADAPT_MAX_S, unit="s",
                          note="at least the control period dt_s, or null: no estimator")
    return tau


def check_adapt_flag(name: str, flag: Any, tau: float | None) -> bool:
    """An estimator's option ``name`` (``stiffness_adapt_velocity``,
    ``stiffness_adapt_relative``) checked: a bool, true only with an estimator (``tau``)."""
    if not isinstance(flag, bool | np.bool_):
        raise ValueError(f"{name}={flag!r} must be true or false")
    if flag and tau is None:
        raise ValueError(f"{name}=true needs stiffness_adapt_s (it changes the stiffness "
                         "estimator's regression)")
    return bool(flag)


@dataclass(frozen=True)
class ActionSpec:
    """The action map (``ForceStiffnessAction``'s kwargs; module docstring)."""

    force_N: float = 20.0  # [N] ground-force correction ΔF at a_F = ±1
    stiffness_rel: float = 0.3  # [-] stiffness correction Δk at a_k = ±1, as a share of k̂
    rate_penalty: float = 0.0  # weight of |a_t − a_{t−1}|² taken off the training reward
    # [s] time constant of the stiffness estimator whose a_k replaces the policy's (module
    # docs), at least the control period; None: the policy's own a_k
    stiffness_adapt_s: float | None = None
    # the estimator regresses ΔF on X̂ and V̂ together (module docs); False: on X̂ alone, as
    # run folders written before this field did
    stiffness_adapt_velocity: bool = False
    # the estimator fits a stiffness excess in proportion to k̂ (module docs); False: in N/m,
    # as run folders written before this field did
    stiffness_adapt_relative: bool = False
    # [N] bound of the harmonic force correction added to ΔF (module docs); None: none, as
    # run folders written before this field
    harmonic_force_N: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "stiffness_adapt_s",
                           adapt_time_constant(self.stiffness_adapt_s))
        for name in ("stiffness_adapt_velocity", "stiffness_adapt_relative"):
            object.__setattr__(self, name, check_adapt_flag(name, getattr(self, name),
                                                            self.stiffness_adapt_s))
        for name, lo, hi in (("force_N", None, 200.0), ("stiffness_rel", None, 1.0),
                             ("rate_penalty", 0.0, 100.0)):
            value = getattr(self, name)
            ok = isinstance(value, int | float) and not isinstance(value, bool) and \
                (lo <= value if lo is not None else 0 < value) and value <= hi
            if not ok:
                interval = f"[{lo:g}, {hi:g}]" if lo is not None else f"(0, {hi:g}]"
                raise ValueError(f"{name}={value!r} must be a number in {interval}")
            object.__setattr__(self, name, float(value))
        if self.harmonic_force_N is not None:
            object.__setattr__(self, "harmonic_force_N", check_range(
                "harmonic_force_N", self.harmonic_force_N, 0.0, HARMONIC_MAX_N, low_open=True,
                unit="N", note="or null: no harmonic force correction"))


# One episode's state of a controller's front-end: a typed record, one per row (env, policy
# instance). An episode starts from the zero record (``np.zeros(n, STATE)``; ``observe_row``
# restarts it at an episode's first observation).
STATE = np.dtype([
    ("integ", np.float64, (1 + 2 * MAX_HARMONICS,)),  # [m s] I_0, I_s1, I_c1, I_s2, …: the
    #                                                   first FeatureSpec.n_integrals are used
    # the actions the env was last given, newest first, clipped to [−1, 1]
    ("prev", np.float64, (MAX_ACTION_HISTORY, 2)),
    # the stiffness estimator (module docstring), all low-passed with time constant τ; its
    # regressor q is X̂ [m], or with ActionSpec.stiffness_adapt_relative the path coordinate
    # z = ∫ k̂ dX̂ [N]:
    ("est_q_mean", np.float64),  # mean of q
    ("est_force_N", np.float64),  # [N] mean of the applied ΔF
    ("est_cov_Fq", np.float64),  # covariance c of ΔF and q
    ("est_var_q", np.float64),  # variance v of q
    # the fitted slope of ΔF against q, c / (v + v₀) (with stiffness_adapt_velocity: q's
    # coefficient of the regression on q and V̂), clipped, low-passed: the stiffness excess,
    # [N/m] (q = X̂) or as a share of k̂ (q = z)
    ("est_slope", np.float64),
    # with ActionSpec.stiffness_adapt_velocity: V̂'s mean, its covariances with ΔF and q, and
    # its variance
    ("est_v_ref_mps", np.float64),  # [m/s]
    ("est_cov_N_mps", np.float64),  # [N m/s]
    ("est_cov_qv", np.float64),
    ("est_var_vv", np.float64),  # [m²/s²]
    # with ActionSpec.stiffness_adapt_relative: z and the X̂, k̂ of its last step
    ("est_path_N", np.float64),  # [N]
    ("est_last_x_ref_m", np.float64),  # [m]
    ("est_last_k_ref_N_per_m", np.float64),  # [N/m]
    ("est_applied_N", np.float64),  # [N] the ΔF applied last step, paired with the next X̂
    ("est_started", np.bool_),  # the estimator has had its first observation
    # [s] the rig's regulator dead time and lag, for FeatureSpec.delay_observation: the
    # rig's, not the episode's, so an episode's start keeps them (Frontend.new_state fills
    # them with known_delay_s; the training wrappers with each episode's plant)
    ("delay_s", np.float64, (2,)),
    # [m s] the harmonic force correction's integrals J_s2, J_c2, J_s3, J_c3, … (module docs)
    ("harm", np.float64, (2 * (HARMONIC_LAST - HARMONIC_FIRST + 1),)),
    ("harm_env_m", np.float64),  # [m] ê, the envelope of |e| that weighs its updates
])

# A front-end's settings as the kernels read them, by name: the fields of FeatureSpec and
# ActionSpec (an optional one as a flag and its value) and the control period.
SETTINGS = np.dtype([
    ("features", np.bool_),  # append FeatureSpec's features; else the observation as it is
    ("limit_m_s", np.float64),
    ("harmonics", np.int64),
    ("n_actions", np.int64),  # FeatureSpec.n_actions
    ("mask_pressures", np.bool_),
    ("fine_error", np.bool_),  # fine_error_m is not None
    ("fine_error_m", np.float64),
    ("delay_observation", np.bool_),
    ("errors_only", np.bool_),
    ("remodulate", np.bool_),
    ("force_stiffness", np.bool_),  # map (a_F, a_k) by ActionSpec; else the action as it is
    ("force_N", np.float64),
    ("stiffness_rel", np.float64),
    ("residual_scale_Pa", np.float64),  # [Pa] the residual env's pressure at action ±1
    ("adapt", np.bool_),  # stiffness_adapt_s is not None
    ("stiffness_adapt_s", np.float64),
    ("adapt_velocity", np.bool_),  # ActionSpec.stiffness_adapt_velocity
    ("adapt_relative", np.bool_),  # ActionSpec.stiffness_adapt_relative
    ("harmonic", np.bool_),  # ActionSpec.harmonic_force_N is not None
    ("harmonic_force_N", np.float64),
    ("dt_s", np.float64),  # [s] the control period: the integrals' and the estimator's step
])


def pack_settings(features: FeatureSpec | None, action: ActionSpec | None, dt_s: float,
                  residual_scale_bar: float | None = None) -> np.ndarray:
    """The ``SETTINGS`` record (an array of one) of a front-end; ``residual_scale_bar`` is the
    residual env's scale, needed with ``action``."""
    rec = np.zeros(1, SETTINGS)
    r = rec[0]
    r["dt_s"] = check_range("dt_s", dt_s, 0.0, low_open=True, unit="s")
    if features is not None:
        r["features"] = True
        for name in ("limit_m_s", "harmonics", "n_actions", "mask_pressures",
                     "errors_only", "remodulate", "delay_observation"):
            r[name] = getattr(features, name)
        r["fine_error"] = features.fine_error_m is not None
        r["fine_error_m"] = features.fine_error_m or 0.0
    if action is not None:
        if residual_scale_bar is None:
            raise ValueError("a force–stiffness action map needs residual_scale_bar (the "
                             "residual env's scale)")
        r["force_stiffness"] = True
        r["force_N"], r["stiffness_rel"] = action.force_N, action.stiffness_rel
        r["residual_scale_Pa"] = check_range("residual_scale_bar", residual_scale_bar, 0.0,
                                             low_open=True, unit="bar") * BAR
        r["adapt"] = action.stiffness_adapt_s is not None
        r["stiffness_adapt_s"] = adapt_time_constant(action.stiffness_adapt_s,
                                                     dt_s=r["dt_s"]) or 0.0
        r["adapt_velocity"] = action.stiffness_adapt_velocity
        r["adapt_relative"] = action.stiffness_adapt_relative
        r["harmonic"] = action.harmonic_force_N is not None
        r["harmonic_force_N"] = action.harmonic_force_N or 0.0
    return rec


@numba.njit(**JIT)
def restart_row(st):
    """The zero record: an episode's start (every field of ``STATE``)."""
    for i in range(st.integ.shape[0]):
        st.integ[i] = 0.0
    for i in range(st.prev.shape[0]):
        st.prev[i, 0] = 0.0
        st.prev[i, 1] = 0.0
    st.est_q_mean = 0.0
    st.est_force_N = 0.0
    st.est_cov_Fq = 0.0
    st.est_var_q = 0.0
    st.est_slope = 0.0
    st.est_applied_N = 0.0
    st.est_v_ref_mps = 0.0
    st.est_cov_N_mps = 0.0
    st.est_cov_qv = 0.0
    st.est_var_vv = 0.0
    st.est_path_N = 0.0
    st.est_last_x_ref_m = 0.0
    st.est_last_k_ref_N_per_m = 0.0
    st.est_started = False
    for i in range(st.harm.shape[0]):
        st.harm[i] = 0.0
    st.harm_env_m = 0.0


@numba.njit(**JIT)
def observe_row(raw, st, fresh, cfg, feat):
    """The features of one observation ``raw`` (the env's own) into ``feat``; returns their
    number. ``fresh``: an episode's first observation (the record restarts, the integrals stay
    zero); else the integrals take this observation's step. Without ``cfg.features``, ``feat``
    is the observation itself.

    Features: [observation (pressures zeroed if mask_pressures; left out if errors_only),
    X̂ − X, V̂ − V, I_0, (I_s1, I_c1), …, (a_{t−1}, …, a_{t−H}), (fine error), (dead time,
    lag), (R_1…R_h, Q_1…Q_h if
    remodulate)], h = 1 … harmonics; the harmonic basis sin hφ, cos hφ by the complex
    recurrence z ← z (cos φ + i sin φ) from the observed phase."""
    if fresh:
        restart_row(st)
    if not cfg.features:
        for i in range(raw.shape[0]):
            feat[i] = raw[i]
        return raw.shape[0]
    h_max, lim = cfg.harmonics, cfg.limit_m_s
    m = 1 + 2 * h_max
    e = raw[OXR] - raw[OX]
    s1, c1 = raw[OSIN], raw[OCOS]
    if not fresh:  # I ← clip(I + e · basis(φ) · dt, ±limit)
        dt = cfg.dt_s
        st.integ[0] = min(max(st.integ[0] + e * 1.0 * dt, -lim), lim)
        zr, zi = 1.0, 0.0
        for h in range(h_max):
            zr, zi = zr * c1 - zi * s1, zr * s1 + zi * c1
            st.integ[1 + 2 * h] = min(max(st.integ[1 + 2 * h] + e * zi * dt, -lim), lim)
            st.integ[2 + 2 * h] = min(max(st.integ[2 + 2 * h] + e * zr * dt, -lim), lim)
    n = 0
    if not cfg.errors_only:
        for i in range(raw.shape[0]):
            feat[n] = 0.0 if (cfg.mask_pressures and (i == OPE or i == OPF)) else raw[i]
            n += 1
    feat[n] = e
    feat[n + 1] = raw[OVR] - raw[OV]
    n += 2
    for i in range(m):
        feat[n] = st.integ[i]
        n += 1
    for i in range(cfg.n_actions):
        feat[n] = st.prev[i, 0]
        feat[n + 1] = st.prev[i, 1]
        n += 2
    if cfg.fine_error:
        feat[n] = min(max(e, -cfg.fine_error_m), cfg.fine_error_m)
        n += 1
    if cfg.delay_observation:
        feat[n] = st.delay_s[0]
        feat[n + 1] = st.delay_s[1]
        n += 2
    if cfg.remodulate:  # R_h = I_sh sin hφ + I_ch cos hφ, Q_h = I_sh cos hφ − I_ch sin hφ
        zr, zi = 1.0, 0.0
        for h in range(h_max):
            zr, zi = zr * c1 - zi * s1, zr * s1 + zi * c1
            i_s, i_c = st.integ[1 + 2 * h], st.integ[2 + 2 * h]
            feat[n + h] = i_s * zi + i_c * zr
            feat[n + h_max + h] = i_s * zr - i_c * zi
        n += 2 * h_max
    return n


@numba.njit(**JIT)
def estimate_row(st, x_ref, v_ref, e, k_ref, a_F, p_min_bar, cfg):
    """One step of the stiffness estimator (module docstring) at reference X̂ = ``x_ref``
    [m], V̂ = ``v_ref`` [m/s] (kept at the start, used with ``cfg.adapt_velocity`` only),
    tracking error ``e`` [m] and k̂ = ``k_ref`` [N/m], its record fields updated → â_k; then
    the force correction ``a_F`` applied this step, which the next update pairs with the next
    X̂. ``p_min_bar``: the lower of the two measured pressures [bar], for
    ``cfg.adapt_relative``'s floor rule (module docstring)."""
    if not st.est_started:
        st.est_force_N = 0.0
        st.est_cov_Fq = 0.0
        st.est_var_q = 0.0
        st.est_slope = 0.0
        st.est_applied_N = 0.0
        st.est_cov_N_mps = 0.0
        st.est_cov_qv = 0.0
        st.est_var_vv = 0.0
        st.est_path_N = 0.0
        st.est_last_x_ref_m, st.est_last_k_ref_N_per_m = x_ref, k_ref
        st.est_q_mean = 0.0 if cfg.adapt_relative else x_ref
        st.est_v_ref_mps, st.est_started = v_ref, True
    if cfg.adapt_relative:  # z += k̂ dX̂, by the trapezoid rule
        st.est_path_N += (0.5 * (k_ref + st.est_last_k_ref_N_per_m)
                          * (x_ref - st.est_last_x_ref_m))
        st.est_last_x_ref_m, st.est_last_k_ref_N_per_m = x_ref, k_ref
        q, v0, span = st.est_path_N, ADAPT_VAR_M2 * k_ref * k_ref, cfg.stiffness_rel
    else:
        q, v0, span = x_ref, ADAPT_VAR_M2, cfg.stiffness_rel * abs(k_ref)
    rate = cfg.dt_s / cfg.stiffness_adapt_s
    al = rate / (1.0 + (e / ADAPT_ERROR_M) ** 2)
    at_floor = cfg.adapt_relative and p_min_bar < ADAPT_FLOOR_BAR  # nothing learned there
    if not at_floor:
        st.est_q_mean += al * (q - st.est_q_mean)
        st.est_force_N += al * (st.est_applied_N - st.est_force_N)
        dq, dF = q - st.est_q_mean, st.est_applied_N - st.est_force_N
        st.est_cov_Fq += al * (dF * dq - st.est_cov_Fq)
        st.est_var_q += al * (dq * dq - st.est_var_q)
        if cfg.adapt_velocity:
            st.est_v_ref_mps += al * (v_ref - st.est_v_ref_mps)
            dv = v_ref - st.est_v_ref_mps
            st.est_cov_N_mps += al * (dF * dv - st.est_cov_N_mps)
            st.est_cov_qv += al * (dq * dv - st.est_cov_qv)
            st.est_var_vv += al * (dv * dv - st.est_var_vv)
    a_k = 0.0
    v = st.est_var_q + v0
    if at_floor:  # nothing learned: the whole rate returns it to zero (span > 0 here)
        st.est_slope -= rate * st.est_slope
        a_k = min(max(-st.est_slope / span, -1.0), 1.0)
    elif span > 0.0 and v > 0.0:  # v = 0: k̂ = 0 and no motion yet (relative), nothing to fit
        if cfg.adapt_velocity:  # q's coefficient of the regression on (q, V̂)
            vv, cqv = st.est_var_vv + ADAPT_VAR_V2, st.est_cov_qv
            fit = (st.est_cov_Fq * vv - cqv * st.est_cov_N_mps) / (v * vv - cqv * cqv)
        else:
            fit = st.est_cov_Fq / v
        slope = min(max(fit, -span), span)
        # the rest of the step's rate, what the weight kept from learning, returns the
        # estimate towards zero (module docstring: the leg not tracking)
        st.est_slope += al * (slope - st.est_slope) - (rate - al) * st.est_slope
        a_k = min(max(-st.est_slope / span, -1.0), 1.0)
    st.est_applied_N = min(max(a_F, -1.0), 1.0) * cfg.force_N
    return a_k


@numba.njit(**JIT)
def harmonic_row(st, s1, c1, e, cfg):
    """One step of the harmonic force correction (module docstring) at the reference phase
    (sin φ, cos φ) = (``s1``, ``c1``) and tracking error ``e`` [m]: its integrals in ``st``
    updated → ΔF_h [N]. The basis sin hφ, cos hφ by the features' recurrence."""
    st.harm_env_m = max(abs(e), st.harm_env_m * (1.0 - cfg.dt_s / HARMONIC_RELEASE_S))
    w = cfg.dt_s * e / (1.0 + (st.harm_env_m / HARMONIC_ERROR_M) ** 2)
    zr, zi = 1.0, 0.0
    out, j = 0.0, 0
    for h in range(1, HARMONIC_LAST + 1):
        zr, zi = zr * c1 - zi * s1, zr * s1 + zi * c1
        if h >= HARMONIC_FIRST:
            st.harm[j] = min(max(st.harm[j] + w * zi, -HARMONIC_LIMIT_M_S), HARMONIC_LIMIT_M_S)
            st.harm[j + 1] = min(max(st.harm[j + 1] + w * zr, -HARMONIC_LIMIT_M_S),
                                 HARMONIC_LIMIT_M_S)
            out += st.harm[j] * zi + st.harm[j + 1] * zr
            j += 2
    return min(max(HARMONIC_GAIN * out, -cfg.harmonic_force_N), cfg.harmonic_force_N)


@numba.njit(**JIT)
def force_stiffness_row(a_F, a_k, x_ref, k_ref, cfg, c, out):
    """(a_F, a_k) → the residual action (a_e, a_f) into ``out``: solves J(X̂) ΔP = (a_F ·
    force_N, a_k · stiffness_rel · k̂) on the nominal model (constants ``c``, ``fast.pack``)
    at X̂ = ``x_ref`` (noise-free, and where the feedforward holds the leg), V = 0, with J the
    pressure coefficients of F and k (``design.affine_in_pressures``: three evaluations, both
    being affine in each pressure); ΔP / residual scale, clipped to [−1, 1], rounded to the
    action space's float32."""
    F0, k0 = fast.force_and_stiffness(x_ref, 0.0, 0.0, 0.0, c)
    Fe, ke = fast.force_and_stiffness(x_ref, 0.0, BAR, 0.0, c)
    Ff, kf = fast.force_and_stiffness(x_ref, 0.0, 0.0, BAR, c)
    j11, j12, j21, j22 = (Fe - F0) / BAR, (Ff - F0) / BAR, (ke - k0) / BAR, (kf - k0) / BAR
    dF = min(max(a_F, -1.0), 1.0) * cfg.force_N
    dk = min(max(a_k, -1.0), 1.0) * cfg.stiffness_rel * k_ref
    det = j11 * j22 - j12 * j21
    scale = cfg.residual_scale_Pa
    out[0] = np.float32(min(max((dF * j22 - j12 * dk) / det / scale, -1.0), 1.0))
    out[1] = np.float32(min(max((j11 * dk - j21 * dF) / det / scale, -1.0), 1.0))


@numba.njit(**JIT)
def act_row(a, raw, st, cfg, c, out):
    """The env's action for the policy's action ``a`` at observation ``raw`` (the env's own)
    into ``out``: with ``cfg.force_stiffness``, a = (a_F, a_k), the harmonic force correction
    added to a_F if ``cfg.harmonic``, a_k replaced by the stiffness estimator's if
    ``cfg.adapt``, mapped by ``force_stiffness_row``; else ``a`` itself. The
    record keeps it (clipped, as the env applies it) as the next features' a_{t−1}, the older
    ones moving down the history."""
    if cfg.force_stiffness:
        x_ref = np.float64(raw[OXR])
        k_ref = np.float64(raw[OK]) * OBS_KREF_SCALE
        a_F, a_k = np.float64(a[0]), np.float64(a[1])
        if cfg.harmonic:
            dF = harmonic_row(st, np.float64(raw[OSIN]), np.float64(raw[OCOS]),
                              x_ref - np.float64(raw[OX]), cfg)
            a_F = min(max(a_F, -1.0), 1.0) + dF / cfg.force_N
        if cfg.adapt:
            a_k = estimate_row(st, x_ref, np.float64(raw[OVR]), x_ref - np.float64(raw[OX]),
                               k_ref, a_F, min(np.float64(raw[OPE]), np.float64(raw[OPF])), cfg)
        force_stiffness_row(a_F, a_k, x_ref, k_ref, cfg, c, out)
    else:
        out[0] = a[0]
        out[1] = a[1]
    for i in range(st.prev.shape[0] - 1, 0, -1):
        st.prev[i, 0] = st.prev[i - 1, 0]
        st.prev[i, 1] = st.prev[i - 1, 1]
    st.prev[0, 0] = min(max(out[0], -1.0), 1.0)
    st.prev[0, 1] = min(max(out[1], -1.0), 1.0)


@numba.njit(**JIT)
def _observe_rows(raw, state, fresh, cfg, feat):
    for i in range(raw.shape[0]):
        observe_row(raw[i], state[i], fresh[i], cfg[0], feat[i])


@numba.njit(**JIT)
def _act_rows(a, raw, state, cfg, c, out):
    for i in range(a.shape[0]):
        act_row(a[i], raw[i], state[i], cfg[0], c, out[i])


@numba.njit(**JIT)
def _estimate_rows(a_F, raw, state, cfg, out):
    for i in range(a_F.shape[0]):
        x_ref = np.float64(raw[i, OXR])
        out[i] = estimate_row(state[i], x_ref, np.float64(raw[i, OVR]),
                              x_ref - np.float64(raw[i, OX]),
                              np.float64(raw[i, OK]) * OBS_KREF_SCALE, a_F[i],
                              min(np.float64(raw[i, OPE]), np.float64(raw[i, OPF])), cfg[0])


@functools.lru_cache(maxsize=8)
def constants(params: Params) -> np.ndarray:
    """The compiled model's constants of ``params`` (``fast.pack``), packed once."""
    return fast.pack(params)


class Frontend:
    """A controller's front-end (features ``features``, action map ``action``, control period
    ``dt_s``) over batches of rows: the row kernels looped, for the Python callers. The state
    is theirs: an array of ``STATE`` records, one per row (``new_state``).

    ``action`` needs ``residual_scale_bar``, the residual env's scale [bar]."""

    def __init__(self, features: FeatureSpec | None, action: ActionSpec | None, dt_s: float,
                 residual_scale_bar: float | None = None, params: Params = DEFAULT_PARAMS
                 ) -> None:
        self.features, self.action, self.dt = features, action, float(dt_s)
        self.settings = pack_settings(features, action, dt_s, residual_scale_bar)
        self.consts = constants(params)
        # [s] (dead time, lag) of the rig it runs on, for the delay observation: identified
        # (``mpa-gym identify``) or the scenario's; (n, 2): one pair per row of a stack of n
        # policies (``LearnedPolicy.stack_rows``)
        self.known_delay_s: tuple[float, float] | np.ndarray = (0.0, 0.0)

    def new_state(self, n: int) -> np.ndarray:
        """``n`` records at an episode's start on the rig of ``known_delay_s`` (row i on the
        i-th pair's, if it holds one per row)."""
        told = np.asarray(self.known_delay_s, dtype=np.float64)
        if told.ndim == 2 and told.shape[0] != n:
            raise ValueError(f"a stack of {told.shape[0]} policies got a batch of {n} "
                             "observations; row i is policy i's")
        st = new_state(n)
        st["delay_s"] = told
        return st

    def width(self, obs_dim: int) -> int:
        """Number of features of an observation with ``obs_dim`` columns."""
        return _width(self.features, obs_dim)

    def observe(self, raw: np.ndarray, state: np.ndarray, fresh: np.ndarray | bool
                ) -> np.ndarray:
        """(n, d) observations → (n, ``width(d)``) float32 features (``observe_row``), the
        records ``state`` (n,) updated in place; ``fresh`` (n,) or one flag for all."""
        raw = np.ascontiguousarray(raw, dtype=np.float32).reshape(len(state), -1)
        fresh = np.broadcast_to(np.asarray(fresh, dtype=np.bool_), (len(state),))
        feat = np.empty((len(state), self.width(raw.shape[1])), dtype=np.float32)
        _observe_rows(raw, state, np.ascontiguousarray(fresh), self.settings, feat)
        return feat

    def act(self, action: np.ndarray, raw: np.ndarray, state: np.ndarray) -> np.ndarray:
        """(n, 2) policy actions at the observations ``raw`` (n, d) → the env's actions (n, 2)
        in float32 (``act_row``), the records ``state`` updated in place."""
        a = np.ascontiguousarray(action, dtype=np.float64).reshape(len(state), 2)
        raw = np.ascontiguousarray(raw, dtype=np.float32).reshape(len(state), -1)
        out = np.empty((len(state), 2))
        _act_rows(a, raw, state, self.settings, self.consts, out)
        return out.astype(np.float32)

    def estimate(self, a_F: np.ndarray, raw: np.ndarray, state: np.ndarray) -> np.ndarray:
        """(n,) â_k of the stiffness estimator (``estimate_row``) after this step's update at
        the observations ``raw``, the force corrections ``a_F`` then recorded as applied."""
        if not self.settings[0]["adapt"]:
            raise ValueError("this front-end has no stiffness estimator (stiffness_adapt_s)")
        a_F = np.ascontiguousarray(a_F, dtype=np.float64).reshape(len(state))
        raw = np.ascontiguousarray(raw, dtype=np.float32).reshape(len(state), -1)
        out = np.empty(len(state))
        _estimate_rows(a_F, raw, state, self.settings, out)
        return out


@functools.lru_cache(maxsize=64)
def _width(features: FeatureSpec | None, obs_dim: int) -> int:
    """``Frontend.width``, once per spec (the space's length: one layout)."""
    if features is None:
        return obs_dim
    return features.space(spaces.Box(-np.inf, np.inf, (obs_dim,))).shape[0]


def new_state(n: int) -> np.ndarray:
    """``n`` records at an episode's start."""
    return np.zeros(n, STATE)
