"""Run-time assurance for a learned residual: a fallback controller takes over when it fails.

The Simplex architecture (Sha, "Using simplicity to control complexity", IEEE Software 2001;
run-time assurance in the safe-RL literature): a high-performance controller that cannot be
verified runs beside a simple one that can, and a monitor hands control to the simple one when
the loop leaves the region where the first is known to behave. Here the learned residual is the
high-performance controller and a tuned baseline (``pid``: stable on every cell of the
robustness grids up to 30 ms of regulator dead time) the fallback. The monitor watches the
tracking error e = X̂ − X for the three ways a destabilised loop shows itself:

- a divergence: the running RMS of e over ``error_window_s``,
  z_t = z_{t−1} + α (e_t² − z_{t−1}), α = dt / (window + dt), above ``error_mm``;
- a persistent error (with ``persistent_mm``): the running RMS of e itself over
  ``aperiodic_window_s``, each sample clipped to ±``persistent_clip_mm``, from the third
  period on, for the residual alone. Under 20 ms of dead time and a 30 ms lag a policy can
  settle onto a periodic error of several mm. Its change over a period is zero, so the
  limit-cycle monitor cannot see it, and it stays under the divergence level. The clip keeps a
  kick's centimetres from counting for more than c² over their few tenths of a second.
- a limit cycle: the running RMS (over ``aperiodic_window_s``) of e_t − e_{t−T}, the error's
  change over one reference period T, above ``aperiodic_mm``, from the third period on. A
  stable loop settles onto a motion with the reference's period (a sag under a load, a phase
  lag), which cancels in the difference; an oscillation at another frequency does not (for an
  aperiodic part r of RMS ρ, e_t − e_{t−T} has RMS ≈ √2 ρ). This is the robustness sweep's
  "unstable" criterion (``mpa_gym.agents.evaluation.robustness``) made causal. The first two periods are left out
  because the difference would compare the settled loop with its start-up transient. With
  ``aperiodic_clip_mm`` c each sample of e_t − e_{t−T} is clipped to ±c before it is squared
  (winsorised): a kick's transient, centimetres for a few tenths of a second (and seen again
  one period later), then adds at most c² for its length to a mean over seconds, while an
  oscillation whose change stays within ±c is measured exactly as without the clip, and a
  larger one still reaches c² ≥ the level². Without it, the one statistic could not tell a
  kick the policy recovers from in 0.4 s from a limit cycle, and a 30 N kick on a heavy leg
  handed the loop to the fallback for good.

Once either level is crossed, the fallback drives the rest of the episode (the latch never hands
back: a residual that destabilised this plant once does it again). A feedback fallback can fail
too: beyond ~30 ms of dead time the tuned pid limit-cycles on its own. With a ``last_resort``
the error monitor restarts from zero when the fallback takes over and, if the fallback's loop
diverges as well after one period to settle (pid's own limit cycle at 40 ms of dead time on the
unloaded leg reaches 22 mm RMS), the last resort drives the rest of the episode, from its rest
state: ``ff``, the feedforward alone (a zero residual: Eq. 16 open loop, which has no feedback
for a delay to destabilise), or ``afc``, the feedforward with adaptive feedforward cancellation
(``mpa_gym.agents.controllers.baselines.AdaptiveFeedforward``). That controller starts as the feedforward and learns
the periodic command it lacks, acting at the reference's frequency alone, where 40 ms of delay
is a phase of 5°. Handed to ``ff``, the unloaded leg's loop at 40 ms ended 0.001-0.003 mm above
the feedforward alone on four seeds of five. The excursion pid's divergence leaves decays by
~5.5× a period, open loop, and the difference was still in the metric's window. Handed to
``afc``, the same loops end at 0.48-0.77 mm, against 2.07 mm for the feedforward alone.

The fallback's loop is judged on divergence only: after a hand-over it settles from the policy's
oscillation, and where it is near its own stability margin (30 ms on the unloaded leg, 40 ms
with 0.5 kg) that transient crossed the 2 mm limit-cycle level of the default config and handed
a loop pid holds (0.47 and 0.73 mm) to the feedforward (1.8 and 10.6 mm); so, with no grace
period, did the divergence level. The period of grace was set on the default config's policy in
the sweep's 40 ms row (beyond its training range): with half a period the unloaded leg's loop
ended 4e-6 mm above the feedforward alone (the last resort was ``ff`` then; the no-harm audit's
bound is strict); with two periods it left its bounds under pid before the feedforward took
over. The grace was set with ``ff`` as the last resort and kept for ``afc``: the loops it hands
over are the same (no other cell of either grid reaches the last resort).

The fallback is not run until the first trip. It takes over bumplessly (Åström & Hägglund,
"Advanced PID control", 2006, § 3.5): a fallback with a ``take_over(observation, held, state,
rows)`` method (both baselines) starts its integrator from the command the policy held, so the
load the policy was carrying stays carried; one without it starts from zero state. The command
held is the mean of the policy's actions over the last reference period (its DC part: a periodic
loop's corrections at the reference frequency and its harmonics cancel in it, and so, to first
order, does the oscillation that tripped the monitor), not the last action, which would carry
the oscillation's instantaneous value into the integrator. Without it, pid restarted from zero
on a leg carrying 1.6 kg took 5.5 s to recover (|e| < 1 mm) after a kick, against 2.2 s for pid
alone.

Calibration of the default config's levels (``configs/ppo_residual.yaml``; ``mpa-gym
evaluate`` of five seeds of its policy beside the baselines; the sweep's cells, held-out ones
included). The policy's failures under regulator dead time: a chatter whose change over a
period has 0.4-0.5 mm RMS under 10 ms (pid holds 0.29-0.46 mm there), limit cycles of several
mm under 20-40 ms, a periodic error of 2.8 mm on one seed under 20 ms with +0.5 kg, and loops
that leave the leg's bounds, which pass 15 mm within their first second. Its healthy loops: a
change of 0.05-0.16 mm RMS on the kicked levels once the kick has passed, an error of 0.9 mm
RMS or less (the medium level). Hence 0.4 mm for the change, its samples clipped to ±0.5 mm,
2 mm for the error, clipped to ±3 mm, and 15 mm for a divergence. With these, no named or
held-out scenario trips (but the impulse on one seed of five, where pid then tracks to
0.001 mm), the 30 N × 50 ms kick on the 1.6 kg leg stays the policy's on every seed (it
recovers in 0.46-0.84 s, pid alone in 2.2 s), and the kicked easy or medium level goes to pid
on one or two seeds of five. A higher level lets the chatter run on (at 1 mm clipped at 1.5 mm:
10 no-harm breaches of 285 against 4, with ``ff`` as the last resort; the 4 were the 40 ms
cell, and none remain with ``afc``); without the clip, a level this low hands every kick
over. A trip on a healthy loop costs tracking quality (the fallback's instead of the policy's),
never stability where the fallback is stable.

``Supervised`` has the ``predict`` of every controller, so evaluation, the robustness sweep and
rig rollouts run it unchanged; ``took_over(policy, state)`` gives each row's stage (the policy,
the fallback or the last resort), and the reports give the times the fallback and the last
resort took over, so a figure never hides which controller earned it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from mpa_gym.agents.controllers.baselines import BASELINES, Policy

from mpa_gym.model.params import check_range
from mpa_gym.task.contract import OBS_X as OX
from mpa_gym.task.contract import OBS_XREF as OXR

FALLBACKS = ("pid", "mbfb")
# the last resorts (mpa_gym.agents.controllers.baselines names) and what ``describe`` calls them
LAST_RESORTS = {"ff": "ff alone",
                "afc": "afc (the feedforward with adaptive feedforward cancellation)"}
ARM_PERIODS = 2  # periods left out of the limit-cycle monitor (module docstring)
GRACE_PERIODS = 1  # periods the fallback's loop has to settle before it is judged
POLICY, FALLBACK, LAST_RESORT = 0, 1, 2  # the stages: who drives
# the monitor's columns per row (``Supervised``): the two running means, the stage, the steps
# taken, the step the stage began; then the ring buffers
M_ERR, M_AP, M_STAGE, M_STEP, M_SINCE, M_PER = range(6)
M_RING = 6


@dataclass(frozen=True)
class SupervisorSpec:
    """A run config's ``mpa_gym.supervisor`` (its keys; module docstring)."""

    fallback: str = "pid"  # the baseline that takes over
    error_mm: float = 15.0  # [mm] running RMS of X̂ − X above which it takes over
    error_window_s: float = 0.5  # [s] time constant of that running mean
    aperiodic_mm: float = 3.0  # [mm] running RMS of e_t − e_{t−T} above which it takes over
    aperiodic_window_s: float = 3.0  # [s] time constant of that running mean
    aperiodic_clip_mm: float | None = None  # [mm] e_t − e_{t−T} clipped to ± this (None: not)
    # [mm] running RMS (over aperiodic_window_s, from the third period on) of e itself, each
    # sample clipped to ±persistent_clip_mm, above which it takes over (None: not watched)
    persistent_mm: float | None = None
    persistent_clip_mm: float | None = None  # [mm] (None: not clipped)
    # once the fallback trips too: "ff", the feedforward alone; "afc", with adaptive
    # feedforward cancellation (mpa_gym.agents.controllers.baselines.AdaptiveFeedforward)
    last_resort: str | None = None

    def __post_init__(self) -> None:
        if self.fallback not in FALLBACKS:
            raise ValueError(f"supervisor.fallback={self.fallback!r}: allowed {list(FALLBACKS)}")
        if self.last_resort is not None and self.last_resort not in LAST_RESORTS:
            raise ValueError(f"supervisor.last_resort={self.last_resort!r}: allowed null or "
                             f"{list(LAST_RESORTS)}")
        for key, hi, unit in (("error_mm", 100.0, "mm"), ("error_window_s", 30.0, "s"),
                              ("aperiodic_mm", 100.0, "mm"), ("aperiodic_window_s", 30.0, "s")):
            check_range(f"supervisor.{key}", getattr(self, key), 0.0, hi, low_open=True,
                        unit=unit)
        if self.aperiodic_clip_mm is not None:  # below the level, the monitor could never trip
            check_range("supervisor.aperiodic_clip_mm", self.aperiodic_clip_mm,
                        self.aperiodic_mm, 100.0, low_open=True, unit="mm")
        if self.persistent_mm is not None:
            check_range("supervisor.persistent_mm", self.persistent_mm, 0.0, 100.0,
                        low_open=True, unit="mm")
        if self.persistent_clip_mm is not None:
            if self.persistent_mm is None:
                raise ValueError(f"supervisor.persistent_clip_mm={self.persistent_clip_mm!r} "
                                 "needs supervisor.persistent_mm")
            check_range("supervisor.persistent_clip_mm", self.persistent_clip_mm,
                        self.persistent_mm, 100.0, low_open=True, unit="mm")

    @classmethod
    def from_config(cls, value: Any) -> SupervisorSpec:
        """The spec of a config's ``supervisor`` mapping (unknown keys refused by name)."""
        if isinstance(value, cls):
            return value
        keys = [f.name for f in dataclasses.fields(cls)]
        if not isinstance(value, dict):
            raise ValueError(f"supervisor={value!r} must be a mapping with keys {keys}")
        unknown = sorted(set(value) - set(keys), key=str)
        if unknown:
            raise ValueError(f"supervisor: unknown key(s) {unknown}; allowed keys are {keys}")
        return cls(**value)

    def describe(self) -> str:
        out = (f"{self.fallback} takes over once the error's RMS over {self.error_window_s:g} s "
               f"exceeds {self.error_mm:g} mm or, after {ARM_PERIODS} periods, the RMS of its "
               f"change over one period (over {self.aperiodic_window_s:g} s"
               + (f", each sample clipped to ±{self.aperiodic_clip_mm:g} mm"
                  if self.aperiodic_clip_mm is not None else "")
               + f") exceeds {self.aperiodic_mm:g} mm")
        if self.persistent_mm is not None:
            out += (f" or, after {ARM_PERIODS} periods, the error's own RMS over "
                    f"{self.aperiodic_window_s:g} s"
                    + (f" (each sample clipped to ±{self.persistent_clip_mm:g} mm)"
                       if self.persistent_clip_mm is not None else "")
                    + f" exceeds {self.persistent_mm:g} mm")
        if self.last_resort:
            out += (f"; {LAST_RESORTS[self.last_resort]} once {self.fallback}'s loop, given "
                    f"{GRACE_PERIODS} period(s) to settle, passes {self.error_mm:g} mm too")
        return out


