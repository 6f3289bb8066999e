"""Run-time assurance for a learned residual: a declared cascade of controllers, each handing
the loop to the next when one of its monitors trips.

The Simplex architecture (Sha, "Using simplicity to control complexity", IEEE Software 2001;
run-time assurance in the safe-RL literature): a high-performance controller that cannot be
verified runs beside a simple one that can, and a monitor hands control to the simple one when
the loop leaves the region where the first is known to behave. The rule is declared
(``SupervisorSpec``): a cascade of stages (``Stage``), the learned policy, a fallback baseline
(any baseline of ``mpa_gym.agents.controllers.baselines``; the default config names them in the
order ``mpa_gym.agents.evaluation.calibrate`` measured) and optionally a last resort (another
baseline, or ``ff``, the feedforward alone); each stage names the monitors that
judge its loop and the reference periods its loop has to settle first. When one of them trips,
the next stage drives the rest of the episode (a latch: a controller that destabilised this
plant once does it again). The last stage drives to the end.

Each monitor (``Monitor``) is a running mean of a signal s of the tracking error e = X̂ − X,
z_t = z_{t−1} + α (s_t² − z_{t−1}), α = dt / (window_s + dt), each sample clipped to
±``clip_mm`` (winsorised), left at zero for ``arm_periods`` reference periods after its stage
began; it trips when √z passes ``level_mm``.

- ``Divergence``, s = e: a loop leaving the tracking region, seen within its short window.
- ``LimitCycle``, s = e_t − e_{t−T}, T the reference period: an oscillation that does not
  repeat with the reference. A stable loop settles onto a motion of period T (a sag under a
  load, a phase lag), which cancels in the difference; an aperiodic part of RMS ρ gives
  ≈ √2 ρ. It is the robustness sweep's "unstable" criterion
  (``mpa_gym.agents.evaluation.robustness``) made causal, armed after two periods so that it does
  not compare the settled loop with its start-up transient.
- ``Persistent``, s = e: a periodic error of several mm, which the limit cycle cannot see (its
  change over a period is zero) and which stays under the divergence level.

The clip bounds what a kick can add: its transient (centimetres for a few tenths of a second)
adds at most clip² for its length to a mean over seconds, while a signal within ±clip is
measured exactly and a larger one still reaches clip² > level².

On entering a stage its monitors start again from zero. The fallback's loop settles from the
policy's oscillation, slowly where it is near its own stability margin: its grace periods keep
that transient from handing a loop it holds to the last resort. The fallback takes over
bumplessly (Åström & Hägglund, "Advanced PID control", 2006, § 3.5) when it has a
``take_over(observation, held, state, rows, history)`` method (``pid``, ``mbfb``, ``rc``,
``afc``): pid's, mbfb's and rc's integrator starts from the command the policy held, the mean
of the policy's actions over the last reference period (its DC part, in which the periodic
corrections and, to first order, the oscillation that tripped cancel); afc's coefficients
start from that mean and the first harmonic of the same actions (``history``, the period in
time order), what afc itself would converge to. Either way the load the policy carried stays
carried. A stage without it (``ff``), and every stage after the fallback, starts from its rest
state.

Where the spec has a ``select`` (``Selection``), the stage every episode starts at is chosen
before it, on the model: each stage's controller alone is simulated on the scenario's plant
(``mpa_gym.agents.evaluation.select``; the policy failing where its monitors, replayed over
its episode, would hand it over) and the policy starts unless a later stage is predicted better
on position by more than its ratio without being worse on stiffness by more than its
stiffness ratio (``Supervised.choose``; the residual task tracks both). Monitors that fire on
instability alone cannot see a stable loop that its fallback would track better, and hand an
unstable one over too late for it to settle; the model sees both before the first step. A
chosen stage starts from its rest state and is reported as chosen (``who_drove``'s
``chosen``), not as a hand-over.

``Supervised`` has the ``predict`` of every controller, so evaluation, the robustness sweep and
rig rollouts run it unchanged; ``took_over(policy, state)`` gives each row's stage, and
``who_drove`` the times the fallback and the last resort took over and the share of steps the
policy drove, so a figure never hides which controller earned it.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import numpy as np

import mpa_gym.agents.controllers.baselines as baselines
from mpa_gym.agents.controllers.baselines import BASELINES, Policy
from mpa_gym.agents.controllers.gains import load_gains
from mpa_gym.model.params import check_keys, check_range
from mpa_gym.task.contract import OBS_X as OX
from mpa_gym.task.contract import OBS_XREF as OXR

POLICY, FALLBACK, LAST_RESORT = 0, 1, 2  # the stages' places in the cascade: who drives
HAND_OVERS = (("fallback_s", FALLBACK), ("last_resort_s", LAST_RESORT))  # report key, stage
# a later stage's name in reports where it drove from the start (who_drove's ``chosen``)
CHOSEN = {FALLBACK: "fallback", LAST_RESORT: "last_resort"}
FALLBACKS = ("pid", "mbfb", "rc")  # the flat form's fallbacks (a declared stage names any baseline)
# the last resorts (mpa_gym.agents.controllers.baselines names) and what ``describe`` calls them
LAST_RESORTS = {"ff": "ff alone",
                "afc": "afc (the feedforward with adaptive feedforward cancellation)"}
ARM_PERIODS = 2  # periods the limit-cycle and persistent monitors leave out of a stage
GRACE_PERIODS = 1  # periods the fallback's loop has to settle before it is judged
LEVEL_MAX_MM, WINDOW_MAX_S, PERIODS_MAX = 100.0, 30.0, 100  # the monitors' allowed ranges
RATIO_MAX = 10.0  # Selection.ratio's allowed range is [1, this]
# [mm] a position RMSE below this is sensor noise (the rigs' encoder noise is 0.02 mm RMS):
# figures under it are alike, to a supervisor's start (Selection) and to the reports' audits
NOISE_FLOOR_MM = 0.05


def _check_monitor(level_mm: Any, window_s: Any, clip_mm: Any, arm_periods: Any,
                   keys: tuple[str, str, str, str]) -> None:
    """A monitor's values against their ranges; ``keys`` name them in the errors."""
    check_range(keys[0], level_mm, 0.0, LEVEL_MAX_MM, low_open=True, unit="mm")
    check_range(keys[1], window_s, 0.0, WINDOW_MAX_S, low_open=True, unit="s")
    if clip_mm is not None:
        check_range(keys[2], clip_mm, level_mm, LEVEL_MAX_MM, low_open=True, unit="mm",
                    note=f"above {keys[0]}: clipped at or below it, it could never trip")
    _check_periods(keys[3], arm_periods)


