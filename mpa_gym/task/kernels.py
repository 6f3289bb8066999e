"""Compiled task logic shared by the sim kernels and the hardware env: action to command,
the safety layer (slew limit then clip), the reward terms and the observation (its layout is
``task.contract``'s). Scalars in, scalars out, but for the observation row."""

from __future__ import annotations

import math

import numba

from mpa_gym.task.contract import SAFETY_CLIPPED, SAFETY_SLEW, STATE

N_STATE = len(STATE)
JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@numba.njit(**JIT)
def command_from_action(a, ff, residual, scale, p_max):
    """[Pa] pressure command of one MPA: ff + a·scale (residual) or (a + 1)/2 · p_max (direct)."""
    if residual:
        return ff + a * scale
    return 0.5 * (a + 1.0) * p_max


@numba.njit(**JIT)
def safe_command(cmd, prev, p_max, max_delta):
    """Slew-limit ``cmd`` to prev ± max_delta, then clip to [0, p_max]. Returns (cmd, flags)."""
    flags = 0
    if cmd > prev + max_delta:
        cmd = prev + max_delta
        flags |= SAFETY_SLEW
    elif cmd < prev - max_delta:
        cmd = prev - max_delta
        flags |= SAFETY_SLEW
    if cmd > p_max:
        cmd = p_max
        flags |= SAFETY_CLIPPED
    elif cmd < 0.0:
        cmd = 0.0
        flags |= SAFETY_CLIPPED
    return cmd, flags


@numba.njit(**JIT)
def reward_terms(err_x, k, k_ref, a_e, a_f, sigma_x, sigma_k, w_k, w_u):
    """(reward, position term, stiffness term, effort term).

    r = (1 − w_k) / (1 + (e_x/σ_x)²) + w_k / (1 + ((k − k̂)/(k̂ σ_k))²) − w_u (a_e² + a_f²)

    Cauchy kernels: 1 on target, 1/2 at one σ, and heavy-tailed, so an error of several σ
    (a 20 mm sag under an unknown load) still has a gradient toward the target.
    """
    ex = err_x / sigma_x
    rx = (1.0 - w_k) / (1.0 + ex * ex)
    rel = (k - k_ref) / (abs(k_ref) * sigma_k) if k_ref != 0.0 else 0.0
    rk = w_k / (1.0 + rel * rel) if math.isfinite(k) else 0.0
    ru = -w_u * (a_e * a_e + a_f * a_f)
    return rx + rk + ru, rx, rk, ru


@numba.njit(**JIT)
def observe(obs, x, v, pe, pf, ref, noise, spec):
    """Fill one observation row from the measured state (x, v, pe, pf: the STATE signals, SI),
    the plan's row ``ref`` (the PLAN signals) and the sensor noise of each state signal (SI),
    following ``spec`` (``task.contract.obs_spec``): column c = (signal + its noise) / divisor."""
    for c in range(spec.shape[0]):
        s = int(spec[c, 0])
        if s < N_STATE:
            val = ((x, v, pe, pf)[s] + noise[s]) / spec[c, 1]
        else:
            val = ref[s - N_STATE] / spec[c, 1]
        obs[c] = val
