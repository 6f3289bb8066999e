"""Compiled task logic shared by the sim kernels and the hardware env: action to command,
the safety layer (slew limit then clip), the reward terms, the composition of a step's result
(:func:`finish_step`: reward, its terms, termination) and the observation (its layout is
``task.contract``'s). The task's scalar settings travel as one vector (``SETTINGS``, packed
from a ``TaskConfig`` by :func:`task_settings`), the form the compiled code reads."""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from mpa_gym.model.jit import JIT
from mpa_gym.model.params import BAR
from mpa_gym.task.contract import (
    O_K,
    O_R,
    O_RK,
    O_RU,
    O_RX,
    O_TERM,
    SAFETY_CLIPPED,
    SAFETY_SLEW,
    STATE,
    T_KREF,
    T_XREF,
)

N_STATE = len(STATE)

# The scalar settings vector the compiled step reads, packed by name (``pack_settings``).
SETTINGS = ("residual", "residual_scale_Pa", "p_max_Pa", "max_delta_Pa", "quantum_Pa", "dt_s",
            "x_min_m", "x_max_m", "sigma_x_m", "sigma_k", "w_k", "w_u", "encoder_m", "substeps")
(S_RESIDUAL, S_SCALE, S_PMAX, S_DMAX, S_QUANTUM, S_DT, S_XLO, S_XHI, S_SIGX, S_SIGK, S_WK, S_WU,
 S_ENC, S_SUB) = (SETTINGS.index(n) for n in SETTINGS)


def pack_settings(**values: float) -> np.ndarray:
    """The settings vector from its named entries (all of ``SETTINGS``, no others)."""
    if set(values) != set(SETTINGS):
        raise ValueError(f"settings: got {sorted(values)}; expected {sorted(SETTINGS)}")
    return np.array([float(values[k]) for k in SETTINGS], dtype=np.float64)


def task_settings(cfg: Any, residual: bool, quantum_Pa: float = 0.0,
                  encoder_m: float = 0.0) -> np.ndarray:
    """The settings vector of a ``TaskConfig`` for one env id (``residual``); the regulator's
    quantum and the encoder's resolution are the simulated rig's (0 on the real one, whose
    regulator and encoder apply their own)."""
    return pack_settings(
        residual=1.0 if residual else 0.0, residual_scale_Pa=cfg.residual_scale_bar * BAR,
        p_max_Pa=cfg.p_max_bar * BAR, max_delta_Pa=cfg.max_delta_Pa, quantum_Pa=quantum_Pa,
        dt_s=cfg.dt_s, x_min_m=cfg.x_min_m, x_max_m=cfg.x_max_m, sigma_x_m=cfg.sigma_x_m,
        sigma_k=cfg.sigma_k, w_k=cfg.stiffness_weight(residual), w_u=cfg.w_effort,
        encoder_m=encoder_m, substeps=cfg.substeps)


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


@numba.njit(**JIT)
def finish_step(out, x, k, ref, a_e, a_f, s, stopped):
    """Compose the result of a control period into the output row ``out`` (``task.contract``
    OUT columns; the command and safety flags are already in it) and return whether the
    episode terminates: the one composition of the sim's compiled step and the rig's step.

    ``x`` is the hip height the step ended at, ``k`` the joint stiffness there (the plant's true
    one in the sim, the nominal model's at the measured state on the rig), ``ref`` the plan's
    row for that step, ``a_e``, ``a_f`` the clipped action, ``s`` the ``SETTINGS`` vector and
    ``stopped`` whether something other than the position bounds ends the episode (the sim's
    model domain; the rig's stale link, device fault, over-pressure, slow policy step).

    The episode terminates when x leaves [x_min, x_max] or ``stopped``. A terminating step
    earns 0 and its reward terms are 0 too, so that on every step
    reward = reward_position + reward_stiffness + reward_effort (the reward terms of ``info``
    are the parts of the reward returned, as in Gymnasium's MuJoCo envs).
    """
    out[O_K] = k
    if stopped or not (s[S_XLO] <= x <= s[S_XHI]):
        out[O_TERM] = 1.0
        out[O_R] = 0.0
        out[O_RX] = 0.0
        out[O_RK] = 0.0
        out[O_RU] = 0.0
        return True
    r, rx, rk, ru = reward_terms(x - ref[T_XREF], k, ref[T_KREF], a_e, a_f, s[S_SIGX],
                                 s[S_SIGK], s[S_WK], s[S_WU])
    out[O_TERM] = 0.0
    out[O_R] = r
    out[O_RX] = rx
    out[O_RK] = rk
    out[O_RU] = ru
    return False
