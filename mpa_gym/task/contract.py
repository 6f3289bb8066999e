"""The step contract every env shares — ``MPALeg-v0``, ``MPALegResidual-v0``, their vector
versions and the rig (``MPALegHardware-v0``): defined here once, read everywhere else by name.

- **Signals.** What an env knows at the end of a control period: the leg's measured state
  (``STATE``: X, V, P'_e, P'_f, also the columns of the sim engine's state array and the sensor
  noise channels) and the plan's row for the step (``PLAN``: the reference, k̂, the phase, the
  feedforward and the disturbance; the columns of ``TaskPlan.table()``).
- **Observation.** ``OBS_COLUMNS``: name, what it shows, unit, bounds and the signal it is made
  of (``column = signal / divisor``, plus the sensor noise of a measured signal). Every env fills
  its observation through :func:`obs_spec` and the compiled ``task.kernels.observe``, so a column
  added here appears in all of them.
- **Step output.** ``OUT``: what the step kernel computes per leg (the safe command, the true
  stiffness, the reward and its terms, the safety flags, termination).
- **Safety flags.** ``SAFETY_CLIPPED``, ``SAFETY_SLEW``: bits of ``info["safety"]``.
- **info.** :func:`step_info` builds every env's ``info`` from an output row, a state row and a
  plan row (or arrays of them, for a vector env); ``INFO_KEYS`` are the keys every env
  fills on every step (docs/design.md#step-contract).
- **Action.** :func:`action_space` and :func:`check_action` (shape, finiteness, the range, the
  error text).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces

from mpa_gym.model.params import BAR

# ------------------------------------------------------------------------------- signals
# The leg's measured state, SI: the sim engine's state columns and the sensor-noise channels.
STATE = ("x_m", "v_mps", "pe_Pa", "pf_Pa")
ST_X, ST_V, ST_PE, ST_PF = (STATE.index(n) for n in STATE)
# The plan's row for step j (TaskPlan.table()); the feedforward and the disturbance act over
# step j, the rest are the values at t_j.
PLAN = ("x_ref_m", "v_ref_mps", "k_ref_N_per_m", "sin_phase", "cos_phase", "ff_e_Pa", "ff_f_Pa",
        "f_ext_N")
T_XREF, T_VREF, T_KREF, T_SIN, T_COS, T_FFE, T_FFF, T_FEXT = (PLAN.index(n) for n in PLAN)
SIGNALS = (*STATE, *PLAN)  # an observation column shows one of these


def _p_max_plus_1(cfg: Any) -> float:
    """p_max + 1"""
    return cfg.p_max_bar + 1.0


@dataclass(frozen=True)
class ObsColumn:
    """One observation column: ``signal / divisor`` (+ the signal's sensor noise if measured)."""

    name: str
    label: str  # what it shows, for docs and reports
    unit: str
    low: float | Callable[[Any], float]  # a number or a function of the TaskConfig
    high: float | Callable[[Any], float]
    signal: str  # one of SIGNALS
    divisor: float = 1.0
    residual_only: bool = False  # MPALegResidual-v0 only

    def bounds(self, cfg: Any) -> tuple[float, float]:
        return tuple(b(cfg) if callable(b) else float(b) for b in (self.low, self.high))


# Observation layout (float32). Bounds are generous enough for the state one step past a
# termination bound plus sensor noise.
OBS_COLUMNS: tuple[ObsColumn, ...] = (
    ObsColumn("x_m", "hip height X", "m", 0.0, 1.0, "x_m"),
    ObsColumn("v_mps", "hip velocity V", "m/s", -10.0, 10.0, "v_mps"),
    ObsColumn("x_ref_m", "reference X̂", "m", 0.0, 1.0, "x_ref_m"),
    ObsColumn("v_ref_mps", "reference V̂", "m/s", -10.0, 10.0, "v_ref_mps"),
    ObsColumn("sin_phase", "sin(2π t / T) (phase of the reference)", "–", -1.0, 1.0,
              "sin_phase"),
    ObsColumn("cos_phase", "cos(2π t / T)", "–", -1.0, 1.0, "cos_phase"),
    ObsColumn("pe_bar", "measured P'_e", "bar", -1.0, _p_max_plus_1, "pe_Pa", BAR),
    ObsColumn("pf_bar", "measured P'_f", "bar", -1.0, _p_max_plus_1, "pf_Pa", BAR),
    ObsColumn("k_ref_kN_per_m", "stiffness target k̂(t)", "kN/m", -100.0, 100.0,
              "k_ref_N_per_m", 1000.0, residual_only=True),
)


def obs_columns(residual: bool) -> tuple[ObsColumn, ...]:
    """The columns of one env id's observation, in order."""
    return tuple(c for c in OBS_COLUMNS if residual or not c.residual_only)


def obs_names(residual: bool) -> tuple[str, ...]:
    return tuple(c.name for c in obs_columns(residual))


def obs_index(name: str, residual: bool = True) -> int:
    """The column of observation ``name`` (raises naming the allowed names)."""
    names = obs_names(residual)
    if name not in names:
        raise KeyError(f"observation column {name!r}; the columns are {list(names)}")
    return names.index(name)


def obs_spec(residual: bool) -> np.ndarray:
    """(n_columns, 2) float64: each column's signal index into SIGNALS and its divisor, the form
    the compiled ``task.kernels.observe`` reads."""
    cols = obs_columns(residual)
    for c in cols:
        if c.signal not in SIGNALS:
            raise ValueError(f"observation column {c.name!r}: signal={c.signal!r} must be one "
                             f"of {list(SIGNALS)}")
    return np.array([[SIGNALS.index(c.signal), c.divisor] for c in cols], dtype=np.float64)


def observation_space(cfg: Any, residual: bool) -> spaces.Box:
    """Bounds of the observation (positions [m], velocities [m/s], pressures [bar], k̂ [kN/m])."""
    lo, hi = zip(*(c.bounds(cfg) for c in obs_columns(residual)), strict=True)
    return spaces.Box(np.array(lo, dtype=np.float32), np.array(hi, dtype=np.float32),
                      dtype=np.float32)


def obs_table(residual: bool) -> str:
    """The observation layout as the Markdown table of the env docstrings."""
    def show(b: float | Callable[[Any], float]) -> str:
        return (b.__doc__ or "") if callable(b) else f"{b:g}".replace("-", "−")

    rows = ["| Num | Observation | Unit | Min | Max |", "|-----|-------------|------|-----|-----|"]
    for i, c in enumerate(obs_columns(residual)):
        rows.append(f"| {i} | {c.label} | {c.unit} | {show(c.low)} | {show(c.high)} |")
    return "\n".join(rows)


# Kept for code that wants the names as constants (the layout at import time).
OBS_NAMES = obs_names(False)
RESIDUAL_OBS_NAMES = obs_names(True)
# Column indices by name, for controllers reading an observation (the residual env's layout; the
# direct env's is the same without k̂).
(OBS_X, OBS_V, OBS_XREF, OBS_VREF, OBS_SIN, OBS_COS, OBS_PE, OBS_PF, OBS_KREF) = (
    obs_index(name) for name in ("x_m", "v_mps", "x_ref_m", "v_ref_mps", "sin_phase",
                                 "cos_phase", "pe_bar", "pf_bar", "k_ref_kN_per_m"))
# [N/m] per unit of the k̂ column (the observation carries kN/m)
OBS_KREF_SCALE = obs_columns(True)[OBS_KREF].divisor

# --------------------------------------------------------------------------- step output
# What the step computes per leg: safe command (2), true k, reward and its three terms, safety
# flags, terminated (1.0 / 0.0).
OUT = ("cmd_e_Pa", "cmd_f_Pa", "k_N_per_m", "reward", "reward_position", "reward_stiffness",
       "reward_effort", "safety", "terminated")
O_CMDE, O_CMDF, O_K, O_R, O_RX, O_RK, O_RU, O_FLAGS, O_TERM = (OUT.index(n) for n in OUT)

# ------------------------------------------------------------------------------- safety
SAFETY_CLIPPED = 1  # a command was clipped to [0, p_max]
SAFETY_SLEW = 2  # a command was slew-rate limited

# --------------------------------------------------------------------------------- info
# Keys every env fills on every step (docs/design.md#step-contract) and the reward breakdown.
INFO_KEYS = ("x_m", "x_ref_m", "k_N_per_m", "k_ref_N_per_m", "pressure_cmd_bar", "pressure_bar")
REWARD_KEYS = ("reward_position", "reward_stiffness", "reward_effort")


def step_info(out: np.ndarray, state: np.ndarray, ref: np.ndarray, t_s: Any) -> dict[str, Any]:
    """The step ``info`` of one leg (1-D rows: Python floats) or a batch (2-D: arrays).

    ``out`` holds the OUT columns, ``state`` the STATE columns (measured), ``ref`` the plan's
    PLAN row for the step just reached; ``t_s`` its time. Pressures are shown in bar.
    """
    if out.ndim == 1:  # one leg: plain Python numbers (one tolist per row is the cheap read)
        o, s, r = out.tolist(), state.tolist(), ref.tolist()
        return {
            "x_m": s[ST_X],
            "x_ref_m": r[T_XREF],
            "k_N_per_m": o[O_K],
            "k_ref_N_per_m": r[T_KREF],
            "pressure_cmd_bar": np.array((o[O_CMDE] / BAR, o[O_CMDF] / BAR)),
            "pressure_bar": np.array((s[ST_PE] / BAR, s[ST_PF] / BAR)),
            "reward_position": o[O_RX],
            "reward_stiffness": o[O_RK],
            "reward_effort": o[O_RU],
            "safety": int(o[O_FLAGS]),
            "t_s": t_s,
        }
    return {key: np.array(value) for key, value in (  # a batch: arrays, one entry per leg
        ("x_m", state[:, ST_X]),
        ("x_ref_m", ref[:, T_XREF]),
        ("k_N_per_m", out[:, O_K]),
        ("k_ref_N_per_m", ref[:, T_KREF]),
        ("pressure_cmd_bar", out[:, O_CMDE:O_CMDF + 1] / BAR),
        ("pressure_bar", state[:, ST_PE:ST_PF + 1] / BAR),
        ("reward_position", out[:, O_RX]),
        ("reward_stiffness", out[:, O_RK]),
        ("reward_effort", out[:, O_RU]),
        ("safety", out[:, O_FLAGS].astype(np.int64)),
        ("t_s", t_s),
    )}


# ------------------------------------------------------------------------------- action
def action_space() -> spaces.Box:
    """Every id: two normalised actions in [−1, 1] (extensor first), as SB3 recommends."""
    return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)


