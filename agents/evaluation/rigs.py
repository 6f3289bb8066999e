"""Random real-rig plants: ``mpa-gym evaluate --random-rigs N [--rigs-seed S]``.

The robustness sweep scores fixed cells, and a supervisor or a policy chosen on them can be
good there and nowhere else. Here every controller runs on ``N`` plants drawn at random from
``configs/rigs/random.yaml`` (its ranges reach beyond the default training plants; the file
says how), each with a reference period drawn from ``PERIOD_S``, one episode of the file's
``duration_s`` per rig and controller (the rig's number ``i`` is its episode seed's offset, so
a rig is the same plant and noise for every controller). Per rig and controller, over the last
three reference periods as in the sweep (``robustness.cell_metrics``): ``position_rmse_mm``,
``stiffness_rmse_pct``, ``unstable`` and who drove. A terminated or unstable episode counts as
infinitely bad on both below.

The audit, for each learned run (``ratio`` = ``RIG_RATIO``, every bound raised to
``robustness.HARM_FLOOR_MM``, below which sensor noise decides):

- ``alone_within_pid``: the share of rigs on which the policy alone tracks within ratio × pid;
- ``supervised_within``: the share of rigs on which the supervised loop tracks within ratio ×
  the better of the policy alone and the best classical baseline evaluated (``CLASSICAL``), the
  rigs that break it listed: a supervisor that hands a good loop to a worse fallback shows
  here, and so does one that keeps a failing policy;
- ``supervised_undominated``: the share of rigs on which none of those references both tracks
  position over ratio × better than the supervised loop and tracks stiffness within ratio ×
  its error (the residual task tracks both), the rigs where one does listed (``dominated``):
  a supervisor that keeps its policy where a baseline is better on position but over ratio ×
  worse on stiffness passes this and not the position-only share;
- ``hand_overs``: the rigs on which a monitor handed the loop to the supervisor's fallback;
- ``chosen``: the rigs on which a fallback drove from the start, chosen on the rig's model
  (``mpa_gym.agents.evaluation.select``; the model is the rig's plant, as ``mpa-gym identify``
  would write it, as the delays a policy is told are).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from mpa_gym.agents.controllers.gains import Gains
from mpa_gym.agents.controllers.supervisor import handed_over
from mpa_gym.agents.evaluation.episodes import (
    Job,
    eval_task,
    run_episodes,
    score_mm,
    score_stiffness_pct,
    stack_jobs,
    trace_metrics,
)
from mpa_gym.agents.evaluation.robustness import HARM_FLOOR_MM
from mpa_gym.agents.evaluation.select import choose_starts
from mpa_gym.agents.learned.config import EVAL_SEED
from mpa_gym.agents.learned.policies import (
    ALONE,
    has_supervisor,
    load_for_plant,
    load_policy,
    loads_per_scenario,
    selects,
    spec_label,
    with_alone,
)
from mpa_gym.analysis.scenario import Randomization, load_scenario
from mpa_gym.configs import RIG_DIR

RIGS_FILE = RIG_DIR / "random.yaml"
RIGS_SEED = 3 * EVAL_SEED  # plant draws: beyond training, evaluation and calibration (2e6)
PERIOD_S = (2.0, 4.0)  # [s] each rig's reference period is drawn from this range,
PERIOD_STEP_S = 0.01  # rounded to this (a whole number of 100 Hz steps: rc's delay line)
RIG_RATIO = 1.2
MAX_RIGS = 10_000  # ~0.3 s per rig and controller: about an hour per controller at the most
CLASSICAL = ("pid", "mbfb", "afc", "rc")  # the classical baselines a supervised loop is held to


def draw(n: int, seed: int = RIGS_SEED) -> list[tuple[float, dict[str, float]]]:
    """``n`` rigs: (reference period [s], per-leg plant fields drawn from ``RIGS_FILE``)."""
    rnd = load_scenario(RIGS_FILE).randomize
    rng = np.random.default_rng(seed)
    return [(round(float(rng.uniform(*PERIOD_S)) / PERIOD_STEP_S) * PERIOD_STEP_S,
             rnd.sample(rng)) for _ in range(n)]


def random_rigs(policies: list[str], n: int, seed: int = RIGS_SEED, episode_seed: int = 0,
                gains: Gains | None = None) -> dict[str, Any]:
    """Every controller of ``policies`` (a supervised run folder also alone) on ``n`` random
    rigs, as one batch, and the audit (module docstring)."""
    if not 1 <= n <= MAX_RIGS:
        raise ValueError(f"--random-rigs={n} must be in [1, {MAX_RIGS}]")
    policies = with_alone(policies)
    base = load_scenario(RIGS_FILE)
    rigs = draw(n, seed)
    scenarios = [dataclasses.replace(
        base, name=f"rig{i:02d}", randomize=Randomization(),
        reference=dataclasses.replace(base.reference, period=period))
        for i, (period, _) in enumerate(rigs)]
    # a supervised run is loaded for each rig (its monitors and fallbacks follow the rig's
    # reference period), a policy that observes delays told the rig's (loads_per_scenario)
    learned = {p: load_policy(p) for p in policies if not loads_per_scenario(p)}
    choosing = {p for p in policies if selects(p)}  # read each run's config once
    jobs, chosen = [], []
    for i, (sc, (_, plant)) in enumerate(zip(scenarios, rigs, strict=True)):
        for p in policies:
            one = learned[p] if p in learned else load_for_plant(p, sc, plant, gains)
            if p in choosing:
                chosen.append((one, sc, plant))
            policy, env_id, cfg = one
            jobs.append(Job(sc, policy, env_id, eval_task(cfg), plant=plant,
                            seed=episode_seed + i))
    # a supervisor's start, chosen on each rig's model (its plant, as identify would write it)
    if chosen:
        choose_starts([c[0] for c in chosen], [c[1] for c in chosen], [c[2] for c in chosen])
    # each controller's rigs as one stack where it stacks (not a supervisor: its monitors
    # hold one reference period, and the rigs' differ)
    jobs = stack_jobs(jobs, [list(range(k, len(jobs), len(policies)))
                             for k in range(len(policies))])
    traces = run_episodes(jobs, episode_seed)
    labels = [spec_label(p) for p in policies]
    per_rig = []
    for i, (period, plant) in enumerate(rigs):
        row = {}
        for k, label in enumerate(labels):
            row[label] = trace_metrics(traces[i * len(policies) + k], period)
        per_rig.append({"rig": i, "period_s": period, "plant": plant, "controllers": row})
    out: dict[str, Any] = {"n": n, "seed": seed, "episode_seed": episode_seed,
                           "file": RIGS_FILE.name, "period_s": list(PERIOD_S),
                           "ratio": RIG_RATIO, "floor_mm": HARM_FLOOR_MM, "rigs": per_rig}
    out["median_mm"] = {lab: _median([r["controllers"][lab] for r in per_rig], score_mm)
                        for lab in labels}
    out["median_stiffness_pct"] = {lab: _median([r["controllers"][lab] for r in per_rig],
                                                score_stiffness_pct) for lab in labels}
    out["unstable"] = {lab: sum(r["controllers"][lab]["unstable"] for r in per_rig)
                       for lab in labels}
    out["audit"] = {spec_label(p): _audit(per_rig, spec_label(p), spec_label(p + ALONE),
                                          labels) for p in policies if has_supervisor(p)}
    return out


def _median(ms: list[dict[str, Any]], score: Callable[[dict[str, Any]], float]
            ) -> float | None:
    v = float(np.median([score(m) for m in ms]))
    return None if math.isinf(v) else v


def _within(x: float, ref: float) -> bool:
    return x <= max(RIG_RATIO * ref, HARM_FLOOR_MM)


def _audit(per_rig: list[dict[str, Any]], supervised: str, alone: str, labels: list[str]
           ) -> dict[str, Any]:
    classical = [c for c in CLASSICAL if c in labels]
    broken, dominated, near_pid, hand_overs, chosen = [], [], 0, [], []
    for r in per_rig:
        c = r["controllers"]
        best = min([score_mm(c[alone])] + [score_mm(c[b]) for b in classical])
        mm, pct = score_mm(c[supervised]), score_stiffness_pct(c[supervised])
        if not _within(mm, best):
            broken.append({"rig": r["rig"], "supervised_mm": _finite(mm),
                           "alone_mm": _finite(score_mm(c[alone])), "best_mm": _finite(best)})
        # the references better on position that are not worse on stiffness (inf <= inf: the
        # supervised loop unstable tracks no stiffness)
        over = [b for b in [alone, *classical] if not _within(mm, score_mm(c[b]))
                and score_stiffness_pct(c[b]) <= RIG_RATIO * pct]
        if over:
            dominated.append({"rig": r["rig"], "supervised_mm": _finite(mm),
                              "supervised_pct": _finite(pct), "by": {
                                  b: [score_mm(c[b]), _finite(score_stiffness_pct(c[b]))]
                                  for b in over}})
        if "pid" in c:
            near_pid += _within(score_mm(c[alone]), score_mm(c["pid"]))
        if handed_over(c[supervised]):
            hand_overs.append(r["rig"])
        if c[supervised].get("chosen") is not None:
            chosen.append(r["rig"])
    n = len(per_rig)
    return {"alone": alone, "classical": classical,
            "alone_within_pid": near_pid / n if "pid" in labels else None,
            "supervised_within": (n - len(broken)) / n, "broken": broken,
            "supervised_undominated": (n - len(dominated)) / n, "dominated": dominated,
            "hand_overs": hand_overs, "chosen": chosen}


def _finite(v: float) -> float | None:
    return None if math.isinf(v) else v


def markdown(rr: dict[str, Any]) -> list[str]:
    """The random rigs' section of the Markdown report."""
    labels = list(rr["rigs"][0]["controllers"])
    out = ["## Random rigs", "",
           f"{rr['n']} plants drawn from `configs/rigs/{rr['file']}` (seed {rr['seed']}), "
           f"reference periods {rr['period_s'][0]:g}–{rr['period_s'][1]:g} s: position RMSE "
           "[mm] and stiffness RMSE [%] over the last three periods; **unstable** as in the "
           "sweep; ‡: the supervisor's fallback took over. Audit: the supervised loop within "
           f"{rr['ratio']:g}× the better of the policy alone and the best classical baseline, "
           f"the policy alone within {rr['ratio']:g}× pid (bounds raised to "
           f"{rr['floor_mm']:g} mm); undominated: no such reference over {rr['ratio']:g}× "
           f"better on position and within {rr['ratio']:g}× on stiffness.", ""]
    for ctrl, a in rr["audit"].items():
        pid = ("" if a["alone_within_pid"] is None else
               f"; {a['alone']} within {rr['ratio']:g}× pid on {a['alone_within_pid']:.0%}")
        out.append(f"**{ctrl}**: supervised within {rr['ratio']:g}× the better of "
                   f"{a['alone']} and {', '.join(a['classical']) or 'no baseline'} on "
                   f"{a['supervised_within']:.0%} of the rigs, undominated on "
                   f"{a['supervised_undominated']:.0%}{pid}; hand-overs on "
                   f"{len(a['hand_overs'])} rigs"
                   + (f" (rigs {', '.join(map(str, a['hand_overs']))})" if a["hand_overs"]
                      else "")
                   + (f"; a fallback chosen on the rig's model drove rigs "
                      f"{', '.join(map(str, a['chosen']))}" if a.get("chosen") else "") + ".")
    out += ["", "| | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels),
            "| median | " + " | ".join(_mm(rr["median_mm"][lab]) for lab in labels) + " |",
            "| median stiffness [%] | " + " | ".join(
                _mm(rr["median_stiffness_pct"][lab], ".2f") for lab in labels) + " |",
            "| unstable | " + " | ".join(str(rr["unstable"][lab]) for lab in labels) + " |", "",
            "| rig | period [s] | plant | " + " | ".join(labels) + " |",
            "|---|---|---|" + "---|" * len(labels)]
    for r in rr["rigs"]:
        plant = ", ".join(f"{k} {v:.3g}" for k, v in r["plant"].items())
        cells = []
        for lab in labels:
            m = r["controllers"][lab]
            cell = ("terminated" if m["terminated"] else f"{m['position_rmse_mm']:.3f}"
                    + (" **unstable**" if m["unstable"] else
                       f" · {m['stiffness_rmse_pct']:.1f} %"))
            cells.append(cell + ("" if m.get("fallback_s") is None else
                                 f" ‡{m['chosen'].replace('_', ' ')} chosen"
                                 if m.get("chosen") else f" ‡{m['fallback_s']:.1f} s"))
        out.append(f"| {r['rig']} | {r['period_s']:.2f} | {plant} | " + " | ".join(cells) + " |")
    return [*out, ""]


def _mm(v: float | None, fmt: str = ".3f") -> str:
    return "–" if v is None else f"{v:{fmt}}"

