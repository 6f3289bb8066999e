"""McKibben pneumatic actuator (MPA) force, Eq. (1)-(4) and the Appendix.

Symbols (Appendix): L actuator length, L0 resting length, D0 resting diameter, b braid length,
n number of fibre turns, C1/C2 Mooney-Rivlin constants, V_b interior (bladder) volume,
V_r rubber volume, W strain-energy density, γ viscosity. Every function takes floats or numpy
arrays (broadcast) of L, P' and v.

Documented assumption (docs/design.md#assumptions): the braided-cylinder geometry
``D(L) = sqrt(b² − L²) / (n π)`` and ``V_b(L) = π D² L / 4 = L (b² − L²) / (4 π n²)``.
The stretches used in W are λ1 = L / L0 (axial), λ2 = D(L) / D0 (hoop), λ3 = 1 / (λ1 λ2)
(incompressible rubber); the Appendix's dW/dL is exactly the L-derivative of this W.

Braid friction (not in the paper; off by default, ``MPAParams.friction`` = 0). The strands of the
braid rub on each other and on the bladder, and the friction grows with the pressure that presses
them together: Tondu & Lopez ("Modeling and control of McKibben artificial muscle robot
actuators", IEEE Control Systems Magazine 20(2):15-38, 2000) model it as a dry friction force
proportional to the pressure force, opposing the contraction velocity. Here

    f_fr = −μ_b f_P tanh(v / v_b),    f_P = −P' dV_b/dL ≥ 0 (the pressure term of Eq. 2)

with the sign function regularised by tanh over the contraction velocity v_b (``friction_v``) so
that the right-hand side stays smooth and fixed-step RK4 stays fourth order. It only dissipates
(f_fr v ≤ 0) and, for |v| ≫ v_b, gives the rate-independent loop of width 2 μ_b f_P between
contraction and extension that McKibben muscles show in slow pressure or length sweeps. Below
v_b it acts as a viscous term, so a sweep slower than that shows a narrower loop.
"""

from __future__ import annotations

import math

from mpa_gym.model.params import MPAParams
from mpa_gym.model.xp import Array, sqrt, tanh

PI = math.pi


def braid_diameter(L: Array, p: MPAParams) -> Array:
    """[m] D(L) = sqrt(b² − L²) / (n π) (docs/design.md#assumptions)."""
    return sqrt(p.b**2 - L**2) / (p.n * PI)


def bladder_volume(L: Array, p: MPAParams) -> Array:
    """[m^3] V_b(L) = L (b² − L²) / (4 π n²) (docs/design.md#assumptions)."""
    return L * (p.b**2 - L**2) / (4.0 * PI * p.n**2)


def dVb_dL(L: Array, p: MPAParams) -> Array:
    """[m^2] dV_b/dL = (b² − 3 L²) / (4 π n²); negative for L > b/√3."""
    return (p.b**2 - 3.0 * L**2) / (4.0 * PI * p.n**2)


def d2Vb_dL2(L: Array, p: MPAParams) -> Array:
    """[m] d²V_b/dL² = −6 L / (4 π n²)."""
    return -6.0 * L / (4.0 * PI * p.n**2)


def strain_energy_density(L: Array, p: MPAParams) -> Array:
    """[Pa] Mooney-Rivlin W = C1 (I1 − 3) + C2 (I2 − 3) with the stretches of the module doc."""
    l1 = L / p.L0
    l2 = braid_diameter(L, p) / p.D0
    l3 = 1.0 / (l1 * l2)
    i1 = l1**2 + l2**2 + l3**2
    i2 = l1**-2 + l2**-2 + l3**-2
    return p.C1 * (i1 - 3.0) + p.C2 * (i2 - 3.0)


def dW_dL(L: Array, p: MPAParams) -> Array:
    """[Pa/m] dW/dL exactly as printed in the Appendix."""
    B = p.b**2
    K = p.D0**2 * p.n**2 * PI**2  # D0² n² π²
    L02 = p.L0**2
    s = B - L**2
    c1 = 2.0 * L / L02 - 2.0 * L / K - 2.0 * L02 * K * (B - 2.0 * L**2) / (L**3 * s**2)
    c2 = -2.0 * L02 / L**3 + 2.0 * K * L / s**2 + (2.0 * L * B - 4.0 * L**3) / (L02 * K)
    return p.C1 * c1 + p.C2 * c2


def d2W_dL2(L: Array, p: MPAParams) -> Array:
    """[Pa/m^2] d²W/dL², the L-derivative of the Appendix's dW/dL (needed by Eq. 23)."""
    B = p.b**2
    K = p.D0**2 * p.n**2 * PI**2
    L02 = p.L0**2
    s = B - L**2
    c1 = (
        2.0 / L02
        - 2.0 / K
        - 2.0 * L02 * K * (-3.0 * B**2 + 9.0 * B * L**2 - 10.0 * L**4) / (L**4 * s**3)
    )
    c2 = 6.0 * L02 / L**4 + 2.0 * K * (B + 3.0 * L**2) / s**3 + (2.0 * B - 12.0 * L**2) / (L02 * K)
    return p.C1 * c1 + p.C2 * c2


def force(P: Array, L: Array, v: Array, p: MPAParams) -> Array:
    """[N] MPA tension f(P', L, v) = −P' dV_b/dL + V_r dW/dL − γ v, Eq. (2) with Eq. (4),
    minus the braid friction μ_b f_P tanh(v / v_b) of the module docstring when μ_b > 0.

    Parameters
    ----------
    P : gauge pressure P' [Pa].
    L : actuator length [m].
    v : contractile velocity [m/s], positive when the MPA shortens.
    """
    f = -P * dVb_dL(L, p) + p.Vr * dW_dL(L, p) - p.gamma * v
    if p.friction:
        f = f - braid_friction(P, L, v, p)
    return f


def braid_friction(P: Array, L: Array, v: Array, p: MPAParams) -> Array:
    """[N] μ_b f_P tanh(v / v_b), f_P = −P' dV_b/dL: the friction that ``force`` subtracts."""
    return p.friction * (-P * dVb_dL(L, p)) * tanh(v / p.friction_v)


def dforce_dL(P: Array, L: Array, p: MPAParams, v: Array = 0.0) -> Array:
    """[N/m] ∂f/∂L at fixed P' and v: −P' d²V_b/dL² (1 − μ_b tanh(v/v_b)) + V_r d²W/dL²."""
    scale = 1.0 - p.friction * tanh(v / p.friction_v) if p.friction else 1.0
    return -P * d2Vb_dL2(L, p) * scale + p.Vr * d2W_dL2(L, p)


def dforce_dv(P: Array, L: Array, v: Array, p: MPAParams) -> Array:
    """[N s/m] ∂f/∂v at fixed P' and L: −γ − μ_b f_P (1 − tanh²(v/v_b)) / v_b."""
    if not p.friction:
        return -p.gamma + 0.0 * v
    th = tanh(v / p.friction_v)
    return -p.gamma - p.friction * (-P * dVb_dL(L, p)) * (1.0 - th * th) / p.friction_v