def _check_periods(key: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{key}={value!r} must be a whole number of reference periods in "
                         f"[0, {PERIODS_MAX}]")
    check_range(key, value, 0, PERIODS_MAX)


@dataclass(frozen=True)
class Monitor(ABC):
    """A running RMS of one signal of the tracking error and the level at which it trips
    (module docstring). The subclasses say which signal; their defaults are the default
    config's."""

    name: ClassVar[str]  # its key in a config's ``supervisor.monitors``
    what: ClassVar[str]  # what ``describe`` calls its statistic

    level_mm: float  # [mm] it trips once the running RMS passes this
    window_s: float  # [s] time constant of the running mean
    clip_mm: float | None  # [mm] each sample clipped to ± this before it is squared (None: not)
    arm_periods: int  # reference periods after its stage began before it accumulates

    def __post_init__(self) -> None:
        _check_monitor(self.level_mm, self.window_s, self.clip_mm, self.arm_periods,
                       tuple(f"supervisor.monitors.{self.name}.{f}" for f in
                             ("level_mm", "window_s", "clip_mm", "arm_periods")))

    @abstractmethod
    def signal(self, e: np.ndarray, past: np.ndarray) -> np.ndarray:
        """s_t per row from e_t and e_{t−T} [m] (each kind of monitor says which)."""

    def update(self, z: np.ndarray, e: np.ndarray, past: np.ndarray, armed: np.ndarray,
               dt: float) -> np.ndarray:
        """The running mean of s² [m²] after this step, per row (left where not ``armed``)."""
        clip = np.inf if self.clip_mm is None else self.clip_mm * 1e-3
        s = np.clip(self.signal(e, past), -clip, clip)
        return z + np.where(armed, dt / (self.window_s + dt) * (s**2 - z), 0.0)

    def tripped(self, z: np.ndarray) -> np.ndarray:
        """Per row, whether the running RMS √z has passed the level."""
        return np.sqrt(z) > self.level_mm * 1e-3

    def describe(self) -> str:
        return (f"{self.what} over {self.window_s:g} s"
                + (f" (each sample clipped to ±{self.clip_mm:g} mm)"
                   if self.clip_mm is not None else "")
                + f" exceeds {self.level_mm:g} mm"
                + (f" after the stage's first {self.arm_periods} periods"
                   if self.arm_periods else ""))


@dataclass(frozen=True)
class Divergence(Monitor):
    """s = e: a divergence, the loop leaving the tracking region."""

    name: ClassVar[str] = "divergence"
    what: ClassVar[str] = "the error's RMS"
    level_mm: float = 29.056
    window_s: float = 0.5
    clip_mm: float | None = None
    arm_periods: int = 0

    def signal(self, e: np.ndarray, past: np.ndarray) -> np.ndarray:
        return e


@dataclass(frozen=True)
class LimitCycle(Monitor):
    """s = e_t − e_{t−T}: an oscillation that does not repeat with the reference."""

    name: ClassVar[str] = "limit_cycle"
    what: ClassVar[str] = "the RMS of the error's one-period change"
    level_mm: float = 3.079
    window_s: float = 3.0
    clip_mm: float | None = 3.849
    arm_periods: int = ARM_PERIODS

    def signal(self, e: np.ndarray, past: np.ndarray) -> np.ndarray:
        return e - past


@dataclass(frozen=True)
class Persistent(Monitor):
    """s = e over seconds: a persistent (periodic) error of several mm."""

    name: ClassVar[str] = "persistent"
    what: ClassVar[str] = "the error's own RMS"
    level_mm: float = 3.832
    window_s: float = 3.0
    clip_mm: float | None = 5.748
    arm_periods: int = ARM_PERIODS

    def signal(self, e: np.ndarray, past: np.ndarray) -> np.ndarray:
        return e


