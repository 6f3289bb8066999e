"""Ground force (Eq. 5), its partial derivatives, the hip dynamics (Eq. 15) and integrators.

State ``y = [X, V]`` (hip height [m], hip velocity [m/s]) with shape ``(..., 2)``; inputs are the
gauge pressures ``(P'_e, P'_f)`` [Pa] and an external vertical force ``f_ext`` [N] on the hip.
Every function broadcasts, so the same code steps one leg or an array of legs.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike
from scipy.integrate import solve_ivp

from mpa_gym.model import mpa
from mpa_gym.model.leg import kinematics
from mpa_gym.model.params import Params
from mpa_gym.model.xp import Array, tanh


class ForceTerms(NamedTuple):
    """Ground force and what it is made of (arrays broadcast like X)."""

    F: Array  # [N] ground reaction force, Eq. (5)
    fe: Array  # [N] extensor tension, Eq. (6)
    ff: Array  # [N] flexor tension, Eq. (7)
    dF_dX: Array  # [N/m] ∂F/∂X at fixed P', V  (k = −∂F/∂X, Eq. 23)
    dF_dV: Array  # [N s/m] ∂F/∂V at fixed P', X  (m a_1, Eq. 18, 20)


def ground_force(X: Array, V: Array, Pe: Array, Pf: Array, p: Params) -> Array:
    """[N] F(X, V, P'_e, P'_f) = G_e f_e − G_f f_f, Eq. (5)-(7), (13), (14)."""
    kin = kinematics(X, p.leg, p.mpa)
    fe = mpa.force(Pe, kin.Le, kin.Ge * V, p.mpa)
    ff = mpa.force(Pf, kin.Lf, -kin.Gf * V, p.mpa)
    return kin.Ge * fe - kin.Gf * ff


def force_terms(X: Array, V: Array, Pe: Array, Pf: Array, p: Params) -> ForceTerms:
    """F of Eq. (5) with its analytic partials ∂F/∂X (Eq. 23) and ∂F/∂V (Eq. 20).

    With dL_e/dX = −G_e, dL_f/dX = G_f, v_e = G_e V, v_f = −G_f V:

    ∂F/∂X = G_e' f_e − G_e² ∂f_e/∂L + G_e G_e' V ∂f_e/∂v − G_f' f_f − G_f² ∂f_f/∂L
            + G_f G_f' V ∂f_f/∂v
    ∂F/∂V = G_e² ∂f_e/∂v + G_f² ∂f_f/∂v

    and ∂f/∂v = −γ for the paper's MPA (braid friction off), which gives Eq. (20) and (23).
    """
    kin = kinematics(X, p.leg, p.mpa)
    ve, vf = kin.Ge * V, -kin.Gf * V
    fe = mpa.force(Pe, kin.Le, ve, p.mpa)
    ff = mpa.force(Pf, kin.Lf, vf, p.mpa)
    dfe_dv = mpa.dforce_dv(Pe, kin.Le, ve, p.mpa)
    dff_dv = mpa.dforce_dv(Pf, kin.Lf, vf, p.mpa)
    F = kin.Ge * fe - kin.Gf * ff
    dF_dX = (
        kin.dGe * fe
        - kin.Ge**2 * mpa.dforce_dL(Pe, kin.Le, p.mpa, ve)
        + kin.Ge * kin.dGe * V * dfe_dv
        - kin.dGf * ff
        - kin.Gf**2 * mpa.dforce_dL(Pf, kin.Lf, p.mpa, vf)
        + kin.Gf * kin.dGf * V * dff_dv
    )
    dF_dV = kin.Ge**2 * dfe_dv + kin.Gf**2 * dff_dv
    return ForceTerms(F, fe, ff, dF_dX, dF_dV)


def slider_friction(V: Array, p: Params) -> Array:
    """[N] friction of the hip slider on the hip, f_s = −F_c tanh(V / v_s) − c_s V.

    Coulomb (F_c) plus viscous (c_s) friction, not in the paper's Eq. (15) (0 by default). The
    sign of V is regularised by tanh over v_s (``LegParams.friction_v``, 5 mm/s by default) so
    that the right-hand side stays smooth and fixed-step RK4 keeps its order; f_s V ≤ 0 always.
    """
    lg = p.leg
    return -lg.friction_coulomb * tanh(V / lg.friction_v) - lg.friction_viscous * V


def mechanical_energy(X: Array, V: Array, Pe: Array, Pf: Array, p: Params) -> Array:
    """[J] E = m V²/2 + m g X + U(P'_e, L_e) + U(P'_f, L_f), U = −P' V_b(L) + V_r W(L).

    U is the potential of the MPA's static tension at fixed pressure (dU/dL = f at v = 0,
    Eq. 2), so with constant pressures and no external force dE/dt = −``dissipated_power``.
    """
    kin = kinematics(X, p.leg, p.mpa)

    def U(P: Array, L: Array) -> Array:
        return -P * mpa.bladder_volume(L, p.mpa) + p.mpa.Vr * mpa.strain_energy_density(L, p.mpa)

    return 0.5 * p.leg.m * V**2 + p.leg.m * p.leg.g * X + U(Pe, kin.Le) + U(Pf, kin.Lf)


def dissipated_power(X: Array, V: Array, Pe: Array, Pf: Array, p: Params) -> Array:
    """[W] what the MPA viscosity (Eq. 4), the braid friction and the slider friction take out:
    γ (v_e² + v_f²) + μ_b (f_Pe tanh(v_e/v_b) v_e + f_Pf tanh(v_f/v_b) v_f) − f_s V ≥ 0."""
    kin = kinematics(X, p.leg, p.mpa)
    ve, vf = kin.Ge * V, -kin.Gf * V
    d = p.mpa.gamma * (ve**2 + vf**2) - slider_friction(V, p) * V
    if p.mpa.friction:
        d = d + (mpa.braid_friction(Pe, kin.Le, ve, p.mpa) * ve
                 + mpa.braid_friction(Pf, kin.Lf, vf, p.mpa) * vf)
    return d


def leg_dynamics(
    t: float,
    y: ArrayLike,
    u: ArrayLike,
    p: Params,
    f_ext: ArrayLike = 0.0,
) -> np.ndarray:
    """dy/dt = [V, (F + f_s + f_ext)/m − g], Eq. (15) with an external force on the hip
    (and the slider friction f_s of ``slider_friction``, 0 for the paper's plant).

    Parameters
    ----------
    t : time [s] (unused: the plant is time-invariant; kept for the f(t, x, u, params) form).
    y : state ``[..., (X, V)]``.
    u : pressures ``[..., (P'_e, P'_f)]`` [Pa].
    p : plant parameters (its ``leg.m`` is the total moving mass).
    f_ext : external vertical force [N], positive upward.
    """
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float)
    if y.ndim == 1 and u.ndim == 1:  # one leg: the float path of the kernels
        X, V = float(y[0]), float(y[1])
        F = ground_force(X, V, float(u[0]), float(u[1]), p) + slider_friction(V, p)
        return np.array((V, (F + float(f_ext)) / p.leg.m - p.leg.g))
    X, V = y[..., 0], y[..., 1]
    F = ground_force(X, V, u[..., 0], u[..., 1], p) + slider_friction(V, p)
    dV = (F + np.asarray(f_ext, dtype=float)) / p.leg.m - p.leg.g
    return np.stack(np.broadcast_arrays(V, dV), axis=-1)


Rhs = Callable[[float, np.ndarray], np.ndarray]


def rk4_step(f: Rhs, t: float, y: np.ndarray, dt: float) -> np.ndarray:
    """One classical fourth-order Runge-Kutta step of dy/dt = f(t, y); y of any shape."""
    k1 = f(t, y)
    k2 = f(t + 0.5 * dt, y + 0.5 * dt * k1)
    k3 = f(t + 0.5 * dt, y + 0.5 * dt * k2)
    k4 = f(t + dt, y + dt * k3)
    return y + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def integrate_rk4(f: Rhs, t0: float, y0: ArrayLike, dt: float, n_steps: int) -> np.ndarray:
    """Fixed-step RK4 from ``t0``: returns the states at t0, t0 + dt, …, shape (n_steps + 1, *y0).

    ``y0`` may be one state ``(2,)`` or a batch ``(N, 2)``; ``f`` must broadcast accordingly.
    """
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt={dt!r} must be a finite number > 0 s")
    if int(n_steps) != n_steps or n_steps < 0:
        raise ValueError(f"n_steps={n_steps!r} must be a whole number >= 0")
    y = np.array(y0, dtype=float)
    out = np.empty((int(n_steps) + 1, *y.shape))
    out[0] = y
    for i in range(int(n_steps)):
        y = rk4_step(f, t0 + i * dt, y, dt)
        out[i + 1] = y
    return out


def integrate_reference(
    f: Rhs,
    t_eval: ArrayLike,
    y0: ArrayLike,
    *,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    breakpoints: tuple[float, ...] = (),
) -> np.ndarray:
    """Accuracy reference: scipy ``solve_ivp`` (DOP853) at ``t_eval``; returns shape (len, 2).

    ``breakpoints`` are times where f is discontinuous (an impulse starting or ending); the
    integration restarts there so the adaptive step never straddles them.
    """
    t_eval = np.asarray(t_eval, dtype=float)
    t0, t1 = float(t_eval[0]), float(t_eval[-1])
    edges = [t0, *sorted(b for b in breakpoints if t0 < b < t1), t1]
    y = np.asarray(y0, dtype=float)
    out = np.empty((t_eval.size, y.size))
    for a, b in itertools.pairwise(edges):
        last = b == t1
        mask = (t_eval >= a) & ((t_eval <= b) if last else (t_eval < b))
        te = t_eval[mask]
        if te.size == 0 or te[-1] < b:
            te = np.append(te, b)  # the segment's end state starts the next segment
        sol = solve_ivp(f, (a, b), y, method="DOP853", rtol=rtol, atol=atol, t_eval=te)
        if not sol.success:
            raise RuntimeError(f"solve_ivp failed on [{a}, {b}] s: {sol.message}")
        out[mask] = sol.y[:, : int(mask.sum())].T
        y = sol.y[:, -1]
    return out


RhsU = Callable[[np.ndarray, np.ndarray], np.ndarray]


def rk4_step_u(f: RhsU, y: np.ndarray, u0: np.ndarray, um: np.ndarray, u1: np.ndarray,
               dt: float) -> np.ndarray:
    """RK4 step of dy/dt = f(y, u(t)) with the input known at t, t + dt/2 and t + dt.

    For a time-varying input this is the classical RK4 of dy/dt = f(y, u(t)); it is how a
    feedforward that is a closed-form function of time is applied without interpolation error.
    """
    k1 = f(y, u0)
    k2 = f(y + 0.5 * dt * k1, um)
    k3 = f(y + 0.5 * dt * k2, um)
    k4 = f(y + dt * k3, u1)
    return y + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def regulator_rate(P: Array, cmd: Array, p: Params) -> Array:
    """[Pa/s] dP'/dt = sat((c − P') / τ, r) of ``RegulatorParams`` (τ > 0 or r > 0).

    With τ = 0 and r > 0 it is r sign(c − P'): the exact but discontinuous rate limiter, for
    accuracy references only (fixed-step integrators use ``regulator_pressure``).
    """
    reg = p.regulator
    if reg.lag > 0.0:
        rate = (cmd - P) / reg.lag
        return np.clip(rate, -reg.slew, reg.slew) if reg.slew > 0.0 else rate
    return reg.slew * np.sign(cmd - P)


def regulator_pressure(P0: Array, cmd: Array, s: Array, p: Params) -> Array:
    """[Pa] P'(s): the exact solution of the regulator ODE from P'(0) = P0 under a command held
    at ``cmd`` for s ≥ 0 seconds (the dead time is the caller's: ``cmd`` is the delayed one).

    e = c − P0. With a lag τ and a slew r: ramp at r sign(e) while |c − P'| > r τ, i.e. until
    s₁ = (|e| − r τ)/r, then the exponential c − sign(e) r τ e^(−(s − s₁)/τ) (the two join
    with the same slope r). Without a slew limit s₁ ≤ 0 and it is c − e e^(−s/τ). With τ = 0:
    P0 + clip(e, −r s, r s), i.e. the ramp until c is reached (or c at once when r = 0).
    """
    reg = p.regulator
    tau, r = reg.lag, reg.slew
    P0, cmd, s = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (P0, cmd, s)))
    e = cmd - P0
    if tau == 0.0:
        return cmd.copy() if r == 0.0 else P0 + np.clip(e, -r * s, r * s)
    if r == 0.0:
        return cmd - e * np.exp(-s / tau)
    s1 = np.maximum((np.abs(e) - r * tau) / r, 0.0)
    ramp = P0 + np.sign(e) * r * np.minimum(s, s1)
    e1 = cmd - ramp  # what is left when the exponential takes over
    return np.where(s <= s1, ramp, cmd - e1 * np.exp(-(s - s1) / tau))


def has_pressure_state(p: Params) -> bool:
    """True when the regulator has dynamics (a lag or a slew limit): P' is then part of the
    state of ``plant_rhs``."""
    return p.regulator.lag > 0.0 or p.regulator.slew > 0.0


def plant_rhs(y: np.ndarray, u: np.ndarray, p: Params) -> np.ndarray:
    """dy/dt of the plant, Eq. (15), with the regulator of ``p.regulator`` and slider friction.

    ``u = (P'_e cmd, P'_f cmd, f_ext)`` [Pa, Pa, N], the commands already delayed by the dead
    time. With a regulator that has dynamics (``has_pressure_state``) the state is
    ``(X, V, P'_e, P'_f)`` and dP'/dt = ``regulator_rate``; otherwise it is ``(X, V)`` and the
    commanded pressures act at once. One state ``(n,)`` or a batch ``(N, n)``.
    """
    dyn = has_pressure_state(p)
    if dyn:
        pe, pf = y[..., 2], y[..., 3]
    else:
        pe, pf = u[..., 0], u[..., 1]
    X, V = y[..., 0], y[..., 1]
    if y.ndim == 1:
        X, V, pe, pf = float(X), float(V), float(pe), float(pf)
    F = ground_force(X, V, pe, pf, p) + slider_friction(V, p)
    acc = (F + u[..., 2]) / p.leg.m - p.leg.g
    if dyn:
        parts = (V, acc, regulator_rate(pe, u[..., 0], p), regulator_rate(pf, u[..., 1], p))
    else:
        parts = (V, acc)
    if y.ndim == 1:
        return np.array(parts, dtype=float)
    return np.stack(np.broadcast_arrays(*parts), axis=-1)