class Supervised:
    """``policy`` until the monitor trips, then ``fallback`` for the rest of the episode
    (module docstring); ``period_s`` is the reference's period T, ``dt`` the control period.
    With ``spec.last_resort``, the error monitor restarts when the fallback takes over and, if
    the fallback's loop diverges too (after ``GRACE_PERIODS`` to settle), ``last`` (the
    controller ``spec.last_resort`` names) drives the rest of the episode from its rest state.

    State: (policy's, fallback's, monitor, last resort's) with the monitor an (n, 6 + 3N) array
    per row: the ``M_*`` columns (running mean of e², running mean of (e_t − e_{t−T})², the
    stage, the steps taken, the step the stage began, running mean of the clipped e²), then ring
    buffers of the last N = T / dt errors and of the policy's last N actions (extensor's, then
    flexor's)."""

    def __init__(self, policy: Policy, fallback: Policy, dt: float, period_s: float,
                 spec: SupervisorSpec = SupervisorSpec(), last: Policy | None = None) -> None:
        if spec.last_resort is not None and (
                last is None or type(last).__name__ != BASELINES[spec.last_resort]):
            raise ValueError(f"supervisor.last_resort={spec.last_resort!r} needs its controller "
                             f"{BASELINES[spec.last_resort]}, got {type(last).__name__} "
                             "(mpa_gym.agents.learned.policies.supervise builds it)")
        self.policy, self.fallback, self.last, self.spec = policy, fallback, last, spec
        self.n_period = max(1, round(period_s / dt))
        self.a_err = dt / (spec.error_window_s + dt)
        self.a_ap = dt / (spec.aperiodic_window_s + dt)
        self.clip = np.inf if spec.aperiodic_clip_mm is None else spec.aperiodic_clip_mm * 1e-3
        self.persistent = np.inf if spec.persistent_mm is None else spec.persistent_mm * 1e-3
        self.per_clip = (np.inf if spec.persistent_clip_mm is None
                         else spec.persistent_clip_mm * 1e-3)

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation, dtype=np.float64)
        single = obs.ndim == 1
        rows = obs.reshape(1, -1) if single else obs
        n, N = rows.shape[0], self.n_period
        inner, fb, mon, lr = (None, None, None, None) if state is None else state
        mon = np.zeros((n, M_RING + 3 * N)) if mon is None else np.array(mon, dtype=float)
        if episode_start is not None:
            mon[np.asarray(episode_start, dtype=bool).reshape(-1)] = 0.0
        stage_before = mon[:, M_STAGE].copy()
        e = rows[:, OXR] - rows[:, OX]
        k = mon[:, M_STEP].astype(np.int64)
        slot = M_RING + k % N
        past = mon[np.arange(n), slot]  # e one period ago (once k >= N)
        mon[:, M_ERR] += self.a_err * (e**2 - mon[:, M_ERR])
        armed = k - mon[:, M_SINCE] >= ARM_PERIODS * N  # two periods into the stage
        change = np.clip(e - past, -self.clip, self.clip)
        mon[:, M_AP] += np.where(armed, self.a_ap * (change**2 - mon[:, M_AP]), 0.0)
        held_e = np.clip(e, -self.per_clip, self.per_clip)
        mon[:, M_PER] += np.where(armed, self.a_ap * (held_e**2 - mon[:, M_PER]), 0.0)
        mon[np.arange(n), slot] = e
        # the fallback's loop is judged on divergence alone: after a hand-over it settles from
        # the policy's oscillation, slowly where it is near its own margin (module docstring)
        grace = (stage_before > 0.0) & (k - mon[:, M_SINCE] < GRACE_PERIODS * N)
        trip = (((np.sqrt(mon[:, M_ERR]) > self.spec.error_mm * 1e-3) & ~grace)
                | (((np.sqrt(mon[:, M_AP]) > self.spec.aperiodic_mm * 1e-3)
                    | (np.sqrt(mon[:, M_PER]) > self.persistent))
                   & (stage_before == 0.0)))
        last = LAST_RESORT if self.spec.last_resort else FALLBACK
        mon[:, M_STAGE] = np.where(trip, np.minimum(stage_before + 1.0, last), stage_before)
        if self.spec.last_resort:  # each stage is judged on its own loop: the monitor restarts
            moved = (mon[:, M_STAGE] > stage_before) & (mon[:, M_STAGE] < last)
            mon[moved, M_ERR] = mon[moved, M_AP] = mon[moved, M_PER] = 0.0
            mon[moved, M_SINCE] = k[moved] + 1
        driving = mon[:, M_STAGE] > 0.0
        a, inner = self.policy.predict(observation, inner, episode_start, deterministic)
        a2 = np.atleast_2d(a)
        mon[np.arange(n), slot + N] = a2[:, 0]
        mon[np.arange(n), slot + 2 * N] = a2[:, 1]
        mon[:, M_STEP] += 1
        if not driving.any():  # the fallback runs only once it drives
            return a, (inner, None, mon, None)
        new = driving & ~(stage_before > 0.0) if fb is not None else driving
        take_over = getattr(self.fallback, "take_over", None)
        if take_over is None:  # no bumpless transfer: from zero state
            b, fb = self.fallback.predict(observation, fb, new[0] if single else new,
                                          deterministic)
        else:
            fb = take_over(rows, self.held(mon), fb, new) if new.any() else fb
            b, fb = self.fallback.predict(observation, fb, None, deterministic)
        out = np.where(driving[:, None], np.atleast_2d(b), a2)
        resort = mon[:, M_STAGE] >= LAST_RESORT
        if resort.any():  # the last resort, from its rest state on the rows it takes over
            fresh = resort & (stage_before < LAST_RESORT)
            c, lr = self.last.predict(observation, lr, fresh[0] if single else fresh,
                                      deterministic)
            out[resort] = np.atleast_2d(c)[resort]
        out = out.astype(np.float32)
        return (out[0] if single else out), (inner, fb, mon, lr)

    def held(self, mon: np.ndarray) -> np.ndarray:
        """(n, 2) per row, the mean of the policy's actions over the last reference period (or
        over the steps so far, within the first): the command the fallback takes over."""
        N, r = self.n_period, M_RING
        filled = np.minimum(mon[:, M_STEP], N)[:, None]
        return np.stack([mon[:, r + N:r + 2 * N].sum(axis=1),
                         mon[:, r + 2 * N:].sum(axis=1)], axis=-1) / np.maximum(filled, 1.0)

    @staticmethod
    def stage(state: Any) -> np.ndarray | None:
        """Per row, who drives: ``POLICY``, ``FALLBACK`` or ``LAST_RESORT`` (None before the
        first step)."""
        return None if state is None else np.asarray(state[2])[:, M_STAGE].astype(np.int8)


def took_over(policy: Policy, state: Any) -> np.ndarray | None:
    """Per row of a batch, the supervisor's stage (``POLICY`` 0, ``FALLBACK`` 1,
    ``LAST_RESORT`` 2: non-zero where a fallback drives); None for an unsupervised policy."""
    return Supervised.stage(state) if isinstance(policy, Supervised) else None


def take_over_times(t: np.ndarray, stages: np.ndarray | None) -> dict[str, float | None]:
    """The reports' ``fallback_s`` and ``last_resort_s`` of one episode: [s] the time ``t`` of
    its first step whose stage (``took_over``'s, per step) reached the fallback, and the last
    resort; None if none did (or there are no stages: an unsupervised controller)."""
    out: dict[str, float | None] = {}
    for key, stage in (("fallback_s", FALLBACK), ("last_resort_s", LAST_RESORT)):
        hit = np.array([], dtype=int) if stages is None else np.flatnonzero(
            np.asarray(stages) >= stage)
        out[key] = None if hit.size == 0 else float(t[hit[0]])
    return out