MONITORS: dict[str, type[Monitor]] = {m.name: m for m in (Divergence, LimitCycle, Persistent)}


@dataclass(frozen=True)
class Stage:
    """One place in the cascade: who drives, which monitors judge its loop (the first to trip
    hands the row to the next stage) and how long its loop has to settle before they do."""

    # "policy", or the mpa_gym.agents.controllers.baselines name of a fallback / last resort
    controller: str
    monitors: tuple[str, ...] = ()  # names of the spec's monitors; none: it drives to the end
    grace_periods: int = 0  # reference periods from its start before its loop is judged

    def __post_init__(self) -> None:
        object.__setattr__(self, "monitors", tuple(self.monitors))

    def check(self, where: str, known: tuple[str, ...]) -> None:
        bad = [m for m in self.monitors if m not in known]
        if bad or len(set(self.monitors)) != len(self.monitors):
            raise ValueError(f"{where}.monitors={list(self.monitors)!r}: allowed distinct names "
                             f"of supervisor.monitors {list(known)}")
        _check_periods(f"{where}.grace_periods", self.grace_periods)
        if self.grace_periods and not self.monitors:
            raise ValueError(f"{where}.grace_periods={self.grace_periods} needs monitors to "
                             "delay (a stage without monitors is never judged)")


@dataclass(frozen=True)
class Selection:
    """How the stage the loop starts at is chosen before the episode: every stage's controller
    alone is simulated on the model (``mpa_gym.agents.evaluation.select``: the scenario's plant,
    the rig's as ``mpa-gym identify`` wrote it) and scored as a report scores it; the policy
    starts unless a later stage is predicted better by more than ``ratio`` on position and, with
    a ``stiffness_ratio``, no more than that ratio worse on stiffness (then the best such stage
    starts, and its monitors and the cascade after it stay as declared), a position figure
    below ``NOISE_FLOOR_MM`` counting as that floor (sensor noise)."""

    ratio: float = 1.1  # the policy starts unless its predicted RMSE exceeds ratio x the best
    # a later stage starts only if its predicted stiffness RMSE is at most this x the policy's
    # (the residual task tracks both); None (the default config's, whose comment says why):
    # chosen on position alone
    stiffness_ratio: float | None = None

    def __post_init__(self) -> None:
        check_range("supervisor.select.ratio", self.ratio, 1.0, RATIO_MAX)
        if self.stiffness_ratio is not None:
            check_range("supervisor.select.stiffness_ratio", self.stiffness_ratio, 1.0,
                        RATIO_MAX)

    def start(self, predicted_mm: list[float],
              predicted_stiffness_pct: list[float] | None = None) -> int:
        """The stage to start at from each stage's predicted position RMSE [mm] and stiffness
        RMSE [%] (inf: unstable or terminated on the model), in cascade order: ``POLICY``
        unless a later stage's position figure is below the policy's / ratio (and, with a
        ``stiffness_ratio``, its stiffness figure at most stiffness_ratio x the policy's), else
        the best such stage on position (the earliest of equals); each position figure raised
        to ``NOISE_FLOOR_MM`` first (below it, noise tells them apart)."""
        if len(predicted_mm) < 2:
            raise ValueError(f"predicted_mm={predicted_mm!r}: one figure per stage, at least "
                             "two stages")
        mm = np.maximum(np.asarray(predicted_mm, dtype=float), NOISE_FLOOR_MM)
        better = self.ratio * mm < mm[POLICY]
        if self.stiffness_ratio is not None:
            if predicted_stiffness_pct is None or len(predicted_stiffness_pct) != len(mm):
                raise ValueError(f"predicted_stiffness_pct={predicted_stiffness_pct!r}: "
                                 f"supervisor.select.stiffness_ratio={self.stiffness_ratio:g} "
                                 f"needs one figure per stage ({len(mm)})")
            st = np.asarray(predicted_stiffness_pct, dtype=float)
            better &= st <= self.stiffness_ratio * st[POLICY]  # inf <= inf: policy unstable
        # the policy's own entry is never better (ratio >= 1)
        if not better.any():
            return POLICY
        return int(np.argmin(np.where(better, mm, np.inf)))

    def describe(self) -> str:
        stiffness = ("" if self.stiffness_ratio is None else
                     f" on position and no more than {self.stiffness_ratio:g}x worse on "
                     "stiffness")
        return (f"the loop starts at the stage predicted best on the model (each stage's "
                f"controller alone), the policy unless another is predicted over "
                f"{self.ratio:g}x better{stiffness} (position figures below "
                f"{NOISE_FLOOR_MM:g} mm alike)")


DEFAULT_MONITORS = (Divergence(), LimitCycle(), Persistent())
DEFAULT_STAGES = (Stage("policy", ("divergence", "limit_cycle", "persistent")),
                  Stage("rc", ("divergence",), GRACE_PERIODS),
                  Stage("pid"))
