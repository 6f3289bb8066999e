"""Coverage of identification's intervals over random emulated rigs:
``mpa-gym identify --coverage N [--seed S] [--episode-s S] [--jobs J] [--coverage-dir DIR]``.

Each of N rigs is a plant drawn at random from ``configs/rigs/coverage.yaml``'s ranges (the
default training config's as the intervals were validated on, dead times to 30 ms: the file says
why), with their ``p_off`` coins, so an effect is absent in about half the rigs; they hold
``configs/rigs/offnominal.yaml``'s values, and the rigs have the encoder noise of that rig. For
each rig, as on a real one: the device emulator plays it in its own process (``mpa-gym emulate
--udp``), the excitation drives it in real time over the link (``excite_rollout``: ``mpa-gym
rollout --policy excite``), ``mpa-gym identify --out`` fits the log and writes a scenario. Each
step is a subprocess (``PYTHONPATH`` chooses the code under test), so a rig whose rollout or fit
fails is counted and the run goes on.

What is scored is the written scenario, i.e. what training on the identified rig draws from: a
plant key is covered when the truth lies in its ``randomize`` range (a range with ``p_off`` also
holds the value the scenario keeps when it leaves the key out: its ``plant`` value), or equals
its ``plant`` value when the key is not randomised. The truth of C1 and C2 is their value at the
nominal bladder thickness (``identify`` keeps the thickness nominal: the model's rubber term is
V_r(t)·C1, V_r(t)·C2, so a rig of thickness t is the same plant as one of nominal thickness with
C1, C2 scaled by V_r(t)/V_r(t_nominal)); the truth of the mass is the total (m + load).

A rollout the rig's safety stops (a loaded machine's late telemetry) is repeated, up to twice,
on a fresh emulator and log. Each rig's record (truth, fit, score) is appended to
``DIR/coverage.jsonl`` as it finishes, so a kill loses only the rigs in flight.
"""

from __future__ import annotations

import functools
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from mpa_gym.agents.rig import rollout as ro
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.configs import RIG_DIR
from mpa_gym.hardware.emulator import EmulatorProcess
from mpa_gym.model.params import DEFAULT_PARAMS, check_range

# the plant keys scored, in the order printed; "mass_kg" is the total mass
SCORED = ("mass_kg", "gamma_Ns_per_m", "C1_Pa", "C2_Pa", "pressure_lag_s",
          "pressure_dead_time_s", "pressure_slew_bar_per_s", "braid_friction_ratio",
          "slider_friction_N", "slider_viscous_Ns_per_m")
ATTEMPTS = 3  # rollouts per rig (a stopped one is repeated on a fresh emulator)
WATCHDOG_S = 0.5  # [s] the emulator's vent watchdog (tests/test_identify.py's, for a loaded PC)
STALE_S = 0.2  # [s] the rollout's telemetry staleness limit (``excite_rollout``)


def draw_rigs(n: int, seed: int) -> list[dict[str, float]]:
    """``n`` plants (scenario ``plant`` dicts) drawn from ``configs/rigs/coverage.yaml``'s
    ranges (the training plants the intervals were validated on; that file says why)."""
    rnd = load_scenario(RIG_DIR / "coverage.yaml").randomize
    rng = np.random.default_rng(seed)
    return [{k: v for k, v in rnd.sample(rng).items() if k in SCORED or k in (
        "extra_mass_kg", "thickness_m")} for _ in range(n)]


