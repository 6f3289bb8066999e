"""Feedforward design (Eq. 16), joint stiffness (Eq. 23) and stiffness-based design (Eq. 25).

A design is a pair of time functions (P'_e(t), P'_f(t)) that makes the reference (X̂, V̂) of Eq. (21)
a solution of Eq. (15) for the *design* model. P'_f comes either from a pattern (Eq. 22) or from a
stiffness target k̂(t) (Eq. 25); P'_e then follows from Eq. (16). Because Eq. (16) is affine in P'_f
and the ground force is affine in both pressures, k is affine in P'_f along the reference, so
Eq. (25) is solved in closed form.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike

from mpa_gym.design.reference import FlexorPattern, Reference
from mpa_gym.model import mpa
from mpa_gym.model.dynamics import force_terms
from mpa_gym.model.leg import kinematics
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_range

P_MAX_DEFAULT = 7.0 * BAR  # [Pa] default upper pressure limit (docs/design.md#physics)


class InfeasibleDesignError(ValueError):
    """A requested design needs pressures or MPA lengths outside their allowed ranges."""


def feedforward_extensor_pressure(
    x: ArrayLike, v: ArrayLike, a: ArrayLike, Pf: ArrayLike, p: Params = DEFAULT_PARAMS
) -> np.ndarray:
    """[Pa] P'_e(X̂, V̂, P'_f) of Eq. (16).

    P'_e = [V_r dW_e/dL_e − γ v_e − (m dV̂/dt + m g + G_f f_f) / G_e] / (dV_be/dL_e)

    Parameters
    ----------
    x, v, a : reference position [m], velocity [m/s] and acceleration [m/s^2].
    Pf : flexor gauge pressure P'_f [Pa].
    """
    kin = kinematics(x, p.leg, p.mpa)
    v = np.asarray(v, dtype=float)
    ff = mpa.force(Pf, kin.Lf, -kin.Gf * v, p.mpa)
    m, g = p.leg.m, p.leg.g
    num = (
        p.mpa.Vr * mpa.dW_dL(kin.Le, p.mpa)
        - p.mpa.gamma * kin.Ge * v
        - (m * np.asarray(a, dtype=float) + m * g + kin.Gf * ff) / kin.Ge
    )
    return num / mpa.dVb_dL(kin.Le, p.mpa)


def joint_stiffness(
    x: ArrayLike, v: ArrayLike, Pe: ArrayLike, Pf: ArrayLike, p: Params = DEFAULT_PARAMS
) -> np.ndarray:
    """[N/m] k = −∂F/∂X at fixed pressures and V (Eq. 23); k = −m a_2."""
    return -force_terms(x, v, Pe, Pf, p).dF_dX


class AffineInPf(NamedTuple):
    """Along the reference, with P'_e from Eq. (16): P'_e = e0 + e1 P'_f and k = k0 + k1 P'_f."""

    e0: np.ndarray  # [Pa]
    e1: np.ndarray  # [-]
    k0: np.ndarray  # [N/m]
    k1: np.ndarray  # [N/m/Pa]


def affine_in_pf(
    x: ArrayLike, v: ArrayLike, a: ArrayLike, p: Params = DEFAULT_PARAMS
) -> AffineInPf:
    """Coefficients of P'_e (Eq. 16) and k (Eq. 23 through Eq. 25) as affine functions of P'_f.

    Both are exactly affine, so two evaluations (P'_f = 0 and 1 bar) determine them.
    """
    zero = np.zeros(np.broadcast(np.asarray(x), np.asarray(v), np.asarray(a)).shape)
    e0 = feedforward_extensor_pressure(x, v, a, zero, p)
    e_bar = feedforward_extensor_pressure(x, v, a, zero + BAR, p)
    k0 = joint_stiffness(x, v, e0, zero, p)
    k_bar = joint_stiffness(x, v, e_bar, zero + BAR, p)
    return AffineInPf(e0, (e_bar - e0) / BAR, k0, (k_bar - k0) / BAR)


class AffineInPressures(NamedTuple):
    """At fixed (X, V): F = F0 + J[0] · (P'_e, P'_f) and k = k0 + J[1] · (P'_e, P'_f)."""

    F0: np.ndarray  # [N]
    k0: np.ndarray  # [N/m]
    J: np.ndarray  # (..., 2, 2): [[∂F/∂P'_e, ∂F/∂P'_f], [∂k/∂P'_e, ∂k/∂P'_f]] [N/Pa], [N/m/Pa]


def affine_in_pressures(x: ArrayLike, v: ArrayLike, p: Params = DEFAULT_PARAMS
                        ) -> AffineInPressures:
    """F (Eq. 5) and k (Eq. 23) as affine functions of both pressures at fixed (X, V).

    Each MPA force is affine in its own pressure, so three evaluations (0, 1 bar on either MPA)
    determine them exactly. Used to map a (force, stiffness) correction to pressures.
    """
    x, v = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(v, dtype=float))
    # the three evaluations (0, 0), (1 bar, 0), (0, 1 bar) as one call on a leading axis of 3:
    # element-wise, so each equals its own call, at a third of the per-call overhead
    shape = (3, *x.shape)
    on = np.array([0.0, BAR, 0.0]).reshape((3,) + (1,) * x.ndim)
    off = np.array([0.0, 0.0, BAR]).reshape((3,) + (1,) * x.ndim)
    t = force_terms(np.broadcast_to(x, shape), np.broadcast_to(v, shape),
                    np.broadcast_to(on, shape), np.broadcast_to(off, shape), p)
    F, dF_dX = t.F, t.dF_dX
    J = np.empty((*x.shape, 2, 2))
    J[..., 0, 0], J[..., 0, 1] = (F[1] - F[0]) / BAR, (F[2] - F[0]) / BAR
    J[..., 1, 0] = -(dF_dX[1] - dF_dX[0]) / BAR
    J[..., 1, 1] = -(dF_dX[2] - dF_dX[0]) / BAR
    return AffineInPressures(F[0], -dF_dX[0], J)


def flexor_pressure_for_stiffness(
    k_hat: ArrayLike, x: ArrayLike, v: ArrayLike, a: ArrayLike, p: Params = DEFAULT_PARAMS
) -> np.ndarray:
    """[Pa] P'_f that gives joint stiffness k̂ along the reference, Eq. (25) in closed form."""
    c = affine_in_pf(x, v, a, p)
    if np.any(np.abs(c.k1) < 1e-12):
        raise InfeasibleDesignError("k does not depend on P'_f here: Eq. (25) has no solution")
    return (np.asarray(k_hat, dtype=float) - c.k0) / c.k1


def feasible_stiffness_range(
    x: ArrayLike, v: ArrayLike, a: ArrayLike, p: Params = DEFAULT_PARAMS,
    p_max: float = P_MAX_DEFAULT,
) -> tuple[np.ndarray, np.ndarray]:
    """[N/m] (k_lo, k_hi): the k̂ reachable with 0 ≤ P'_f, P'_e ≤ p_max; NaN where none is."""
    c = affine_in_pf(x, v, a, p)
    # P'_f ∈ [0, p_max] and e0 + e1 P'_f ∈ [0, p_max]
    with np.errstate(divide="ignore", invalid="ignore"):
        b1 = np.where(c.e1 != 0.0, (0.0 - c.e0) / c.e1, -np.inf)
        b2 = np.where(c.e1 != 0.0, (p_max - c.e0) / c.e1, np.inf)
    lo = np.maximum(0.0, np.minimum(b1, b2))
    hi = np.minimum(p_max, np.maximum(b1, b2))
    const_ok = (c.e1 != 0.0) | ((c.e0 >= 0.0) & (c.e0 <= p_max))
    ok = (lo <= hi) & const_ok
    k_a, k_b = c.k0 + c.k1 * lo, c.k0 + c.k1 * hi
    return (np.where(ok, np.minimum(k_a, k_b), np.nan), np.where(ok, np.maximum(k_a, k_b), np.nan))


# --------------------------------------------------------------------------- stiffness targets
class StiffnessTarget(Protocol):
    """A desired joint stiffness k̂(t) [N/m]."""

    def __call__(self, t: ArrayLike) -> np.ndarray: ...


@dataclass(frozen=True)
class ConstantStiffness:
    """k̂(t) = value."""

    value: float  # [N/m]

    def __post_init__(self) -> None:
        check_range("stiffness_const_N_per_m", self.value, unit="N/m")

    def __call__(self, t: ArrayLike) -> np.ndarray:
        return np.full(np.shape(t), self.value)


@dataclass(frozen=True)
class StiffnessProfile:
    """k̂(t) interpolated linearly, periodically with ``period``, between samples (t_s, k)."""

    t_s: tuple[float, ...]
    k: tuple[float, ...]  # [N/m]
    period: float  # [s]

    def __post_init__(self) -> None:
        if len(self.t_s) != len(self.k) or len(self.t_s) < 2:
            raise ValueError(f"stiffness profile needs >= 2 (t, k) pairs of equal length, got "
                             f"{len(self.t_s)} times and {len(self.k)} values")
        for i, (ti, ki) in enumerate(zip(self.t_s, self.k, strict=True)):
            check_range(f"stiffness_profile.t_s[{i}]", ti, 0.0, self.period, unit="s")
            check_range(f"stiffness_profile.k[{i}]", ki, unit="N/m")
        if np.any(np.diff(self.t_s) <= 0):
            raise ValueError("stiffness_profile.t_s must be strictly increasing")

    def __call__(self, t: ArrayLike) -> np.ndarray:
        return np.interp(np.asarray(t, dtype=float), self.t_s, self.k, period=self.period)


@dataclass(frozen=True)
class StiffnessEnvelope:
    """k̂_max or k̂_min of Fig. 11: the upper or lower limit of the Fig. 9 sweep.

    The sweep is Eq. (22) with P'_f0 = ``pf_mean`` and A_f on ``n_amps`` values spanning
    [−P'_f0, P'_f0], P'_e from Eq. (16) and k from Eq. (23), along the reference.
    """

    kind: str  # "kmax" or "kmin"
    reference: Reference
    pf_mean: float = 0.4 * BAR  # [Pa] P'_f0 of Fig. 9
    n_amps: int = 9
    params: Params = field(default_factory=lambda: DEFAULT_PARAMS)

    def __post_init__(self) -> None:
        if self.kind not in ("kmax", "kmin"):
            raise ValueError(f"stiffness={self.kind!r} must be 'kmax' or 'kmin'")
        if int(self.n_amps) < 2:
            raise ValueError(f"n_amps={self.n_amps!r} must be >= 2")

    @property
    def amps(self) -> np.ndarray:
        return np.linspace(-self.pf_mean, self.pf_mean, int(self.n_amps))

    def __call__(self, t: ArrayLike) -> np.ndarray:
        k = stiffness_sweep(self.reference, self.pf_mean, self.amps, t, self.params)
        return k.max(axis=0) if self.kind == "kmax" else k.min(axis=0)


def stiffness_sweep(
    reference: Reference, pf_mean: float, amps: ArrayLike, t: ArrayLike,
    p: Params = DEFAULT_PARAMS,
) -> np.ndarray:
    """[N/m] k(t) for each flexor amplitude A_f (Fig. 9): shape (len(amps), *t.shape)."""
    t = np.asarray(t, dtype=float)
    x, v, a = reference.position(t), reference.velocity(t), reference.acceleration(t)
    pf = pf_mean + np.asarray(amps, dtype=float).reshape(-1, *([1] * t.ndim)) * np.sin(
        reference.omega * t
    )
    pe = feedforward_extensor_pressure(x, v, a, pf, p)
    return joint_stiffness(x, v, pe, pf, p)


# --------------------------------------------------------------------------- designs
class DesignSample(NamedTuple):
    """A design evaluated at times t (all arrays of t's shape, SI units)."""

    t: np.ndarray  # [s]
    x_ref: np.ndarray  # [m]
    v_ref: np.ndarray  # [m/s]
    pe: np.ndarray  # [Pa] P'_e
    pf: np.ndarray  # [Pa] P'_f
    k: np.ndarray  # [N/m] joint stiffness along the reference, Eq. (23)


@dataclass(frozen=True)
class Violation:
    """A stretch of time in which one quantity leaves its allowed range."""

    quantity: str  # "P'_e", "P'_f", "L_e" or "L_f"
    t_start: float  # [s]
    t_end: float  # [s]
    t_worst: float  # [s]
    value: float  # worst value (Pa for pressures, m for lengths)
    low: float
    high: float

    @property
    def amount(self) -> float:
        """How far the worst value lies outside [low, high] (same unit as value)."""
        return max(self.low - self.value, self.value - self.high)

    def describe(self) -> str:
        if self.quantity.startswith("P"):
            scale, unit = 1.0 / BAR, "bar"
        else:
            scale, unit = 1e3, "mm"
        return (
            f"{self.quantity} = {self.value * scale:.4g} {unit} at t = {self.t_worst:.3f} s "
            f"(outside [{self.low * scale:.4g}, {self.high * scale:.4g}] {unit} by "
            f"{self.amount * scale:.4g} {unit}, "
            f"from t = {self.t_start:.3f} s to {self.t_end:.3f} s)"
        )


@dataclass(frozen=True)
class FeasibilityReport:
    violations: tuple[Violation, ...]

    @property
    def feasible(self) -> bool:
        return not self.violations

    def describe(self) -> str:
        if self.feasible:
            return "feasible"
        return "infeasible: " + "; ".join(v.describe() for v in self.violations)


def _violations(name: str, t: np.ndarray, value: np.ndarray, low: float, high: float
                ) -> list[Violation]:
    bad = (value < low) | (value > high) | ~np.isfinite(value)
    out: list[Violation] = []
    idx = np.flatnonzero(bad)
    if idx.size == 0:
        return out
    splits = np.flatnonzero(np.diff(idx) > 1) + 1
    for run in np.split(idx, splits):
        vals = value[run]
        excess = np.where(np.isfinite(vals), np.maximum(low - vals, vals - high), np.inf)
        w = run[int(np.argmax(excess))]
        out.append(Violation(name, float(t[run[0]]), float(t[run[-1]]), float(t[w]),
                             float(value[w]), low, high))
    return out


@dataclass(frozen=True)
class FeedforwardDesign:
    """Feedforward inputs for a reference: P'_f from a pattern (Eq. 22) or a stiffness target
    (Eq. 25), P'_e from Eq. (16), all on the design model ``params``."""

    reference: Reference = field(default_factory=Reference)
    flexor: FlexorPattern | None = None
    stiffness: StiffnessTarget | None = None
    params: Params = field(default_factory=lambda: DEFAULT_PARAMS)

    def __post_init__(self) -> None:
        if (self.flexor is None) == (self.stiffness is None):
            raise ValueError("give exactly one of flexor (Eq. 22 pattern) and stiffness (Eq. 25 "
                             "target)")
        self.reference.check_reachable(self.params.leg)

    @property
    def period(self) -> float:
        return self.reference.period

    def flexor_pressure(self, t: ArrayLike) -> np.ndarray:
        """[Pa] P'_f(t)."""
        if self.flexor is not None:
            return self.flexor(t)
        r = self.reference
        assert self.stiffness is not None
        return flexor_pressure_for_stiffness(
            self.stiffness(t), r.position(t), r.velocity(t), r.acceleration(t), self.params)

    def pressures(self, t: ArrayLike) -> np.ndarray:
        """[Pa] (P'_e, P'_f) at t, shape (*t.shape, 2), extensor first."""
        r = self.reference
        pf = self.flexor_pressure(t)
        pe = feedforward_extensor_pressure(r.position(t), r.velocity(t), r.acceleration(t), pf,
                                           self.params)
        return np.stack([pe, pf], axis=-1)

    def sample(self, t: ArrayLike) -> DesignSample:
        """Reference, pressures and joint stiffness at times t."""
        t = np.asarray(t, dtype=float)
        r = self.reference
        x, v = r.position(t), r.velocity(t)
        pe, pf = np.moveaxis(self.pressures(t), -1, 0)
        return DesignSample(t, x, v, pe, pf, joint_stiffness(x, v, pe, pf, self.params))

    def feasibility(self, n_samples: int = 601, p_max: float = P_MAX_DEFAULT
                    ) -> FeasibilityReport:
        """Check 0 ≤ P' ≤ p_max and b/√3 < L < b over one period on ``n_samples`` times."""
        check_range("p_max_bar", p_max / BAR, 0.0, low_open=True, unit="bar")
        t = np.linspace(0.0, self.period, int(n_samples))
        s = self.sample(t)
        kin = kinematics(s.x_ref, self.params.leg, self.params.mpa)
        lo, hi = self.params.mpa.length_domain
        eps = 1e-12 * hi  # the open interval (lo, hi), as closed bounds for reporting
        v = [*_violations("P'_e", t, s.pe, 0.0, p_max), *_violations("P'_f", t, s.pf, 0.0, p_max),
             *_violations("L_e", t, kin.Le, lo + eps, hi - eps),
             *_violations("L_f", t, kin.Lf, lo + eps, hi - eps)]
        return FeasibilityReport(tuple(v))

    def require_feasible(self, n_samples: int = 601, p_max: float = P_MAX_DEFAULT
                         ) -> FeedforwardDesign:
        """Return self, or raise InfeasibleDesignError saying where and by how much."""
        rep = self.feasibility(n_samples, p_max)
        if rep.feasible:
            return self
        msg = rep.describe()
        if self.stiffness is not None:
            t = np.array([v.t_worst for v in rep.violations])
            r = self.reference
            k_lo, k_hi = feasible_stiffness_range(r.position(t), r.velocity(t),
                                                  r.acceleration(t), self.params, p_max)
            k_req = self.stiffness(t)
            msg += ". Requested k̂ vs feasible range: " + "; ".join(
                f"t = {ti:.3f} s: k̂ = {kr:.1f} N/m, allowed [{lo_:.1f}, {hi_:.1f}] N/m"
                for ti, kr, lo_, hi_ in zip(t, k_req, k_lo, k_hi, strict=True))
        raise InfeasibleDesignError(msg)


def constant_flexor(pf_bar: float, period: float = 3.0) -> FlexorPattern:
    """Constant P'_f (Fig. 3: 0.5 bar)."""
    return FlexorPattern(mean=pf_bar * BAR, amp=0.0, period=period)