# The flat section that run folders written before the cascade was declared hold: its keys and
# what an omitted one meant then (it is how those runs were evaluated; never change it).
FLAT_KEYS = {"fallback": "pid", "error_mm": 15.0, "error_window_s": 0.5, "aperiodic_mm": 3.0,
             "aperiodic_window_s": 3.0, "aperiodic_clip_mm": None, "persistent_mm": None,
             "persistent_clip_mm": None, "last_resort": None}


@dataclass(frozen=True)
class SupervisorSpec:
    """A run config's ``mpa_gym.supervisor``: the monitors and the cascade of stages (module
    docstring). The defaults are the default config's (``configs/ppo_residual.yaml``)."""

    monitors: tuple[Monitor, ...] = DEFAULT_MONITORS  # one of each kind at most
    stages: tuple[Stage, ...] = DEFAULT_STAGES  # the policy, a fallback, a last resort
    # the later stages' gains (mpa_gym.agents.controllers.gains): a gains file's path or its
    # ``gains`` mapping inline, read once into the mapping; none: the baselines' defaults
    gains: Any = None
    select: Selection | None = Selection()  # the start chosen on the model; None: the policy


    def __post_init__(self) -> None:
        object.__setattr__(self, "monitors", tuple(self.monitors))
        object.__setattr__(self, "stages", tuple(self.stages))
        object.__setattr__(self, "gains", load_gains(self.gains, "supervisor.gains"))
        if self.select is not None and not isinstance(self.select, Selection):
            raise ValueError(f"supervisor.select={self.select!r} must be a Selection or None")
        names = tuple(m.name for m in self.monitors)
        for m in self.monitors:
            if type(m) is not MONITORS.get(m.name):
                raise ValueError(f"supervisor.monitors: {m!r} is not one of {list(MONITORS)}")
        if len(set(names)) != len(names):
            raise ValueError(f"supervisor.monitors={list(names)}: each kind at most once")
        allowed = ("policy", tuple(BASELINES), tuple(BASELINES))
        if not 2 <= len(self.stages) <= len(allowed):
            raise ValueError(f"supervisor.stages has {len(self.stages)} stage(s): allowed 2 "
                             "(the policy, a fallback) or 3 (and a last resort)")
        for i, (stage, ok) in enumerate(zip(self.stages, allowed, strict=False)):
            where = f"supervisor.stages[{i}]"
            if stage.controller not in (ok if isinstance(ok, tuple) else (ok,)):
                raise ValueError(f"{where}.controller={stage.controller!r}: allowed "
                                 f"{list(ok) if isinstance(ok, tuple) else [ok]}")
            stage.check(where, names)
            last = i == len(self.stages) - 1
            if last == bool(stage.monitors):
                raise ValueError(
                    f"{where}.monitors={list(stage.monitors)!r}: the last stage drives to the "
                    "end and has none" if last else
                    f"{where}.monitors=[]: every stage but the last needs a monitor (the next "
                    "stage could never drive)")

    @property
    def fallback(self) -> str:
        """The baseline that takes over from the policy."""
        return self.stages[FALLBACK].controller

    @property
    def last_resort(self) -> str | None:
        """The baseline that takes over from the fallback (None: the fallback drives on)."""
        return self.stages[LAST_RESORT].controller if len(self.stages) > LAST_RESORT else None

    def monitor(self, name: str) -> Monitor:
        return next(m for m in self.monitors if m.name == name)

    @classmethod
    def from_config(cls, value: Any) -> SupervisorSpec:
        """The spec of a config's ``supervisor`` mapping: the declared form (``monitors``,
        ``stages``; each omitted part the default) or, with neither key, the flat form of run
        folders written before (``from_flat``). Unknown keys are refused by name."""
        if isinstance(value, cls):
            return value
        declared = ["monitors", "stages", "gains", "select"]
        if not isinstance(value, dict):
            raise ValueError(f"supervisor={value!r} must be a mapping with keys {declared} "
                             f"(or the flat form's {list(FLAT_KEYS)})")
        if not set(value) & set(declared):
            return cls.from_flat(value)
        check_keys("supervisor", value, declared,
                   note="the flat form's keys do not mix with them")
        stages = _stages(value.get("stages"))
        used = {m for s in stages for m in s.monitors}
        monitors = _monitors(value.get("monitors"))
        # the monitors the stages use (if they name none known, all: the error lists them)
        # an omitted select is the dataclass's default (a start chosen at its ratio)
        select = {"select": _selection(value["select"])} if "select" in value else {}
        return cls(tuple(m for m in monitors if m.name in used) or monitors, stages,
                   value.get("gains"), **select)

    @classmethod
    def from_flat(cls, value: dict[str, Any]) -> SupervisorSpec:
        """The cascade a flat section (``FLAT_KEYS``) meant: the policy judged on divergence
        (error_*), limit cycle (aperiodic_*) and, with persistent_mm, persistent error (over
        aperiodic_window_s); then the fallback, judged on divergence alone after
        ``GRACE_PERIODS`` when a last_resort follows it."""
        check_keys("supervisor", value, FLAT_KEYS,
                   note="or, instead of the flat form, ['monitors', 'stages']")
        f = {**FLAT_KEYS, **value}
        if f["fallback"] not in FALLBACKS:
            raise ValueError(f"supervisor.fallback={f['fallback']!r}: allowed {list(FALLBACKS)}")
        if f["last_resort"] is not None and f["last_resort"] not in LAST_RESORTS:
            raise ValueError(f"supervisor.last_resort={f['last_resort']!r}: allowed null or "
                             f"{list(LAST_RESORTS)}")
        if f["persistent_clip_mm"] is not None and f["persistent_mm"] is None:
            raise ValueError(f"supervisor.persistent_clip_mm={f['persistent_clip_mm']!r} "
                             "needs supervisor.persistent_mm")
        # monitor: its level, window and clip keys (the persistent one has no window of its
        # own), and the periods it was armed after
        flat = {Divergence: ("error_mm", "error_window_s", None, 0),
                LimitCycle: ("aperiodic_mm", "aperiodic_window_s", "aperiodic_clip_mm",
                             ARM_PERIODS),
                Persistent: ("persistent_mm", "aperiodic_window_s", "persistent_clip_mm",
                             ARM_PERIODS)}
        monitors = []
        for kind, (level, window, clip, arm) in flat.items():
            if f[level] is None:  # persistent_mm: not watched
                continue
            c = None if clip is None else f[clip]
            _check_monitor(f[level], f[window], c, arm,
                           (f"supervisor.{level}", f"supervisor.{window}", f"supervisor.{clip}",
                            "arm_periods"))
            monitors.append(kind(float(f[level]), float(f[window]),
                                 None if c is None else float(c), arm))
        if f["last_resort"] is None:
            stages = (Stage("policy", tuple(m.name for m in monitors)), Stage(f["fallback"]))
        else:
            stages = (Stage("policy", tuple(m.name for m in monitors)),
                      Stage(f["fallback"], ("divergence",), GRACE_PERIODS),
                      Stage(f["last_resort"]))
        return cls(tuple(monitors), stages, select=None)  # flat runs always started the policy

    def describe(self) -> str:
        out = ""
        for i, stage in enumerate(self.stages[:-1]):
            nxt = self.stages[i + 1].controller
            who = LAST_RESORTS.get(nxt, nxt) if i + 1 >= LAST_RESORT else nxt
            judged = " or ".join(self.monitor(m).describe() for m in stage.monitors)
            settle = (f" (given {stage.grace_periods} period(s) to settle)"
                      if stage.grace_periods else "")
            out += (f"{who} takes over once {judged}" if i == 0 else
                    f"; {who} takes over once, in {stage.controller}'s loop{settle}, {judged}")
        return out + ("" if self.select is None else "; " + self.select.describe())


