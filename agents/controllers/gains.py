"""Gains files: the tuned gains of the classical baselines as YAML, written by
``mpa-gym tune-baselines --out FILE`` and read by ``evaluate --gains``, ``rollout --gains``,
``bench --loop … --gains`` and a run config's ``supervisor.gains`` (its fallback and last
resort), all through :func:`load_gains`.

The file::

    gains:                      # baseline name -> {field: value}; fields omitted keep defaults
      pid: {kp_bar_per_m: 5.5, ki_bar_per_m_s: 127.0, kd_bar_s_per_m: 2.15, tf_s: 0.00093}
      rc: {learn: 0.3, delay_margin_s: 0.05}
    tuned_on:                   # optional: what tune-baselines tuned them on (not read)
      pid: {...}

A field is a keyword argument of the baseline's class (its dataclass fields less the plan,
params and stack): :data:`GAIN_FIELDS`. Values are finite and ≥ 0; a class checks its own
further ranges when it is built (``RepetitiveControl``'s ``learn`` < 2).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import yaml

import mpa_gym.agents.controllers.baselines as baselines
from mpa_gym.agents.controllers.baselines import BASELINES
from mpa_gym.files import read_yaml
from mpa_gym.model.params import check_keys, check_range

NOT_GAINS = ("plan", "params", "row_plans")  # dataclass fields a gains file cannot set
# baseline name -> the fields a gains file may set (the baselines with gains)
GAIN_FIELDS: dict[str, tuple[str, ...]] = {
    name: tuple(f.name for f in dataclasses.fields(getattr(baselines, cls))
                if f.name not in NOT_GAINS)
    for name, cls in BASELINES.items()
    if dataclasses.is_dataclass(getattr(baselines, cls))}
FILE_KEYS = ("gains", "tuned_on")

Gains = dict[str, dict[str, float]]


def load_gains(source: str | Path | dict[str, Any] | None, where: str = "--gains") -> Gains:
    """The gains of a gains file (a path) or of its ``gains`` mapping given inline, checked:
    known baselines, known fields, finite values ≥ 0. ``where`` names the flag or config key
    in the errors. None: no gains ({})."""
    if source is None:
        return {}
    if isinstance(source, str | Path):
        data = read_yaml(source, f"{where}: gains file")
        if not isinstance(data, dict) or "gains" not in data:
            raise ValueError(f"{where} {str(source)!r}: a gains file is a mapping with keys "
                             f"{list(FILE_KEYS)} (`mpa-gym tune-baselines --out` writes one)")
        check_keys(f"{where} {str(source)!r}", data, FILE_KEYS)
        where, gains = f"{where} {str(source)!r}: gains", data["gains"]
    else:
        gains = source
    if not isinstance(gains, dict):
        raise ValueError(f"{where}={gains!r} must be a mapping of baseline names "
                         f"{sorted(GAIN_FIELDS)} to their fields")
    check_keys(where, gains, GAIN_FIELDS)
    out: Gains = {}
    for name, fields in gains.items():
        if not isinstance(fields, dict):
            raise ValueError(f"{where}.{name}={fields!r} must be a mapping of fields "
                             f"{list(GAIN_FIELDS[name])} to values")
        check_keys(f"{where}.{name}", fields, GAIN_FIELDS[name])
        out[name] = {k: check_range(f"{where}.{name}.{k}", v, 0.0, math.inf)
                     for k, v in fields.items()}
    return out


def gains_yaml(gains: Gains, tuned_on: dict[str, Any] | None = None) -> str:
    """The text of a gains file (:func:`load_gains` reads it back to the same values)."""
    data: dict[str, Any] = {"gains": {n: {k: float(v) for k, v in g.items()}
                                      for n, g in gains.items()}}
    if tuned_on:
        data["tuned_on"] = tuned_on
    return ("# baseline gains (mpa_gym.agents.controllers.gains): read by mpa-gym evaluate / "
            "rollout / bench --loop --gains FILE and a run config's supervisor.gains\n"
            + yaml.safe_dump(data, sort_keys=False))