def check_action(action: Any, n: int | None = None) -> np.ndarray:
    """Validate an action: shape (2,) (or (n, 2) for a vector env), real numbers, finite; then
    clip to [−1, 1] (as SB3 does with its policies' actions, documented in the envs' Action
    Space). NaN, ±inf, wrong shapes and non-numbers raise ``ValueError``; returns float64."""
    arr = np.asarray(action)
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"action={action!r} must be real numbers (dtype {arr.dtype} given); "
                         "allowed range [-1, 1] (extensor, flexor)")
    shape = (2,) if n is None else (n, 2)
    if arr.shape != shape:
        what = "action has" if n is None else "actions have"
        raise ValueError(f"{what} shape {arr.shape}; expected {shape} (extensor, flexor) in "
                         "[-1, 1]")
    if n is None:  # one env, every step: on two Python floats, a fraction of the array ops'
        # cost; the same float64 values and the same clip as the batch branch below
        a_e, a_f = (arr if arr.dtype.char in "efd" else arr.astype(np.float64)).tolist()
        if not (math.isfinite(a_e) and math.isfinite(a_f)):
            raise ValueError(f"action={[a_e, a_f]} must be finite; allowed range [-1, 1] "
                             "(extensor, flexor)")
        return np.array((a_e if -1.0 <= a_e <= 1.0 else (1.0 if a_e > 0.0 else -1.0),
                         a_f if -1.0 <= a_f <= 1.0 else (1.0 if a_f > 0.0 else -1.0)))
    a = arr.astype(np.float64, copy=False)
    finite = np.isfinite(a)
    if not finite.all():
        row = int(np.flatnonzero(~finite.all(axis=1))[0])
        raise ValueError(f"action[{row}]={a[row].tolist()} must be finite; allowed range "
                         "[-1, 1] (extensor, flexor)")
    return np.minimum(np.maximum(a, -1.0), 1.0)  # np.clip's dispatch costs a sim step's time