def _monitors(value: Any) -> tuple[Monitor, ...]:
    """A config's ``supervisor.monitors``: name → the fields that differ from that monitor's
    defaults; every monitor not named keeps its defaults (the stages say which are used)."""
    if value is None:
        return DEFAULT_MONITORS
    if not isinstance(value, dict):
        raise ValueError(f"supervisor.monitors={value!r} must be a mapping of {list(MONITORS)} "
                         "to their fields")
    check_keys("supervisor.monitors", value, MONITORS)
    out = {m.name: m for m in DEFAULT_MONITORS}
    for name, fields in value.items():
        keys = [f.name for f in dataclasses.fields(MONITORS[name])]
        fields = {} if fields is None else fields
        if not isinstance(fields, dict):
            raise ValueError(f"supervisor.monitors.{name}={fields!r} must be a mapping with "
                             f"keys among {keys}")
        check_keys(f"supervisor.monitors.{name}", fields, keys)
        out[name] = MONITORS[name](**fields)
    return tuple(out.values())


def _selection(value: Any) -> Selection | None:
    """A config's ``supervisor.select``: null (the policy always starts) or a mapping of the
    fields that differ from ``Selection``'s defaults (omitted: the defaults)."""
    if value is None:
        return None
    keys = [f.name for f in dataclasses.fields(Selection)]
    if not isinstance(value, dict):
        raise ValueError(f"supervisor.select={value!r} must be null or a mapping with keys "
                         f"among {keys}")
    check_keys("supervisor.select", value, keys)
    return Selection(**value)


def _stages(value: Any) -> tuple[Stage, ...]:
    """A config's ``supervisor.stages``: a list of {controller, monitors, grace_periods}."""
    if value is None:
        return DEFAULT_STAGES
    keys = [f.name for f in dataclasses.fields(Stage)]
    if not isinstance(value, list):
        raise ValueError(f"supervisor.stages={value!r} must be a list of mappings with keys "
                         f"{keys}")
    out = []
    for i, stage in enumerate(value):
        if not isinstance(stage, dict) or "controller" not in stage:
            raise ValueError(f"supervisor.stages[{i}]={stage!r}: a mapping with a controller "
                             f"and keys among {keys}")
        check_keys(f"supervisor.stages[{i}]", stage, keys)
        monitors = stage.get("monitors") or []
        if not isinstance(monitors, list):
            raise ValueError(f"supervisor.stages[{i}].monitors={monitors!r} must be a list of "
                             "monitor names")
        out.append(Stage(stage["controller"], tuple(monitors), stage.get("grace_periods", 0)))
    return tuple(out)