def truth_of(plant: dict[str, float]) -> dict[str, float]:
    """The scored values of a drawn plant (module docstring: total mass, C1 and C2 at the
    nominal thickness, 0 for an effect the draw left out)."""
    mpa = DEFAULT_PARAMS.mpa
    t = plant.get("thickness_m", mpa.thickness)
    ro = mpa.D0 / 2.0
    vr_ratio = (ro**2 - (ro - t) ** 2) / (ro**2 - (ro - mpa.thickness) ** 2)
    out = {k: float(plant.get(k, 0.0)) for k in SCORED}
    out["mass_kg"] = plant.get("mass_kg", DEFAULT_PARAMS.leg.m) + plant.get("extra_mass_kg", 0.0)
    out["gamma_Ns_per_m"] = plant.get("gamma_Ns_per_m", mpa.gamma)
    out["C1_Pa"] = plant.get("C1_Pa", mpa.C1) * vr_ratio
    out["C2_Pa"] = plant.get("C2_Pa", mpa.C2) * vr_ratio
    return out


def written_intervals(scenario_yaml: str | Path) -> dict[str, tuple[float, float, bool]]:
    """(low, high, also the plant value) of each scored key in a scenario ``identify --out``
    wrote: its ``randomize`` range, or its ``plant`` value as a point where not randomised."""
    sc = load_scenario(scenario_yaml)
    plant = sc.plant
    off = dict(sc.randomize.p_off)
    ranges = {k: (lo, hi) for k, lo, hi in sc.randomize.ranges}
    out = {}
    for k in SCORED:
        v = getattr(plant, k)
        if k == "mass_kg":
            v = (v if v is not None else DEFAULT_PARAMS.leg.m) + plant.extra_mass_kg
        v = float(v) if v is not None else math.nan
        lo, hi = ranges.get(k, (v, v))
        out[k] = (lo, hi, off.get(k, 0.0) > 0.0)
    return out


def covered(truth: float, iv: tuple[float, float, bool], plant_value: float) -> bool:
    lo, hi, with_plant = iv
    # relative slack of 1e-9: a range written as YAML text round-trips to the last digit only
    slack = 1e-9 * max(abs(truth), 1e-12)
    return lo - slack <= truth <= hi + slack or (with_plant and truth == plant_value)


def _run(args: list[str], timeout: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "mpa_gym.agents.cli", *args],
                          capture_output=True, text=True, timeout=timeout)


def one_rig(i: int, plant: dict[str, float], folder: Path, episode_s: float) -> dict[str, Any]:
    """Roll ``excite`` out on an emulator playing ``plant``, identify, score."""
    noise = load_scenario(RIG_DIR / "offnominal.yaml").plant.position_noise_m
    log = folder / f"rig{i:03d}.jsonl"
    rec: dict[str, Any] = {"rig": i, "plant": plant, "truth": truth_of(plant), "log": str(log)}
    for attempt in range(ATTEMPTS):
        log.unlink(missing_ok=True)
        with EmulatorProcess({"name": f"rig{i}", "duration_s": episode_s + 5.0, "plant": plant},
                             ("--watchdog", str(WATCHDOG_S), "--position-noise", str(noise))
                             ) as emu:
            p = subprocess.run([sys.executable, "-m", __spec__.name if __spec__ else __name__,
                                "--rollout", emu.url, str(log), str(episode_s)],
                               capture_output=True, text=True, timeout=episode_s + 120.0)
        rec["rollout_attempts"] = attempt + 1
        if p.returncode == 0:
            break
        rec["rollout_error"] = (p.stderr.strip().splitlines() or ["?"])[-1]
    else:
        return rec
    rec.pop("rollout_error", None)
    out = folder / f"rig{i:03d}.yaml"
    t0 = time.monotonic()
    p = _run(["identify", "--log", str(log), "--out", str(out), "--plot",
              str(folder / f"rig{i:03d}.png"), "--json"], timeout=1800.0)
    rec["identify_s"] = time.monotonic() - t0
    if p.returncode != 0:
        rec["identify_error"] = (p.stderr.strip().splitlines() or ["?"])[-1]
        return rec
    report = json.loads(p.stdout)
    rec["estimate"] = {k: report["plant"].get(k) for k in SCORED}
    rec["estimate"]["mass_kg"] = report["plant"]["mass_kg"] + report["plant"]["extra_mass_kg"]
    ivs = written_intervals(out)
    rec["interval"] = {k: [lo, hi] for k, (lo, hi, _) in ivs.items()}
    rec["covered"] = {k: covered(rec["truth"][k], ivs[k], rec["estimate"][k]) for k in SCORED}
    return rec


