"""Compiled (numba) plant step for the environments: the physics of ``mpa``, ``leg`` and
``dynamics`` transcribed into scalar kernels over a packed constants vector.

The readable numpy model is the reference; ``tests/test_fast.py`` holds these kernels to it
(force, stiffness and RK4 step to 1e-12 relative). Environments step one leg or thousands
through the same kernels: ``plant_step`` for one, loops over rows for a batch.

Constants vector (``pack``), SI units: see ``FIELDS``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from mpa_gym.model.jit import JIT
from mpa_gym.model.params import Params

FIELDS = ("C1", "C2", "D0", "b", "n", "gamma", "L0", "Vr", "Lo", "Lu", "L1", "L2", "r", "m", "g",
          "beta0", "l_mf0",
          # derived once here so the kernels do not recompute them every evaluation
          "b2", "K", "L02", "4pi_n2", "LoLu", "Lo2_Lu2", "L1sq_L2sq", "L1L2",
          # reciprocals: the kernels multiply instead of divide
          "1/L02", "1/K", "1/(L02 K)", "1/4pi_n2", "1/(2 LoLu)", "1/LoLu", "1/m",
          # effects beyond the paper (0: off): braid friction, slider friction, regulator
          "mu_b", "1/v_b", "F_c", "c_s", "1/v_s", "lag", "slew")
NC = len(FIELDS)
(C1, C2, D0, B_, N_, GAMMA, L0, VR, LO, LU, L1, L2, R, M, G, BETA0, LMF0,
 B2, KK, L02_, FOURPIN2, LOLU, LO2LU2, L1SQL2SQ, L1L2,
 INV_L02, INV_K, INV_L02K, INV_4PIN2, INV_2LOLU, INV_LOLU, INV_M,
 MU_B, INV_VB, F_C, C_S, INV_VS, LAG, SLEW) = range(NC)


def pack(p: Params) -> np.ndarray:
    """The constants vector of a parameter set (one row of a batch)."""
    mp, lg, reg = p.mpa, p.leg, p.regulator
    vals = {"C1": mp.C1, "C2": mp.C2, "D0": mp.D0, "b": mp.b, "n": mp.n, "gamma": mp.gamma,
            "L0": mp.L0, "Vr": mp.Vr, "Lo": lg.Lo, "Lu": lg.Lu, "L1": lg.L1, "L2": lg.L2,
            "r": lg.r, "m": lg.m, "g": lg.g, "beta0": lg.beta0, "l_mf0": lg.l_mf0,
            "b2": mp.b**2, "K": mp.D0**2 * mp.n**2 * math.pi**2, "L02": mp.L0**2,
            "4pi_n2": 4.0 * math.pi * mp.n**2, "LoLu": lg.Lo * lg.Lu,
            "Lo2_Lu2": lg.Lo**2 + lg.Lu**2, "L1sq_L2sq": lg.L1**2 + lg.L2**2,
            "L1L2": lg.L1 * lg.L2}
    for name in ("L02", "K", "4pi_n2", "LoLu"):
        vals[f"1/{name}"] = 1.0 / vals[name]
    vals["1/(L02 K)"] = 1.0 / (vals["L02"] * vals["K"])
    vals["1/(2 LoLu)"] = 0.5 / vals["LoLu"]
    vals["1/m"] = 1.0 / lg.m
    vals.update({"mu_b": mp.friction, "1/v_b": 1.0 / mp.friction_v, "F_c": lg.friction_coulomb,
                 "c_s": lg.friction_viscous, "1/v_s": 1.0 / lg.friction_v, "lag": reg.lag,
                 "slew": reg.slew})
    return np.array([vals[f] for f in FIELDS], dtype=np.float64)


@numba.njit(**JIT)
def _mpa_static(P, L, c):
    """f at v = 0 of Eq. (2): −P' dV_b/dL + V_r dW/dL with the Appendix's dW/dL."""
    b2, K, L02 = c[B2], c[KK], c[L02_]
    L2_ = L * L
    L3 = L2_ * L
    inv_L3 = 1.0 / L3
    inv_s = 1.0 / (b2 - L2_)
    inv_s2 = inv_s * inv_s
    dVb = (b2 - 3.0 * L2_) * c[INV_4PIN2]
    dW = (c[C1] * (2.0 * L * c[INV_L02] - 2.0 * L * c[INV_K]
                   - 2.0 * L02 * K * (b2 - 2.0 * L2_) * inv_L3 * inv_s2)
          + c[C2] * (-2.0 * L02 * inv_L3 + 2.0 * K * L * inv_s2
                     + (2.0 * L * b2 - 4.0 * L3) * c[INV_L02K]))
    return -P * dVb + c[VR] * dW


@numba.njit(**JIT)
def _mpa_slope(P, L, c):
    """∂f/∂L of Eq. (2): −P' d²V_b/dL² + V_r d²W/dL²."""
    b2, K, L02 = c[B2], c[KK], c[L02_]
    L2_ = L * L
    s = b2 - L2_
    d2Vb = -6.0 * L / c[FOURPIN2]
    d2W = (c[C1] * (2.0 / L02 - 2.0 / K - 2.0 * L02 * K
                    * (-3.0 * b2 * b2 + 9.0 * b2 * L2_ - 10.0 * L2_ * L2_) / (L2_ * L2_ * s**3))
           + c[C2] * (6.0 * L02 / (L2_ * L2_) + 2.0 * K * (b2 + 3.0 * L2_) / s**3
                      + (2.0 * b2 - 12.0 * L2_) / (L02 * K)))
    return -P * d2Vb + c[VR] * d2W


