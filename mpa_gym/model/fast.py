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

from mpa_gym.model.params import Params

FIELDS = ("C1", "C2", "D0", "b", "n", "gamma", "L0", "Vr", "Lo", "Lu", "L1", "L2", "r", "m", "g",
          "beta0", "l_mf0",
          # derived once here so the kernels do not recompute them every evaluation
          "b2", "K", "L02", "4pi_n2", "LoLu", "Lo2_Lu2", "L1sq_L2sq", "L1L2",
          # reciprocals: the kernels multiply instead of divide
          "1/L02", "1/K", "1/(L02 K)", "1/4pi_n2", "1/(2 LoLu)", "1/LoLu", "1/m")
NC = len(FIELDS)
(C1, C2, D0, B_, N_, GAMMA, L0, VR, LO, LU, L1, L2, R, M, G, BETA0, LMF0,
 B2, KK, L02_, FOURPIN2, LOLU, LO2LU2, L1SQL2SQ, L1L2,
 INV_L02, INV_K, INV_L02K, INV_4PIN2, INV_2LOLU, INV_LOLU, INV_M) = range(NC)
JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


def pack(p: Params) -> np.ndarray:
    """The constants vector of a parameter set (one row of a batch)."""
    mp, lg = p.mpa, p.leg
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
def ground_force(X, V, Pe, Pf, c):
    """F of Eq. (5) at one state; NaN outside the model's domain."""
    _, _, _, Le, Lf, Ge, Gf = _geometry(X, c)
    gam = c[GAMMA]
    return Ge * (_mpa_static(Pe, Le, c) - gam * Ge * V) - Gf * (_mpa_static(Pf, Lf, c)
                                                                + gam * Gf * V)


@numba.njit(**JIT)
def force_and_stiffness(X, V, Pe, Pf, c):
    """(F, k = −∂F/∂X) of Eq. (5) and (23) at one state; NaN outside the model's domain."""
    cos_b, sin_b, l_mf, Le, Lf, Ge, Gf = _geometry(X, c)
    dbeta = X / (c[LOLU] * sin_b)
    dGe = Ge / X - Ge * cos_b * dbeta / sin_b
    dGf = Gf / X - Gf * Gf / l_mf
    gam = c[GAMMA]
    fe = _mpa_static(Pe, Le, c) - gam * Ge * V
    ff = _mpa_static(Pf, Lf, c) + gam * Gf * V
    F = Ge * fe - Gf * ff
    dFdX = (dGe * fe - Ge * Ge * _mpa_slope(Pe, Le, c) - gam * Ge * dGe * V
            - dGf * ff - Gf * Gf * _mpa_slope(Pf, Lf, c) - gam * Gf * dGf * V)
    return F, -dFdX


@numba.njit(**JIT)
def _accel(X, V, Pe, Pf, f_ext, c):
    return (ground_force(X, V, Pe, Pf, c) + f_ext) * c[INV_M] - c[G]


@numba.njit(**JIT)
def _rk4(X, V, pe0, pf0, pem, pfm, pe1, pf1, f_ext, h, c):
    k1x, k1v = V, _accel(X, V, pe0, pf0, f_ext, c)
    k2x, k2v = V + 0.5 * h * k1v, _accel(X + 0.5 * h * k1x, V + 0.5 * h * k1v, pem, pfm, f_ext, c)
    k3x, k3v = V + 0.5 * h * k2v, _accel(X + 0.5 * h * k2x, V + 0.5 * h * k2v, pem, pfm, f_ext, c)
    k4x, k4v = V + h * k3v, _accel(X + h * k3x, V + h * k3v, pe1, pf1, f_ext, c)
    return (X + h / 6.0 * (k1x + 2.0 * k2x + 2.0 * k3x + k4x),
            V + h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v))


@numba.njit(**JIT)
def plant_step(X, V, Pe, Pf, cmd_e, cmd_f, f_ext, lag, dt, c, substeps=1):
    """``substeps`` RK4 steps of Eq. (15) over ``dt`` with the pressure command held (ZOH).

    The regulator is first order with time constant ``lag`` (0: ideal, P' = command); its exact
    solution P'(s) = cmd + (P'0 − cmd) e^(−s/lag) gives the pressures at the RK4 stage times.
    ``f_ext`` is the mean external force over the step. Returns (X, V, P'_e, P'_f) at t + dt.
    """
    h = dt / substeps
    for _ in range(substeps):
        if lag > 0.0:
            am = math.exp(-0.5 * h / lag)
            a1 = am * am
            pem, pfm = cmd_e + (Pe - cmd_e) * am, cmd_f + (Pf - cmd_f) * am
            pe1, pf1 = cmd_e + (Pe - cmd_e) * a1, cmd_f + (Pf - cmd_f) * a1
            X, V = _rk4(X, V, Pe, Pf, pem, pfm, pe1, pf1, f_ext, h, c)
            Pe, Pf = pe1, pf1
        else:
            X, V = _rk4(X, V, cmd_e, cmd_f, cmd_e, cmd_f, cmd_e, cmd_f, f_ext, h, c)
            Pe, Pf = cmd_e, cmd_f
    return X, V, Pe, Pf
