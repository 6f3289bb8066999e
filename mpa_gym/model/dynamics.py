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
from mpa_gym.model.xp import Array


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

    With dL_e/dX = −G_e, dL_f/dX = G_f, v_e = G_e V, v_f = −G_f V and ∂f/∂v = −γ:

    ∂F/∂X = G_e' f_e − G_e² ∂f_e/∂L − γ G_e G_e' V − G_f' f_f − G_f² ∂f_f/∂L − γ G_f G_f' V
    ∂F/∂V = −γ (G_e² + G_f²)
    """
    kin = kinematics(X, p.leg, p.mpa)
    g = p.mpa.gamma
    fe = mpa.force(Pe, kin.Le, kin.Ge * V, p.mpa)
    ff = mpa.force(Pf, kin.Lf, -kin.Gf * V, p.mpa)
    F = kin.Ge * fe - kin.Gf * ff
    dF_dX = (
        kin.dGe * fe
        - kin.Ge**2 * mpa.dforce_dL(Pe, kin.Le, p.mpa)
        - g * kin.Ge * kin.dGe * V
        - kin.dGf * ff
        - kin.Gf**2 * mpa.dforce_dL(Pf, kin.Lf, p.mpa)
        - g * kin.Gf * kin.dGf * V
    )
    dF_dV = -g * (kin.Ge**2 + kin.Gf**2) + 0.0 * V
    return ForceTerms(F, fe, ff, dF_dX, dF_dV)


def leg_dynamics(
    t: float,
    y: ArrayLike,
    u: ArrayLike,
    p: Params,
    f_ext: ArrayLike = 0.0,
) -> np.ndarray:
    """dy/dt = [V, (F + f_ext)/m − g], Eq. (15) with an external force on the hip.

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
        F = ground_force(X, V, float(u[0]), float(u[1]), p)
        return np.array((V, (F + float(f_ext)) / p.leg.m - p.leg.g))
    X, V = y[..., 0], y[..., 1]
    F = ground_force(X, V, u[..., 0], u[..., 1], p)
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


def plant_rhs(y: np.ndarray, u: np.ndarray, p: Params, pressure_lag_s: float = 0.0) -> np.ndarray:
    """dy/dt of the plant, Eq. (15), with an optional first-order pressure regulator.

    ``u = (P'_e cmd, P'_f cmd, f_ext)`` [Pa, Pa, N]. With ``pressure_lag_s`` = τ > 0 the state is
    ``(X, V, P'_e, P'_f)`` and dP'/dt = (P'_cmd − P')/τ; with τ = 0 it is ``(X, V)`` and the
    commanded pressures act at once. One state ``(n,)`` or a batch ``(N, n)``.
    """
    if pressure_lag_s > 0.0:
        pe, pf = y[..., 2], y[..., 3]
    else:
        pe, pf = u[..., 0], u[..., 1]
    X, V = y[..., 0], y[..., 1]
    if y.ndim == 1:
        X, V, pe, pf = float(X), float(V), float(pe), float(pf)
    acc = (ground_force(X, V, pe, pf, p) + u[..., 2]) / p.leg.m - p.leg.g
    if pressure_lag_s > 0.0:
        parts = (V, acc, (u[..., 0] - pe) / pressure_lag_s, (u[..., 1] - pf) / pressure_lag_s)
    else:
        parts = (V, acc)
    if y.ndim == 1:
        return np.array(parts, dtype=float)
    return np.stack(np.broadcast_arrays(*parts), axis=-1)