@dataclass
class MonitorState:
    """Per row of a batch, the supervisor's episode state (arrays over n rows)."""

    stage: np.ndarray  # (n,) int: the row's place in the cascade (``POLICY``, ...)
    step: np.ndarray  # (n,) int: steps taken this episode
    since: np.ndarray  # (n,) int: the step its stage began
    mean_sq: dict[str, np.ndarray]  # monitor name → (n,) running mean of s² [m²]
    errors: np.ndarray  # (n, N) e [m] over the last N = T / dt steps, at slot step % N
    actions: np.ndarray  # (n, 2, N) the policy's last N actions (extensor, flexor), likewise

    @classmethod
    def zeros(cls, n: int, monitors: tuple[Monitor, ...], n_period: int,
              start: int | np.ndarray = 0) -> MonitorState:
        return cls(np.broadcast_to(np.asarray(start, dtype=np.int64), (n,)).copy(),
                   np.zeros(n, dtype=np.int64),
                   np.zeros(n, dtype=np.int64), {m.name: np.zeros(n) for m in monitors},
                   np.zeros((n, n_period)), np.zeros((n, 2, n_period)))

    def copy(self) -> MonitorState:
        return MonitorState(self.stage.copy(), self.step.copy(), self.since.copy(),
                            {k: v.copy() for k, v in self.mean_sq.items()},
                            self.errors.copy(), self.actions.copy())

    def restart(self, rows: np.ndarray, start: int | np.ndarray = 0) -> None:
        """A new episode on ``rows``: everything from zero, the stage ``start`` (one for every
        row, or each row's)."""
        for a in (self.step, self.since, *self.mean_sq.values(), self.errors, self.actions):
            a[rows] = 0
        self.stage[rows] = np.broadcast_to(np.asarray(start, dtype=np.int64),
                                           self.stage.shape)[rows]


class SupervisedState(NamedTuple):
    """``Supervised``'s state: the policy's, each later stage's controller's (None until it
    first drives a row) and the monitors'."""

    policy: Any
    stages: tuple[Any, ...]
    monitor: MonitorState


