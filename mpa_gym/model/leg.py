"""Knee geometry and force transmission of the leg, Eq. (8)-(14).

X is the hip height [m], V = dX/dt. β(X) is the knee angle (Eq. 9); the extensor wraps the knee
pulley of radius r (Eq. 11); the flexor spans the chord l_Mf between its attachments (Eq. 10, 12).
G_e = −dL_e/dX and G_f = dL_f/dX (Eq. 8) map actuator tensions to the vertical ground force.
Every function takes a float or a numpy array (broadcast) of X.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

from mpa_gym.model.xp import Array, acos, sqrt

if TYPE_CHECKING:  # annotations only: params imports this module (β0 = β(x_rest))
    from mpa_gym.model.params import LegParams, MPAParams


def _cos_beta(X: Array, leg: LegParams) -> Array:
    return (leg.Lo**2 + leg.Lu**2 - X * X) / (2.0 * leg.Lo * leg.Lu)


def knee_angle(X: Array, leg: LegParams) -> Array:
    """[rad] β(X) = arccos((L_o² + L_u² − X²) / (2 L_o L_u)), Eq. (9)."""
    return acos(_cos_beta(X, leg))


def flexor_path(X: Array, leg: LegParams) -> Array:
    """[m] l_Mf(X) = sqrt(L1² + L2² − 2 L1 L2 cos β(X)), Eq. (10) (flexor MPA + wire)."""
    return sqrt(leg.L1**2 + leg.L2**2 - 2.0 * leg.L1 * leg.L2 * _cos_beta(X, leg))


class Kinematics(NamedTuple):
    """Geometry of the leg at hip height X (each a float or an array shaped like X)."""

    beta: Array  # [rad] β, Eq. (9)
    l_mf: Array  # [m] l_Mf, Eq. (10)
    Le: Array  # [m] L_e, Eq. (11)
    Lf: Array  # [m] L_f, Eq. (12)
    Ge: Array  # [-] G_e, Eq. (8)
    Gf: Array  # [-] G_f, Eq. (8)
    dGe: Array  # [1/m] dG_e/dX
    dGf: Array  # [1/m] dG_f/dX


def kinematics(X: Array, leg: LegParams, mpa: MPAParams) -> Kinematics:
    """β, l_Mf, L_e, L_f, G_e, G_f and the X-derivatives of G_e, G_f at hip height X.

    Eq. (8)-(12) with L_e0 = L_f0 = L0 and β0 = β(x_rest), l_Mf0 = l_Mf(x_rest) (assumption).
    Outside the reachable heights (|L_o − L_u|, L_o + L_u) the result is NaN.
    """
    LoLu = leg.Lo * leg.Lu
    cos_b = _cos_beta(X, leg)
    beta = acos(cos_b)
    sin_b = sqrt(1.0 - cos_b * cos_b)
    l_mf = sqrt(leg.L1**2 + leg.L2**2 - 2.0 * leg.L1 * leg.L2 * cos_b)
    Le = mpa.L0 - leg.r * (beta - leg.beta0)
    Lf = mpa.L0 + l_mf - leg.l_mf0
    dbeta = X / (LoLu * sin_b)  # dβ/dX
    Ge = leg.r * dbeta
    Gf = leg.L1 * leg.L2 * X / (LoLu * l_mf)
    # d/dX of r X/(LoLu sinβ) and of L1 L2 X/(LoLu l_Mf), using dl_Mf/dX = G_f.
    dGe = Ge / X - Ge * cos_b * dbeta / sin_b
    dGf = Gf / X - Gf * Gf / l_mf
    return Kinematics(beta, l_mf, Le, Lf, Ge, Gf, dGe, dGf)


def contractile_velocities(X: Array, V: Array, leg: LegParams, mpa: MPAParams
                           ) -> tuple[Array, Array]:
    """[m/s] (v_e, v_f) = (G_e V, −G_f V), Eq. (13), (14); positive when the MPA shortens."""
    kin = kinematics(X, leg, mpa)
    return kin.Ge * V, -kin.Gf * V
