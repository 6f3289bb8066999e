"""Stability of the periodic motion: a_1, a_2 (Eq. 17-20), Theorem 1 and Floquet multipliers.

Linearising Eq. (15) about the reference (X̂, V̂) driven by the designed feedforward gives
d/dt (X̃, Ṽ) = A(t) (X̃, Ṽ) with A = [[0, 1], [a_2, a_1]] (Eq. 17), a_1 = (1/m) ∂F/∂V and
a_2 = (1/m) ∂F/∂X (Eq. 18). The monodromy matrix Φ(T) of this T-periodic system has the Floquet
multipliers as eigenvalues; by Liouville's formula det Φ(T) = exp(∫_0^T a_1 dt), which is the
quantity Theorem 1 (Eq. 19) bounds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.integrate import quad, solve_ivp

from mpa_gym.design.feedforward import FeedforwardDesign
from mpa_gym.model.dynamics import force_terms
from mpa_gym.model.leg import kinematics
from mpa_gym.model.params import Params


def a1_eq20(x: ArrayLike, p: Params) -> np.ndarray:
    """[1/s] a_1 = −(G_e² γ_e + G_f² γ_f) / m, Eq. (20) (γ_e = γ_f = γ)."""
    kin = kinematics(x, p.leg, p.mpa)
    return -(kin.Ge**2 + kin.Gf**2) * p.mpa.gamma / p.leg.m


def linearisation(design: FeedforwardDesign, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(a_1, a_2) of Eq. (18) along the design's reference at times t [1/s, 1/s^2]."""
    t = np.asarray(t, dtype=float)
    r, p = design.reference, design.params
    pe, pf = np.moveaxis(design.pressures(t), -1, 0)
    ft = force_terms(r.position(t), r.velocity(t), pe, pf, p)
    return ft.dF_dV / p.leg.m, ft.dF_dX / p.leg.m


def theorem1_integral(design: FeedforwardDesign) -> float:
    """∫_0^T a_1(t) dt of Theorem 1 (Eq. 19); negative means the criterion holds."""
    r, p = design.reference, design.params
    val, _ = quad(lambda t: float(a1_eq20(r.position(t), p)), 0.0, r.period,
                  epsabs=1e-13, epsrel=1e-12, limit=200)
    return float(val)


def monodromy_matrix(design: FeedforwardDesign, rtol: float = 1e-11, atol: float = 1e-13
                     ) -> np.ndarray:
    """Φ(T) of Eq. (17): the state-transition matrix over one period, from Φ(0) = I."""

    def rhs(t: float, phi: np.ndarray) -> np.ndarray:
        a1, a2 = linearisation(design, t)
        m = phi.reshape(2, 2)
        A = np.array([[0.0, 1.0], [float(a2), float(a1)]])
        return (A @ m).ravel()

    sol = solve_ivp(rhs, (0.0, design.period), np.eye(2).ravel(), method="DOP853",
                    rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(f"monodromy integration failed: {sol.message}")
    return sol.y[:, -1].reshape(2, 2)


@dataclass(frozen=True)
class StabilityReport:
    int_a1: float  # [-] ∫_0^T a_1 dt (Theorem 1)
    multipliers: np.ndarray  # complex Floquet multipliers (eigenvalues of Φ(T))
    monodromy: np.ndarray  # Φ(T)

    @property
    def theorem1_holds(self) -> bool:
        """Eq. (19): ∫ a_1 dt < 0."""
        return self.int_a1 < 0.0

    @property
    def stable(self) -> bool:
        """Asymptotically stable periodic motion: all Floquet multipliers inside the unit circle."""
        return bool(np.all(np.abs(self.multipliers) < 1.0))

    @property
    def spectral_radius(self) -> float:
        return float(np.max(np.abs(self.multipliers)))


def analyze(design: FeedforwardDesign) -> StabilityReport:
    """Theorem 1's integral and the Floquet multipliers of the design's periodic motion."""
    phi = monodromy_matrix(design)
    return StabilityReport(theorem1_integral(design), np.linalg.eigvals(phi), phi)


def linear_steady_state_error(design: FeedforwardDesign, plant: Params, t: ArrayLike,
                              rtol: float = 1e-11, atol: float = 1e-14) -> np.ndarray:
    """[m] Periodic tracking error X − X̂ predicted by linearisation when the plant differs.

    The feedforward is designed on ``design.params``; on a plant ``plant`` (other m, γ, C1, …)
    the reference leaves a residual acceleration δa(t) = F_p(X̂, V̂, P')/m_p − g − dV̂/dt. The
    error z = (X̃, Ṽ) then obeys z' = A_p(t) z + (0, δa(t)) to first order, with A_p the plant's
    Eq. (17) matrix along the reference. Its T-periodic solution is z(0) = (I − Φ_p)⁻¹ z_p(T),
    z_p the response from rest; it exists because the multipliers lie inside the unit circle.
    Returns X̃ at the times ``t`` (taken modulo T).
    """
    r = design.reference
    m = plant.leg.m

    def rhs(tt: float, z: np.ndarray) -> np.ndarray:
        x, v, a = r.position(tt), r.velocity(tt), r.acceleration(tt)
        pe, pf = design.pressures(tt)
        ft = force_terms(float(x), float(v), float(pe), float(pf), plant)
        da = ft.F / m - plant.leg.g - float(a)
        a1, a2 = ft.dF_dV / m, ft.dF_dX / m
        # columns: particular response (z), then Φ (2x2) for the homogeneous part
        zz = z.reshape(3, 2)
        out = np.empty_like(zz)
        for i in range(3):
            out[i] = (zz[i, 1], a2 * zz[i, 0] + a1 * zz[i, 1] + (da if i == 0 else 0.0))
        return out.ravel()

    T = r.period
    z0 = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 1.0])
    sol = solve_ivp(rhs, (0.0, T), z0, method="DOP853", rtol=rtol, atol=atol)
    end = sol.y[:, -1].reshape(3, 2)
    phi = end[1:].T  # columns are the responses to unit X̃ and Ṽ
    start = np.linalg.solve(np.eye(2) - phi, end[0])
    tq, inverse = np.unique(np.mod(np.asarray(t, dtype=float), T), return_inverse=True)
    per = solve_ivp(rhs, (0.0, T), np.concatenate([start, [1.0, 0.0, 0.0, 1.0]]),
                    method="DOP853", rtol=rtol, atol=atol, t_eval=tq)
    return per.y[0][inverse].reshape(np.shape(t))
