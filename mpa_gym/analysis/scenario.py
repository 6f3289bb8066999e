"""Simulation scenarios of Sec. 3.2 and 4.4: schema, YAML loading and validation.

A scenario fixes the reference (Eq. 21), the feedforward inputs (Eq. 22 or a stiffness target for
Eq. 25), the initial state, the *true* plant (overrides of the nominal model that the feedforward
does not know about) and external disturbances. Named scenarios are the YAML files in
``configs/scenarios/``; ``load_scenario`` also takes a path or a dict.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mpa_gym.configs import RIG_DIR, SCENARIO_DIR
from mpa_gym.design.feedforward import (
    P_MAX_DEFAULT,
    ConstantStiffness,
    FeedforwardDesign,
    StiffnessEnvelope,
)
from mpa_gym.design.reference import MODES, FlexorPattern, Reference, mode_pattern
from mpa_gym.files import read_yaml
from mpa_gym.model.params import (
    BAR,
    DEFAULT_PARAMS,
    Params,
    RegulatorParams,
    check_keys,
    check_range,
)

SCENARIO_DIR_ENV = "MPA_GYM_SCENARIOS"


class ScenarioError(ValueError):
    """A malformed scenario (file or dict); the message names the key, the value and the range."""


@dataclass(frozen=True)
class InitialState:
    x_m: float  # [m] X(0)
    v_mps: float  # [m/s] V(0)


def _number(name: str, value: Any, **rng: Any) -> float:
    """A real number (not a bool or a string) within ``rng`` (``check_range``'s arguments)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ScenarioError(f"{name}={value!r} must be a number")
    try:
        return check_range(name, value, **rng)
    except ValueError as e:
        raise ScenarioError(str(e)) from None


K_CONST_MAX = 1e5  # [N/m] largest |k̂| of a constant-stiffness design (Fig. 11: k <= ~1.3e3)
P_MAX_LIMIT_BAR = 100.0  # [bar] largest regulator limit: 14x the default 7 bar


@dataclass(frozen=True)
class Inputs:
    """Feedforward inputs: an Eq. (22) pattern, a Table 1 mode, or an Eq. (25) stiffness target
    (at most one of ``mode``, ``stiffness``, ``stiffness_const_N_per_m``)."""

    pf_mean_bar: float = 0.5  # [bar] P'_f0 (Fig. 3: constant 0.5 bar)
    pf_amp_bar: float = 0.0  # [bar] A_f
    mode: int | None = None  # Table 1 preset; overrides pf_mean_bar / pf_amp_bar
    stiffness: str | None = None  # "kmax" | "kmin" (Fig. 11) -> Eq. (25) design
    stiffness_const_N_per_m: float | None = None  # constant k̂ -> Eq. (25) design
    p_max_bar: float = P_MAX_DEFAULT / BAR  # [bar] upper pressure limit of the regulators

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        if self.mode is not None and (isinstance(self.mode, bool) or not isinstance(
                self.mode, int | np.integer) or int(self.mode) not in MODES):
            raise ScenarioError(f"inputs.mode={self.mode!r} must be one of {sorted(MODES)}")
        if self.stiffness is not None and self.stiffness not in ("kmax", "kmin"):
            raise ScenarioError(f"inputs.stiffness={self.stiffness!r} must be 'kmax' or 'kmin'")
        set_(self, "p_max_bar", _number("inputs.p_max_bar", self.p_max_bar, low=0.0,
                                        high=P_MAX_LIMIT_BAR, low_open=True, unit="bar",
                                        note="a McKibben muscle is rated below 10 bar"))
        chosen = [k for k in ("mode", "stiffness", "stiffness_const_N_per_m")
                  if getattr(self, k) is not None]
        if len(chosen) > 1:
            raise ScenarioError(f"inputs: give at most one of mode, stiffness, "
                                f"stiffness_const_N_per_m (got {chosen})")
        mean = _number("inputs.pf_mean_bar", self.pf_mean_bar, low=0.0, high=self.p_max_bar,
                       unit="bar")
        set_(self, "pf_mean_bar", mean)
        set_(self, "pf_amp_bar", _number("inputs.pf_amp_bar", self.pf_amp_bar, low=-mean,
                                         high=mean, unit="bar", note="Eq. 22: |A_f| <= P'_f0"))
        if self.stiffness_const_N_per_m is not None:
            set_(self, "stiffness_const_N_per_m", _number(
                "inputs.stiffness_const_N_per_m", self.stiffness_const_N_per_m,
                low=-K_CONST_MAX, high=K_CONST_MAX, unit="N/m",
                note="about 100 times the Fig. 11 envelope's largest k"))

    def design(self, reference: Reference, params: Params = DEFAULT_PARAMS) -> FeedforwardDesign:
        """The feedforward for ``reference`` on the nominal model ``params``: Eq. (25) for a
        stiffness target (the Fig. 11 envelope or a constant k̂), else Eq. (16) under the
        Eq. (22) flexor pattern (a Table 1 mode's, or P'_f0 and A_f)."""
        if self.stiffness is not None:
            return FeedforwardDesign(reference, stiffness=StiffnessEnvelope(
                self.stiffness, reference, params=params), params=params)
        if self.stiffness_const_N_per_m is not None:
            return FeedforwardDesign(reference, stiffness=ConstantStiffness(
                self.stiffness_const_N_per_m), params=params)
        flexor = (mode_pattern(self.mode, reference.period) if self.mode is not None
                  else FlexorPattern(self.pf_mean_bar * BAR, self.pf_amp_bar * BAR,
                                     reference.period))
        return FeedforwardDesign(reference, flexor=flexor, params=params)


@dataclass(frozen=True)
class Plant:
    """The true plant: overrides of the nominal model (``None`` keeps the nominal value) and the
    realism the paper's model leaves out. The design always keeps the nominal model.

    Defaults are the ideal plant of the paper (no lag, no quantisation, perfect sensors).
    """

    extra_mass_kg: float = 0.0  # [kg] load at the hip (Sec. 4.4: +1 kg)
    mass_kg: float | None = None  # [kg] true m instead of Tab. A2's 3.74 kg
    gamma_Ns_per_m: float | None = None  # [N s/m] true γ instead of Tab. A1's 30 N s/m
    C1_Pa: float | None = None  # [Pa] true Mooney-Rivlin C1 instead of 192 kPa
    C2_Pa: float | None = None  # [Pa] true Mooney-Rivlin C2 instead of 1.3 kPa
    thickness_m: float | None = None  # [m] true bladder wall thickness instead of 1 mm
    pressure_lag_s: float = 0.0  # [s] first-order regulator time constant (0: ideal)
    pressure_dead_time_s: float = 0.0  # [s] regulator dead time, any value (not whole steps)
    pressure_slew_bar_per_s: float = 0.0  # [bar/s] regulator rate limit (0: unlimited)
    braid_friction_ratio: float = 0.0  # [-] MPA braid friction / pressure force (hysteresis)
    slider_friction_N: float = 0.0  # [N] Coulomb friction of the hip slider
    slider_viscous_Ns_per_m: float = 0.0  # [N s/m] viscous friction of the hip slider
    pressure_quantum_bar: float = 0.0  # [bar] command resolution of the regulator (0: exact)
    encoder_resolution_m: float = 0.0  # [m] hip-encoder quantum (0: exact)
    position_noise_m: float = 0.0  # [m] std of white noise on the measured X
    velocity_noise_mps: float = 0.0  # [m/s] std of white noise on the measured V
    pressure_noise_bar: float = 0.0  # [bar] std of white noise on the measured pressures

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is not None:
                object.__setattr__(self, f.name, check_plant_value(f.name, v))


# field -> (low, high, low_open, unit): the allowed range of each plant field, shared by the
# loader, the randomisation ranges and reset(options=...)
PLANT_RANGES: dict[str, tuple[float, float, bool, str]] = {
    "extra_mass_kg": (0.0, 50.0, False, "kg"),
    "mass_kg": (0.0, 100.0, True, "kg"),
    "gamma_Ns_per_m": (0.0, 1e4, True, "N s/m"),
    "C1_Pa": (0.0, 1e8, True, "Pa"),
    "C2_Pa": (0.0, 1e8, False, "Pa"),
    "thickness_m": (0.0, 7.5e-3, True, "m"),
    "pressure_lag_s": (0.0, 1.0, False, "s"),
    "pressure_dead_time_s": (0.0, 1.0, False, "s"),
    "pressure_slew_bar_per_s": (0.0, 1e4, False, "bar/s"),
    "braid_friction_ratio": (0.0, 0.5, False, ""),
    "slider_friction_N": (0.0, 100.0, False, "N"),
    "slider_viscous_Ns_per_m": (0.0, 1e3, False, "N s/m"),
    "pressure_quantum_bar": (0.0, 1.0, False, "bar"),
    "encoder_resolution_m": (0.0, 0.01, False, "m"),
    "position_noise_m": (0.0, 0.01, False, "m"),
    "velocity_noise_mps": (0.0, 1.0, False, "m/s"),
    "pressure_noise_bar": (0.0, 1.0, False, "bar"),
}
# what domain randomisation may draw per episode (plus the initial-state offsets)
RANDOMIZABLE = ("extra_mass_kg", "mass_kg", "gamma_Ns_per_m", "C1_Pa", "C2_Pa", "thickness_m",
                "pressure_lag_s", "pressure_dead_time_s", "pressure_slew_bar_per_s",
                "braid_friction_ratio", "slider_friction_N", "slider_viscous_Ns_per_m")
INITIAL_OFFSETS: dict[str, tuple[float, float, bool, str]] = {
    "initial_x_offset_m": (-0.05, 0.05, False, "m"),
    "initial_v_offset_mps": (-1.0, 1.0, False, "m/s"),
}
# A random kick: an impulse on the hip that an episode draws like a plant field (force, start,
# length; the ``Impulse`` of ``disturbances`` with drawn values). Leaving ``kick_force_N`` out
# of a draw (its ``p_off``) leaves the episode without one. Not a plant field: a rig has no
# such setting (the device emulator plays a scenario's ``plant`` and ``disturbances``).
KICK_FIELDS: dict[str, tuple[float, float, bool, str]] = {
    "kick_force_N": (-1e4, 1e4, False, "N"),
    "kick_t_s": (0.0, 3600.0, False, "s"),
    "kick_duration_s": (0.0, 10.0, False, "s"),
}
# what an episode draws besides the plant: the initial-state offsets and the random kick
EPISODE_FIELDS = {**INITIAL_OFFSETS, **KICK_FIELDS}


def check_plant_value(key: str, value: Any, where: str = "plant") -> float:
    """Validate one plant value (or an episode draw's: initial offset, random kick) against its
    allowed range."""
    rng = {**PLANT_RANGES, **EPISODE_FIELDS}
    if key not in rng:
        check_keys(where, [key], rng, ScenarioError)
    lo, hi, lo_open, unit = rng[key]
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ScenarioError(f"{where}.{key}={value!r} must be a number")
    try:
        return check_range(f"{where}.{key}", value, lo, hi, low_open=lo_open, unit=unit)
    except ValueError as e:
        raise ScenarioError(str(e)) from None


@dataclass(frozen=True)
class Randomization:
    """Per-episode uniform ranges (low, high) for plant fields, initial-state offsets and a
    random kick (``KICK_FIELDS``).

    ``p_off`` gives a field a probability of being left out of a draw, so that the episode keeps
    the scenario's ``plant`` value (for a plant effect: off). Uniform draws of a dozen effects
    rarely give a plant with one effect strong and the others off (a long dead time without
    friction to damp it); ``p_off`` makes such plants common.
    """

    ranges: tuple[tuple[str, float, float], ...] = ()
    p_off: tuple[tuple[str, float], ...] = ()  # (field, probability of no draw)

    def __post_init__(self) -> None:
        checked = []
        for entry in self.ranges:
            if not (isinstance(entry, tuple | list) and len(entry) == 3):
                raise ScenarioError(f"randomize: {entry!r} must be a (field, low, high) triple")
            k, lo, hi = entry
            check_keys("randomize", [k], {*RANDOMIZABLE, *EPISODE_FIELDS}, ScenarioError)
            lo = check_plant_value(k, lo, "randomize")
            hi = check_plant_value(k, hi, "randomize")
            if lo > hi:
                raise ScenarioError(f"randomize.{k}=[{lo:g}, {hi:g}]: low must be <= high")
            checked.append((k, lo, hi))
        object.__setattr__(self, "ranges", tuple(checked))
        drawn = {k for k, _, _ in checked}
        off = []
        for entry in self.p_off:
            if not (isinstance(entry, tuple | list) and len(entry) == 2):
                raise ScenarioError(f"randomize: {entry!r} must be a (field, p_off) pair")
            k, p = entry
            if k not in drawn:
                raise ScenarioError(f"randomize.{k}.p_off: {k!r} has no range to draw from")
            if isinstance(p, bool) or not isinstance(p, int | float | np.floating | np.integer):
                raise ScenarioError(f"randomize.{k}.p_off={p!r} must be a number")
            try:
                off.append((k, check_range(f"randomize.{k}.p_off", p, 0.0, 1.0)))
            except ValueError as e:
                raise ScenarioError(str(e)) from None
        object.__setattr__(self, "p_off", tuple(off))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Randomization:
        """From the YAML form {field: [low, high]} or {field: {range: [low, high], p_off: p}}."""
        ranges, p_off = [], []
        for k, v in d.items():
            if isinstance(v, dict):
                unknown = sorted(set(v) - {"range", "p_off"})
                if unknown or "range" not in v:
                    raise ScenarioError(f"randomize.{k}={v!r} must be {{range: [low, high], "
                                        f"p_off: p}} (p_off optional)")
                if "p_off" in v:
                    p_off.append((k, v["p_off"]))
                v = v["range"]
            if not (isinstance(v, list | tuple) and len(v) == 2):
                raise ScenarioError(f"randomize.{k}={v!r} must be a [low, high] pair")
            ranges.append((k, v[0], v[1]))
        return cls(tuple(ranges), tuple(p_off))

    def as_dict(self) -> dict[str, Any]:
        off = dict(self.p_off)
        return {k: {"range": [lo, hi], "p_off": off[k]} if k in off else [lo, hi]
                for k, lo, hi in self.ranges}

    def describe(self) -> str:
        """One line for reports: "field low–high (off p), …", or "none"."""
        off = dict(self.p_off)
        return ", ".join(f"{k} {lo:g}–{hi:g}" + (f" (off {off[k]:g})" if k in off else "")
                         for k, lo, hi in self.ranges) or "none"

    def sample(self, rng: np.random.Generator) -> dict[str, float]:
        """One draw: {field: value} (fields in the order given; a field left out by its
        ``p_off`` is absent). The values are drawn first and the ``p_off`` coins after them,
        so adding a ``p_off`` leaves every field's value as it was."""
        draw = {k: float(rng.uniform(lo, hi)) for k, lo, hi in self.ranges}
        for k, p in self.p_off:
            if rng.random() < p:
                del draw[k]
        return draw

    def span(self, plant: Plant, params: Params = DEFAULT_PARAMS
             ) -> dict[str, tuple[float, float]]:
        """The smallest interval of each field's draws: its range, widened to the value the
        episode keeps where ``p_off`` leaves the field out (the scenario's ``plant`` value, the
        nominal ``params`` where that is unset, 0 for an initial offset or a kick)."""
        off = dict(self.p_off)
        nominal = {"mass_kg": params.leg.m, "gamma_Ns_per_m": params.mpa.gamma,
                   "C1_Pa": params.mpa.C1, "C2_Pa": params.mpa.C2,
                   "thickness_m": params.mpa.thickness}
        span = {}
        for k, lo, hi in self.ranges:
            if off.get(k, 0.0) > 0.0:
                kept = getattr(plant, k, 0.0)
                kept = nominal[k] if kept is None else kept
                lo, hi = min(lo, kept), max(hi, kept)
            span[k] = (lo, hi)
        return span


@dataclass(frozen=True)
class Impulse:
    """A constant vertical force on the hip from ``t_s`` for ``duration_s`` (Sec. 3.2: 20 N for
    0.05 s). ``type: static`` is a force that, once applied, stays (duration = rest of the run)."""

    t_s: float  # [s] start
    force_N: float  # [N] positive upward
    duration_s: float  # [s]
    type: str = "impulse"  # "impulse" or "static"


@dataclass(frozen=True)
class Scenario:
    name: str
    duration_s: float = 30.0
    reference: Reference = field(default_factory=Reference)
    inputs: Inputs = field(default_factory=Inputs)
    initial_state: InitialState | None = None  # None: start on the reference, (X̂(0), V̂(0))
    plant: Plant = field(default_factory=Plant)
    disturbances: tuple[Impulse, ...] = ()
    randomize: Randomization = field(default_factory=Randomization)
    description: str = ""

    def start_state(self) -> tuple[float, float]:
        """(X(0), V(0)) [m, m/s]."""
        if self.initial_state is None:
            return (float(self.reference.position(0.0)), float(self.reference.velocity(0.0)))
        return (self.initial_state.x_m, self.initial_state.v_mps)

    def design(self, params: Params = DEFAULT_PARAMS) -> FeedforwardDesign:
        """The feedforward, designed on the nominal model ``params`` (never on the plant)."""
        return self.inputs.design(self.reference, params)

    def plant_params(self, params: Params = DEFAULT_PARAMS, plant: Plant | None = None
                     ) -> Params:
        """The true plant: the nominal model with this scenario's (or ``plant``'s) overrides."""
        pl = self.plant if plant is None else plant
        m = (pl.mass_kg if pl.mass_kg is not None else params.leg.m) + pl.extra_mass_kg
        over = {"gamma": pl.gamma_Ns_per_m, "C1": pl.C1_Pa, "C2": pl.C2_Pa,
                "thickness": pl.thickness_m}
        mpa = dataclasses.replace(params.mpa, **{k: v for k, v in over.items() if v is not None},
                                  friction=pl.braid_friction_ratio)
        leg = dataclasses.replace(params.leg, m=m, friction_coulomb=pl.slider_friction_N,
                                  friction_viscous=pl.slider_viscous_Ns_per_m)
        reg = RegulatorParams(lag=pl.pressure_lag_s, dead_time=pl.pressure_dead_time_s,
                              slew=pl.pressure_slew_bar_per_s * BAR)
        return Params(mpa=mpa, leg=leg, regulator=reg)

    def to_dict(self) -> dict[str, Any]:
        """The resolved scenario in the YAML schema (for writing beside results)."""
        d: dict[str, Any] = {
            "name": self.name,
            "description": self.description,
            "duration_s": self.duration_s,
            "reference": {"x0_m": self.reference.x0, "amp_m": self.reference.amp,
                          "period_s": self.reference.period},
            "inputs": {k: v for k, v in dataclasses.asdict(self.inputs).items() if v is not None},
            "plant": {k: v for k, v in dataclasses.asdict(self.plant).items() if v is not None},
            "disturbances": [
                {"type": d.type, "t_s": d.t_s, "force_N": d.force_N, "duration_s": d.duration_s}
                for d in self.disturbances
            ],
            "randomize": self.randomize.as_dict(),
        }
        if self.initial_state is not None:
            d["initial_state"] = dataclasses.asdict(self.initial_state)
        return d


# ----------------------------------------------------------------------------- loading
# YAML key of each Reference field (Eq. 21)
REFERENCE_KEYS = {"x0_m": "x0", "amp_m": "amp", "period_s": "period"}
_TOP_KEYS = {"name", "description", "duration_s", "initial_state", "reference", "inputs", "plant",
             "disturbances", "randomize"}


def _section(d: Any, where: str, allowed: set[str], required: set[str] = frozenset()
             ) -> dict[str, Any]:
    if d is None:
        d = {}
    if not isinstance(d, dict):
        raise ScenarioError(f"{where} must be a mapping, got {type(d).__name__}: {d!r}")
    check_keys(where, d, allowed, ScenarioError)
    missing = sorted(required - set(d))
    if missing:
        raise ScenarioError(f"{where}: missing required key(s) {missing}")
    return d


def _num(d: dict[str, Any], key: str, where: str, default: Any = None, **rng: Any) -> Any:
    if key not in d or d[key] is None:
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ScenarioError(f"{where}.{key}={v!r} must be a number{_why_not_number(v)}")
    try:
        return check_range(f"{where}.{key}", v, **rng)
    except ValueError as e:
        raise ScenarioError(str(e)) from None


def _why_not_number(v: Any) -> str:
    """YAML 1.1 reads ``1e9`` (no dot) as a string: say so when that is what happened."""
    if isinstance(v, str):
        try:
            float(v)
        except ValueError:
            return ""
        return (f" (YAML read {v!r} as text: a number in exponent form needs a dot and a "
                "sign, e.g. 1.0e+9, or write it out)")
    return ""


def scenario_from_dict(d: Any, name: str = "custom") -> Scenario:
    """Build and validate a Scenario from the YAML schema (docs/design.md#scenarios)."""
    top = _section(d, f"scenario {name!r}", _TOP_KEYS, {"duration_s"})
    w = str(top.get("name", name))
    try:
        ref_d = _section(top.get("reference"), f"{w}: reference", set(REFERENCE_KEYS))
        ref = Reference(**{REFERENCE_KEYS[k]: _num(ref_d, k, "reference") for k in ref_d
                           if ref_d[k] is not None})
        ref.check_reachable(DEFAULT_PARAMS.leg)
        inp_d = _section(top.get("inputs"), f"{w}: inputs",
                         {f.name for f in dataclasses.fields(Inputs)})
        inputs = Inputs(**{k: v for k, v in inp_d.items() if v is not None})
        plant_d = _section(top.get("plant"), f"{w}: plant", set(PLANT_RANGES))
        plant = Plant(**{k: v for k, v in plant_d.items() if v is not None})
        randomize = Randomization.from_dict(_section(top.get("randomize"), f"{w}: randomize",
                                                     set(RANDOMIZABLE) | set(EPISODE_FIELDS)))
        duration = _num(top, "duration_s", "scenario", None, low=0.0, low_open=True, high=3600.0,
                        unit="s")
        init = None
        if top.get("initial_state") is not None:
            init_d = _section(top["initial_state"], f"{w}: initial_state", {"x_m", "v_mps"},
                              {"x_m", "v_mps"})
            lo, hi = DEFAULT_PARAMS.leg.x_domain
            init = InitialState(
                _num(init_d, "x_m", "initial_state", low=lo, high=hi, low_open=True,
                     high_open=True, unit="m"),
                _num(init_d, "v_mps", "initial_state", low=-10.0, high=10.0, unit="m/s"))
        dist_l = top.get("disturbances") or []
        if not isinstance(dist_l, list):
            raise ScenarioError(f"{w}: disturbances must be a list, got {dist_l!r}")
        dists = []
        for i, dd in enumerate(dist_l):
            where = f"disturbances[{i}]"
            kind = dd.get("type") if isinstance(dd, dict) else None
            need = {"type", "t_s", "force_N"} | ({"duration_s"} if kind == "impulse" else set())
            dd = _section(dd, f"{w}: {where}", {"type", "t_s", "force_N", "duration_s"}, need)
            if kind not in ("impulse", "static"):
                raise ScenarioError(f"{where}.type={kind!r}: allowed types are "
                                    "['impulse', 'static']")
            t_s = _num(dd, "t_s", where, low=0.0, high=duration, unit="s")
            dists.append(Impulse(
                t_s=t_s,
                force_N=_num(dd, "force_N", where, low=-1e4, high=1e4, unit="N"),
                duration_s=_num(dd, "duration_s", where, duration - t_s, low=0.0,
                                low_open=True, high=duration, unit="s"),
                type=kind))
        return Scenario(name=w, duration_s=duration, reference=ref, inputs=inputs,
                        initial_state=init, plant=plant, disturbances=tuple(dists),
                        randomize=randomize,
                        description=str(top.get("description", "")))
    except ScenarioError as e:
        raise ScenarioError(f"scenario {w!r}: {e}") from None
    except ValueError as e:  # a dataclass's own range check
        raise ScenarioError(f"scenario {w!r}: {e}") from None


def scenario_dirs() -> list[Path]:
    """Where named scenarios are looked up: $MPA_GYM_SCENARIOS, then the shipped scenarios and
    rigs (``mpa_gym.configs``: ``scenarios/``, ``rigs/``)."""
    dirs = []
    if os.environ.get(SCENARIO_DIR_ENV):
        dirs.append(Path(os.environ[SCENARIO_DIR_ENV]))
    return [*dirs, SCENARIO_DIR, RIG_DIR]


def scenario_names() -> list[str]:
    """Names of the scenarios found in :func:`scenario_dirs`."""
    return sorted({p.stem for d in scenario_dirs() if d.is_dir() for p in d.glob("*.yaml")})


def load_scenario(spec: str | os.PathLike[str] | dict[str, Any] | Scenario) -> Scenario:
    """A Scenario from a name (:func:`scenario_names`), a YAML path, a dict or a Scenario."""
    if isinstance(spec, Scenario):
        return spec
    if isinstance(spec, dict):
        return scenario_from_dict(spec, str(spec.get("name", "custom")))
    if not isinstance(spec, str | os.PathLike):
        raise ScenarioError(f"scenario={spec!r} must be a name of {scenario_names()}, a YAML "
                            "path, a mapping or a Scenario")
    path = Path(spec)
    if not path.suffix:
        for d in scenario_dirs():
            if (d / f"{spec}.yaml").is_file():
                path = d / f"{spec}.yaml"
                break
        else:
            if path.is_dir():
                raise ScenarioError(f"scenario={str(spec)!r} is a folder, not a YAML file or one "
                                    f"of the named scenarios {scenario_names()}")
            raise ScenarioError(f"scenario={str(spec)!r} is neither a file nor one of the named "
                                f"scenarios {scenario_names()}")
    data = read_yaml(path, "scenario file", ScenarioError)
    data = {} if data is None else data  # an empty file: every field's default
    if not isinstance(data, dict):  # the file is what the user named: say which
        raise ScenarioError(f"scenario file {str(path)!r} must be a mapping of fields, got "
                            f"{type(data).__name__}: {data!r}")
    return scenario_from_dict(data, data.get("name", path.stem))