@numba.njit(**JIT)
def _geometry(X, c):
    """(cos β, sin β, l_Mf, L_e, L_f, G_e, G_f) of Eq. (8)-(12); NaN outside the domain."""
    cos_b = (c[LO2LU2] - X * X) * c[INV_2LOLU]
    if not (-1.0 < cos_b < 1.0):
        nan = math.nan
        return nan, nan, nan, nan, nan, nan, nan
    sin_b = math.sqrt(1.0 - cos_b * cos_b)
    l_mf = math.sqrt(c[L1SQL2SQ] - 2.0 * c[L1L2] * cos_b)
    Le = c[L0] - c[R] * (math.acos(cos_b) - c[BETA0])
    Lf = c[L0] + l_mf - c[LMF0]
    x_lolu = X * c[INV_LOLU]
    Ge = c[R] * x_lolu / sin_b
    Gf = c[L1L2] * x_lolu / l_mf
    return cos_b, sin_b, l_mf, Le, Lf, Ge, Gf


@numba.njit(**JIT)
def _tension(P, L, v, c):
    """(f, ∂f/∂v, braid-friction factor tanh(v/v_b)) of one MPA: Eq. (2), (4) and the braid
    friction of ``mpa.force`` (μ_b = 0: the paper's f = static − γ v)."""
    f = _mpa_static(P, L, c) - c[GAMMA] * v
    dfdv = -c[GAMMA]
    th = 0.0
    mu = c[MU_B]
    if mu > 0.0:
        fP = -P * (c[B2] - 3.0 * L * L) * c[INV_4PIN2]  # −P' dV_b/dL
        th = math.tanh(v * c[INV_VB])
        f -= mu * fP * th
        dfdv -= mu * fP * (1.0 - th * th) * c[INV_VB]
    return f, dfdv, th


@numba.njit(**JIT)
def ground_force(X, V, Pe, Pf, c):
    """F of Eq. (5) at one state; NaN outside the model's domain."""
    _, _, _, Le, Lf, Ge, Gf = _geometry(X, c)
    fe, _, _ = _tension(Pe, Le, Ge * V, c)
    ff, _, _ = _tension(Pf, Lf, -Gf * V, c)
    return Ge * fe - Gf * ff


@numba.njit(**JIT)
def force_and_stiffness(X, V, Pe, Pf, c):
    """(F, k = −∂F/∂X) of Eq. (5) and (23) at one state; NaN outside the model's domain.

    ∂F/∂X in the general form of ``dynamics.force_terms`` (∂f/∂v = −γ without braid friction).
    """
    cos_b, sin_b, l_mf, Le, Lf, Ge, Gf = _geometry(X, c)
    dbeta = X / (c[LOLU] * sin_b)
    dGe = Ge / X - Ge * cos_b * dbeta / sin_b
    dGf = Gf / X - Gf * Gf / l_mf
    fe, dfe_dv, the = _tension(Pe, Le, Ge * V, c)
    ff, dff_dv, thf = _tension(Pf, Lf, -Gf * V, c)
    F = Ge * fe - Gf * ff
    # ∂f/∂L at fixed v: the pressure term of the slope scaled by (1 − μ_b tanh(v/v_b))
    mu = c[MU_B]
    d2Vb_e = -6.0 * Le * c[INV_4PIN2]
    d2Vb_f = -6.0 * Lf * c[INV_4PIN2]
    sl_e = _mpa_slope(Pe, Le, c) + mu * the * Pe * d2Vb_e
    sl_f = _mpa_slope(Pf, Lf, c) + mu * thf * Pf * d2Vb_f
    dFdX = (dGe * fe - Ge * Ge * sl_e + Ge * dGe * V * dfe_dv
            - dGf * ff - Gf * Gf * sl_f + Gf * dGf * V * dff_dv)
    return F, -dFdX