def coverage(n: int, seed: int = 0, episode_s: float = 30.0, jobs: int = 2,
             folder: str | Path | None = None) -> dict[str, Any]:
    """Draw ``n`` rigs, identify each (``one_rig``, ``jobs`` at a time) and return each rig's
    record and, per scored key, the share of identified rigs whose interval holds the truth."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 1000:
        raise ValueError(f"--coverage={n!r} must be a whole number in [1, 1000]")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or not 1 <= jobs <= (os.cpu_count()
                                                                                 or 1):
        raise ValueError(f"--jobs={jobs!r} must be a whole number in [1, {os.cpu_count()}]")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
        raise ValueError(f"--seed={seed!r} must be a whole number in [0, 2**32 - 1]")
    check_range("--episode-s", episode_s, 12.0, 600.0, unit="s")
    if folder is None:
        folder = tempfile.mkdtemp(prefix="mpa-gym-coverage-")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    results_path = folder / "coverage.jsonl"
    results_path.touch()  # the folder is writable before any rig runs
    rigs = draw_rigs(n, seed)

    def run(i: int) -> dict[str, Any]:
        rec = one_rig(i, rigs[i], folder, episode_s)
        with open(results_path, "a") as f:
            f.write(json.dumps(rec) + "\n")
        return rec

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        records = list(pool.map(run, range(n)))
    scored = [r for r in records if "covered" in r]
    share = {k: (sum(r["covered"][k] for r in scored) / len(scored) if scored else math.nan)
             for k in SCORED}
    return {"rigs": n, "identified": len(scored), "seed": seed, "episode_s": episode_s,
            "coverage": share, "folder": str(folder), "records": records}


def show(o: dict[str, Any]) -> str:
    lines = [f"coverage over {o['identified']} of {o['rigs']} random emulated rigs (seed "
             f"{o['seed']}, {o['episode_s']:g} s excitation each; records: "
             f"{o['folder']}/coverage.jsonl):"]
    for k, v in o["coverage"].items():
        n = sum(r["covered"][k] for r in o["records"] if "covered" in r)
        lines.append(f"  {k:<26} {v * 100:5.1f} %  ({n}/{o['identified']})")
    for r in o["records"]:
        if "covered" not in r:
            lines.append(f"  rig {r['rig']}: not identified: "
                         f"{r.get('rollout_error') or r.get('identify_error')}")
    return "\n".join(lines)


def excite_rollout(device: str, log: str | Path, episode_s: float) -> dict[str, Any]:
    """``mpa-gym rollout --policy excite --realtime`` with the link's staleness limit relaxed to
    ``STALE_S`` (as the rig tests do): a loaded machine's scheduling hiccup then does not stop
    an excitation whose log is all that is needed (a rig's limits are for its safety, the
    emulator's watchdog, ``WATCHDOG_S``, still vents)."""
    env = ro.HardwareLegEnv
    ro.HardwareLegEnv = functools.partial(env, stale_s=STALE_S)
    try:
        return ro.rollout("excite", device, log, episode_s=episode_s, realtime=True)
    finally:
        ro.HardwareLegEnv = env


__all__ = ["coverage", "draw_rigs", "excite_rollout", "show", "truth_of", "written_intervals"]

if __name__ == "__main__":  # one rig's rollout, in its own process (``one_rig``)
    if sys.argv[1:2] != ["--rollout"] or len(sys.argv) != 5:
        sys.exit("usage: python -m mpa_gym.agents.rig.coverage --rollout DEVICE LOG EPISODE_S")
    out = excite_rollout(sys.argv[2], sys.argv[3], float(sys.argv[4]))
    sys.exit(1 if out.get("stopped") else 0)