class Supervised:
    """``policy`` under the cascade of ``spec`` (module docstring); ``fallback`` and ``last``
    are the controllers of its later stages (``mpa_gym.agents.learned.policies.supervise`` builds
    them), ``period_s`` the reference's period T, ``dt`` the control period. The last resort must be
    the controller its stage names (it starts from that controller's rest state)."""

    def __init__(self, policy: Policy, fallback: Policy, dt: float, period_s: float,
                 spec: SupervisorSpec = SupervisorSpec(), last: Policy | None = None) -> None:
        if spec.last_resort is not None:
            cls = getattr(baselines, BASELINES[spec.last_resort])
            if type(last) is not cls:
                raise ValueError(f"supervisor.last_resort={spec.last_resort!r} needs its "
                                 f"controller {cls.__name__}, got {type(last).__name__} "
                                 "(mpa_gym.agents.learned.policies.supervise builds it)")
        self.policy, self.spec, self.dt, self.period_s = policy, spec, dt, period_s
        self.controllers = (fallback, last)[:len(spec.stages) - 1]
        self.n_period = max(1, round(period_s / dt))
        N = self.n_period
        # per stage: which of spec.monitors judge it, and the steps of grace from its start
        self.judges = np.array([[m.name in s.monitors for m in spec.monitors]
                                for s in spec.stages], dtype=bool).reshape(len(spec.stages), -1)
        self.grace_steps = np.array([s.grace_periods * N for s in spec.stages])
        # the stage every episode starts at, and what it was chosen on: ``spec.select``'s
        # choice, made by mpa_gym.agents.evaluation.select.choose_starts (``POLICY``: not made);
        # in a stack (``stack_rows``) an array, each row's
        self.start, self.predicted_mm, self.predicted_stiffness_pct = POLICY, None, None

    @classmethod
    def stack_rows(cls, supervisors: list[Supervised]) -> Supervised:
        """One supervisor for a batch whose row i is ``supervisors[i]``'s
        (``baselines.stack``): one spec, control period and reference period; its policy and
        each later stage's controller the stack of theirs, and each row started at its own
        supervisor's start (chosen on its own model, ``choose``)."""
        first = supervisors[0]
        if any(np.ndim(s.start) for s in supervisors):
            raise ValueError("stack: a stack of supervisors does not stack again")
        for s in supervisors:
            if (s.spec, s.dt, s.n_period) != (first.spec, first.dt, first.n_period):
                raise ValueError("stack: supervisors of one spec, control period and reference "
                                 "period only")
        later = [baselines.stack([s.controllers[i] for s in supervisors])
                 for i in range(len(first.controllers))]
        out = cls(baselines.stack([s.policy for s in supervisors]), later[0], first.dt,
                  first.period_s, first.spec, later[1] if len(later) > 1 else None)
        out.start = np.array([s.start for s in supervisors], dtype=np.int64)
        return out

    def choose(self, predicted_mm: list[float],
               predicted_stiffness_pct: list[float] | None = None) -> int:
        """Start every episode at the stage ``spec.select`` chooses from each stage's predicted
        position RMSE [mm] and stiffness RMSE [%] on the model (``Selection.start``); the
        policy without a select."""
        if np.ndim(self.start):
            raise ValueError("choose: a stack of supervisors starts each row where its own "
                             "supervisor chose; choose on each before stacking")
        for name, figures in (("predicted_mm", predicted_mm),
                              ("predicted_stiffness_pct", predicted_stiffness_pct)):
            if figures is not None and len(figures) != len(self.spec.stages):
                raise ValueError(f"{name}={figures!r}: one figure per stage "
                                 f"({len(self.spec.stages)})")
        self.predicted_mm = [float(v) for v in predicted_mm]
        self.predicted_stiffness_pct = (None if predicted_stiffness_pct is None else
                                        [float(v) for v in predicted_stiffness_pct])
        self.start = POLICY if self.spec.select is None else self.spec.select.start(
            self.predicted_mm, self.predicted_stiffness_pct)
        return self.start

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation, dtype=np.float64)
        single = obs.ndim == 1
        rows = obs.reshape(1, -1) if single else obs
        n, N, later = rows.shape[0], self.n_period, len(self.controllers)
        if np.ndim(self.start) and len(self.start) != n:
            raise ValueError(f"a stack of {len(self.start)} supervisors got a batch of {n} "
                             "observations; row i is supervisor i's")
        if state is None:
            state = SupervisedState(None, (None,) * later, None)
        mon = (MonitorState.zeros(n, self.spec.monitors, N, self.start)
               if state.monitor is None else state.monitor.copy())
        if episode_start is not None:
            mon.restart(np.asarray(episode_start, dtype=bool).reshape(-1), self.start)
        before, k, r = mon.stage.copy(), mon.step.copy(), np.arange(n)
        slot = k % N
        self._judge(mon, rows[:, OXR] - rows[:, OX])

        a, inner = self.policy.predict(observation, state.policy, episode_start, deterministic)
        a2 = np.atleast_2d(a)
        mon.actions[r, 0, slot], mon.actions[r, 1, slot] = a2[:, 0], a2[:, 1]
        mon.step = k + 1
        if not (mon.stage > POLICY).any():  # the later stages run only while one drives
            return a, SupervisedState(inner, (None,) * later, mon)
        out, states = a2, list(state.stages)
        for s, ctrl in enumerate(self.controllers, start=FALLBACK):
            at = mon.stage >= s
            if not at.any():
                continue
            st = states[s - 1]
            # rows it takes over: those that reached its stage this step, those whose episode
            # starts at it (from rest: chosen on the model) and every row of its first call
            rest = at & (before >= s) & (k == 0)
            fresh = at & (before < s) | rest if st is not None else at
            take_over = getattr(ctrl, "take_over", None) if s == FALLBACK else None
            if take_over is None or rest.all():  # from its rest state
                b, st = ctrl.predict(observation, st, fresh[0] if single else fresh,
                                     deterministic)
            else:  # bumpless: from the command the policy held
                handed = fresh & ~rest
                st = (take_over(rows, self.held(mon), st, handed, history=self.history(mon))
                      if handed.any() else st)
                b, st = ctrl.predict(observation, st, (rest[0] if single else rest)
                                     if rest.any() else None, deterministic)
            states[s - 1] = st
            out = np.where(at[:, None], np.atleast_2d(b), out)
        out = out.astype(np.float32)
        return (out[0] if single else out), SupervisedState(inner, tuple(states), mon)

    def _judge(self, mon: MonitorState, e: np.ndarray) -> None:
        """One step of the monitors on each row's observed error ``e`` = X̂ − X [m]: every
        monitor's running mean, ``e`` kept for a period, and the rows whose stage's monitors
        trip (past its grace) moved to the next stage, judged afresh from the next step.
        ``mon.step`` is the step being judged (the caller advances it)."""
        N, k, r = self.n_period, mon.step, np.arange(len(e))
        before, slot = mon.stage.copy(), k % N
        past = mon.errors[r, slot]  # e one period ago (zero within the first)
        age = k - mon.since  # steps into the stage
        tripped = np.zeros((len(e), len(self.spec.monitors)), dtype=bool)
        for j, m in enumerate(self.spec.monitors):
            mon.mean_sq[m.name] = m.update(mon.mean_sq[m.name], e, past,
                                           age >= m.arm_periods * N, self.dt)
            tripped[:, j] = m.tripped(mon.mean_sq[m.name])
        mon.errors[r, slot] = e
        trip = (tripped & self.judges[before]).any(axis=1) & (age >= self.grace_steps[before])
        mon.stage = before + trip  # the last stage has no monitors: it never trips
        for name in mon.mean_sq:  # the new stage's loop is judged on its own
            mon.mean_sq[name][trip] = 0.0
        mon.since[trip] = k[trip] + 1

    def first_trips(self, errors: np.ndarray) -> np.ndarray:
        """The monitors of a loop started at the policy, replayed over ``errors`` (steps, n):
        the observed error X̂ − X [m] the policy was given at each step of n episodes it drove
        alone. Per episode, the first step at which this supervisor would hand over (−1:
        never). Up to that step a supervised loop started at the policy is the policy's own,
        action for action, so it is where that loop hands over (``predict``'s monitors, the
        same code)."""
        steps, n = errors.shape
        mon = MonitorState.zeros(n, self.spec.monitors, self.n_period, POLICY)
        out = np.full(n, -1, dtype=np.int64)
        for k in range(steps):
            self._judge(mon, errors[k])
            out[(out < 0) & (mon.stage > POLICY)] = k
            mon.step += 1
            if (out >= 0).all():
                break
        return out

    def held(self, mon: MonitorState) -> np.ndarray:
        """(n, 2) per row, the mean of the policy's actions over the last reference period (or
        over the steps so far, within the first): the command the fallback takes over."""
        filled = np.minimum(mon.step, self.n_period)[:, None]
        return mon.actions.sum(axis=-1) / np.maximum(filled, 1.0)

    def history(self, mon: MonitorState) -> np.ndarray:
        """(n, 2, N) per row, the policy's actions over the last reference period in time order
        (oldest first, the newest this step's); NaN in the slots of a row younger than a
        period."""
        N = self.n_period
        order = (mon.step[:, None] + np.arange(N)[None, :]) % N  # the oldest slot first
        out = np.take_along_axis(mon.actions, np.repeat(order[:, None, :], 2, axis=1), axis=2)
        young = np.arange(N)[None, :] < N - np.minimum(mon.step, N)[:, None]
        return np.where(young[:, None, :], np.nan, out)

    @staticmethod
    def stage(state: Any) -> np.ndarray | None:
        """Per row, who drives: ``POLICY``, ``FALLBACK`` or ``LAST_RESORT`` (None before the
        first step)."""
        return None if state is None else state.monitor.stage.astype(np.int8)