@numba.njit(**JIT)
def _accel(X, V, Pe, Pf, f_ext, c):
    """dV/dt of Eq. (15) with the slider friction −F_c tanh(V/v_s) − c_s V."""
    fs = -c[F_C] * math.tanh(V * c[INV_VS]) - c[C_S] * V if c[F_C] > 0.0 or c[C_S] > 0.0 else 0.0
    return (ground_force(X, V, Pe, Pf, c) + fs + f_ext) * c[INV_M] - c[G]


@numba.njit(**JIT)
def _rk4(X, V, pe0, pf0, pem, pfm, pe1, pf1, f_ext, h, c):
    k1x, k1v = V, _accel(X, V, pe0, pf0, f_ext, c)
    k2x, k2v = V + 0.5 * h * k1v, _accel(X + 0.5 * h * k1x, V + 0.5 * h * k1v, pem, pfm, f_ext, c)
    k3x, k3v = V + 0.5 * h * k2v, _accel(X + 0.5 * h * k2x, V + 0.5 * h * k2v, pem, pfm, f_ext, c)
    k4x, k4v = V + h * k3v, _accel(X + h * k3x, V + h * k3v, pe1, pf1, f_ext, c)
    return (X + h / 6.0 * (k1x + 2.0 * k2x + 2.0 * k3x + k4x),
            V + h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v))


@numba.njit(**JIT)
def regulator_pressure(P0, cmd, s, tau, r):
    """P'(s) under a held command: ``dynamics.regulator_pressure`` for one MPA."""
    e = cmd - P0
    if tau == 0.0:
        if r == 0.0:
            return cmd
        return P0 + min(max(e, -r * s), r * s)
    if r == 0.0:
        return cmd - e * math.exp(-s / tau)
    s1 = (abs(e) - r * tau) / r
    sg = 1.0 if e > 0.0 else -1.0
    if s1 <= 0.0:
        return cmd - e * math.exp(-s / tau)
    if s <= s1:
        return P0 + sg * r * s
    return cmd - sg * r * tau * math.exp(-(s - s1) / tau)


@numba.njit(**JIT)
def _regime_end(P0, cmd, tau, r, eps):
    """[s] when the held-command solution changes form (the end of a slew ramp), or +inf
    (also for an end closer than ``eps``): the RK4 steps stop there so they never straddle
    the kink."""
    if r == 0.0:
        return math.inf
    s1 = (abs(cmd - P0) - r * tau) / r
    return s1 if s1 > eps else math.inf


@numba.njit(**JIT)
def plant_step(X, V, Pe, Pf, ce0, cf0, ce1, cf1, t_switch, f_ext, dt, c, substeps=1):
    """One control period ``dt`` of Eq. (15) in ``substeps`` RK4 steps, the regulator of
    ``RegulatorParams`` solved exactly.

    The command reaching the regulator is (ce0, cf0) before ``t_switch`` and (ce1, cf1) from
    then on, so a dead time that is not a whole number of control periods switches inside the
    period (the caller keeps the command history; ``t_switch`` = 0: the command is (ce1, cf1)
    throughout). The pressures follow the exact held-command solution (``regulator_pressure``,
    lag τ and slew r from the constants) and are evaluated at each RK4 stage time; the RK4
    steps are split where the command switches and where a slew ramp ends, so no step
    straddles a kink of P'(t). ``f_ext`` is the mean external force over the period.
    Returns (X, V, P'_e, P'_f) at t + dt.
    """
    h = dt / substeps
    tau, r = c[LAG], c[SLEW]
    eps = 1e-12 * dt
    t = 0.0
    for k in range(substeps):
        t_end = dt if k == substeps - 1 else (k + 1) * h
        while t < t_end - eps:
            if t < t_switch - eps:
                ce, cf, seg = ce0, cf0, min(t_end, t_switch)
            else:
                ce, cf, seg = ce1, cf1, t_end
            seg = min(seg, t + _regime_end(Pe, ce, tau, r, eps),
                      t + _regime_end(Pf, cf, tau, r, eps))
            hh = seg - t
            pe0 = regulator_pressure(Pe, ce, 0.0, tau, r)
            pf0 = regulator_pressure(Pf, cf, 0.0, tau, r)
            pem = regulator_pressure(Pe, ce, 0.5 * hh, tau, r)
            pfm = regulator_pressure(Pf, cf, 0.5 * hh, tau, r)
            pe1 = regulator_pressure(Pe, ce, hh, tau, r)
            pf1 = regulator_pressure(Pf, cf, hh, tau, r)
            X, V = _rk4(X, V, pe0, pf0, pem, pfm, pe1, pf1, f_ext, hh, c)
            Pe, Pf = pe1, pf1
            t = seg
    return X, V, Pe, Pf
