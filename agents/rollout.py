"""Roll a controller out on the rig: `mpa-gym rollout --policy P --device URL [--dry-run]`.

Pre-flight (link, sensor sanity, low-pressure test), then the episodes; every step is appended to
a JSON-lines log and flushed as it happens, so a killed process leaves a log readable up to its
last step (``read_log`` skips a torn last line). The end prints the evaluation report's metrics.
``--dry-run`` starts the device emulator on UDP loopback and rolls out against it.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.evaluate import Trace, metrics
from agents.policies import load_policy
from mpa_gym.hardware import protocol as proto
from mpa_gym.hardware.env import HardwareFault, HardwareLegEnv
from mpa_gym.model.params import BAR


def preflight(env: HardwareLegEnv, test_bar: float = 0.5, hold_s: float = 0.3,
              link_timeout_s: float = 2.0) -> dict[str, Any]:
    """Link, sensor sanity and a low-pressure test; raises HardwareFault naming what failed."""
    t0 = time.monotonic()
    while env._tel is None and time.monotonic() - t0 < link_timeout_s:
        env.vent()  # also tells a UDP device where to send its telemetry
        env._read(time.monotonic() + 0.05)
    if env._tel is None:
        raise HardwareFault(f"pre-flight: no telemetry within {link_timeout_s:g} s: check the "
                            "device is on, the URL, cable / network, and that nothing else "
                            "holds the port")
    settle_end = time.monotonic() + 3.0  # a vented leg sinks onto its end stop: let it rest
    while abs(env._tel.v_mps) > 0.05 and time.monotonic() < settle_end:
        env.vent()
        env._read(time.monotonic() + 0.05)
    t = env._tel
    lo, hi = 0.6, 0.87
    if not (lo <= t.x_m <= hi and math.isfinite(t.v_mps) and abs(t.v_mps) < 0.5):
        raise HardwareFault(f"pre-flight: implausible encoder reading X = {t.x_m:.4f} m, V = "
                            f"{t.v_mps:.3f} m/s (expected X in [{lo}, {hi}] m, |V| < 0.5 m/s)")
    end = time.monotonic() + hold_s
    while time.monotonic() < end:  # both MPAs at a low pressure
        env._send(proto.Command, test_bar * BAR, test_bar * BAR)
        env._read(time.monotonic() + 0.01)
    p = np.array([env._tel.pe_Pa, env._tel.pf_Pa]) / BAR
    env.vent()
    if np.any(np.abs(p - test_bar) > 0.2):
        raise HardwareFault(f"pre-flight: low-pressure test commanded {test_bar} bar, measured "
                            f"({p[0]:.2f}, {p[1]:.2f}) bar: check supply and regulators")
    return {"x_m": t.x_m, "v_mps": t.v_mps, "test_pressure_bar": p.tolist()}


def read_log(path: str | Path) -> list[dict[str, Any]]:
    """The complete records of a rollout log (a torn last line from a kill is skipped)."""
    out = []
    for line in Path(path).read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return out


def rollout(policy_spec: str, device: Any, log_path: str | Path, episodes: int = 1,
            scenario: Any = "nominal", control_hz: float = 100.0, episode_s: float | None = None,
            seed: int = 0) -> dict[str, Any]:
    """Run ``episodes`` of ``policy_spec`` on ``device``; returns metrics and timing."""
    # a baseline's integrator and feedforward timing follow the rig's control period
    policy, env_id, run_cfg = load_policy(policy_spec, {"scenario": scenario,
                                                        "task": {"dt_s": 1.0 / control_hz}})
    task = dict((run_cfg.env_kwargs.get("task") or {}) if run_cfg else {})
    task.pop("dt_s", None)
    task["episode_s"] = episode_s if episode_s is not None else task.get("episode_s")
    if task["episode_s"] is None:
        task.pop("episode_s")
    env = HardwareLegEnv(device, scenario=scenario, task=task,
                         residual=env_id == "MPALegResidual-v0", control_hz=control_hz)
    log = Path(log_path)
    log.parent.mkdir(parents=True, exist_ok=True)
    results: list[dict[str, Any]] = []
    with env, log.open("a", buffering=1) as f:
        pre = preflight(env)
        f.write(json.dumps({"event": "preflight", **pre}) + "\n")
        for ep in range(episodes):
            obs, info = env.reset(seed=seed + ep)
            state, start = None, np.array([True])
            rows = []
            while True:
                action, state = policy.predict(obs, state, start, deterministic=True)
                start = np.array([False])
                obs, r, term, trunc, info = env.step(action)
                rec = {"episode": ep, "reward": r, "terminated": term,
                       **{k: (v.tolist() if isinstance(v, np.ndarray) else v)
                          for k, v in info.items()}}
                f.write(json.dumps(rec, allow_nan=True) + "\n")  # line-buffered: one write
                rows.append(rec)
                if term or trunc:
                    break
            os.fsync(f.fileno())
            results.append(_episode_metrics(rows, env))
    period = np.array(env.timing["period_s"])
    jitter = np.abs(period - env.cfg.dt_s)
    return {"episodes": results, "log": str(log),
            "timing": {"control_hz": control_hz, "overruns": env.overruns,
                       "p99_jitter_ms": float(np.percentile(jitter, 99) * 1e3) if jitter.size
                       else None,
                       "median_latency_ms": float(np.nanmedian(env.timing["latency_s"]) * 1e3)
                       if env.timing["latency_s"] else None}}


def _episode_metrics(rows: list[dict[str, Any]], env: HardwareLegEnv) -> dict[str, Any]:
    col = lambda k: np.array([r[k] for r in rows])  # noqa: E731
    tr = Trace(col("t_s"), col("x_m"), col("x_ref_m"), col("k_N_per_m"), col("k_ref_N_per_m"),
               col("pressure_bar"), col("pressure_cmd_bar"), (col("safety") & 1) > 0,
               col("reward"), bool(rows[-1]["terminated"]))
    m = metrics(tr, env.plan.design.reference.period, None)
    if "fault" in rows[-1]:
        m["fault"] = rows[-1]["fault"]
    return m