def took_over(policy: Policy, state: Any) -> np.ndarray | None:
    """Per row of a batch, the supervisor's stage (``POLICY`` 0, ``FALLBACK`` 1,
    ``LAST_RESORT`` 2: non-zero where a fallback drives); None for an unsupervised policy."""
    return Supervised.stage(state) if isinstance(policy, Supervised) else None


def take_over_times(t: np.ndarray, stages: np.ndarray | None) -> dict[str, float | None]:
    """The reports' ``fallback_s`` and ``last_resort_s`` of one episode: [s] the time ``t`` of
    its first step whose stage (``took_over``'s, per step) reached the fallback, and the last
    resort; None if none did (or there are no stages: an unsupervised controller)."""
    out: dict[str, float | None] = {}
    for key, stage in HAND_OVERS:
        hit = np.array([], dtype=int) if stages is None else np.flatnonzero(
            np.asarray(stages) >= stage)
        out[key] = None if hit.size == 0 else float(t[hit[0]])
    return out


def policy_share(stages: np.ndarray | None) -> float:
    """The share of an episode's steps the learned policy drove: those whose stage (per step,
    ``took_over``'s) is ``POLICY``. 1.0 without stages (an unsupervised controller, a
    baseline: nothing took over), so every report row carries it."""
    if stages is None or np.size(stages) == 0:
        return 1.0
    return float(np.mean(np.asarray(stages) == POLICY))


def who_drove(t: np.ndarray, stages: np.ndarray | None, start: int = POLICY
              ) -> dict[str, Any]:
    """What every report row and sweep cell says of who drove one episode: ``fallback_s`` and
    ``last_resort_s`` (``take_over_times``), ``policy_share`` (:func:`policy_share`) and
    ``chosen``: the stage the episode started at (``Supervised.start``), ``"fallback"`` or
    ``"last_resort"`` where it was chosen on the model before the episode rather than handed
    the loop by a monitor, None where the policy started."""
    return {**take_over_times(t, stages), "policy_share": policy_share(stages),
            "chosen": CHOSEN.get(start)}


def handed_over(row: dict[str, Any]) -> bool:
    """Whether a monitor handed the row's loop from the policy to a fallback (not a fallback
    chosen on the model before the episode: :func:`who_drove`'s ``chosen``)."""
    return row.get("fallback_s") is not None and row.get("chosen") is None


def hand_overs(row: dict[str, Any], stages: list[str] | None = None) -> str:
    """What a report row (:func:`who_drove`'s keys) says of the controllers that drove besides
    the policy, e.g. ``pid from 9.5 s, afc from 12.0 s; policy 79 % of steps`` or ``rc chosen
    on the model; policy 0 % of steps`` (``stages``: the supervisor's controllers in cascade
    order; without them ``fallback`` / ``last_resort``); ``""`` where nothing took over."""
    took, first = [], row.get("chosen")
    for key, i in HAND_OVERS:
        if row.get(key) is None:  # (a two-stage cascade has no last resort)
            continue
        name = stages[i] if stages else CHOSEN[i]
        if first == CHOSEN[i]:
            took.append(f"{name} chosen on the model")
        elif not (first == CHOSEN[LAST_RESORT] and i == FALLBACK):
            took.append(f"{name} from {row[key]:.1f} s")
    if not took:
        return ""
    return ", ".join(took) + f"; policy {row.get('policy_share', 1.0) * 100:.0f} % of steps"
