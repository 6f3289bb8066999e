"""Timing of a trained run's inference on the rig's path: the compiled deployed policy
(``mpa_gym.agents.learned.inference``) against SB3's ``predict``, with a device emulator serving
telemetry from another process meanwhile (``mpa-gym bench --inference RUN_DIR``)."""

from __future__ import annotations

import time
from typing import Any

import gymnasium as gym
import numpy as np

from mpa_gym.agents.evaluation.episodes import eval_task
from mpa_gym.agents.learned.policies import load_run
from mpa_gym.hardware import protocol as proto
from mpa_gym.hardware.emulator import EmulatorProcess
from mpa_gym.hardware.transport import open_transport


def benchmark(run_dir: str, n_actions: int = 20_000, n_reference: int = 2_000,
              emulator: bool = True) -> dict[str, Any]:
    """Time per action of a run: the deployed path and SB3's ``predict`` (the reference), in the
    same process and run, on the observations of a simulated episode, with (``emulator``) a
    device emulator serving telemetry from another process meanwhile.

    Returns median and p99 [ms] of each and their ratios (SB3 / deployed)."""
    sb3, cfg = load_run(run_dir)
    deployed, _ = load_run(run_dir, deployed=True)
    env = gym.make(cfg.env_id, scenario="load_1kg", task={**eval_task(cfg), "episode_s": 3.0})
    obs, _ = env.reset(seed=0)
    observations = [obs]
    state, start = None, np.array([True])
    for _ in range(299):  # the observations a policy sees along an episode
        a, state = sb3.predict(obs, state, start)
        start = np.array([False])
        obs, *_ = env.step(a)
        observations.append(obs)
    emu = link = None
    try:
        if emulator:
            emu = EmulatorProcess()
            link = open_transport(emu.url)
            link.send(proto.encode(proto.Vent(1, 0)))  # the emulator now streams to us
        times = {}
        for name, n, call in (
                ("deployed", n_actions, lambda o: deployed.act(o)),
                ("sb3", n_reference, lambda o: sb3.predict(o, state, start))):
            for o in observations[:50]:  # warm caches
                call(o)
            t = np.empty(n)
            for i in range(n):
                o = observations[i % len(observations)]
                t0 = time.perf_counter_ns()
                call(o)
                t[i] = time.perf_counter_ns() - t0
            times[name] = t * 1e-6  # [ms]
    finally:
        if link is not None:
            link.close()
        if emu is not None:
            emu.close()
    out: dict[str, Any] = {"run_dir": str(run_dir), "emulator_process": emulator}
    for name, t in times.items():
        out[name] = {"actions": int(t.size), "median_ms": float(np.median(t)),
                     "p99_ms": float(np.percentile(t, 99)), "max_ms": float(t.max())}
    out["ratio_median_sb3_over_deployed"] = out["sb3"]["median_ms"] / out["deployed"]["median_ms"]
    out["ratio_p99_sb3_over_deployed"] = out["sb3"]["p99_ms"] / out["deployed"]["p99_ms"]
    return out


def show_benchmark(o: dict[str, Any]) -> str:
    lines = [f"inference of {o['run_dir']} (device emulator in another process: "
             f"{'yes' if o['emulator_process'] else 'no'}), time per action:"]
    for name, label in (("deployed", "deployed (compiled)"), ("sb3", "SB3 predict (reference)")):
        m = o[name]
        lines.append(f"  {label:<26} median {m['median_ms']:.4f} ms   p99 {m['p99_ms']:.4f} ms"
                     f"   max {m['max_ms']:.3f} ms   ({m['actions']} actions)")
    lines.append(f"  SB3 / deployed: median x{o['ratio_median_sb3_over_deployed']:.1f}, "
                 f"p99 x{o['ratio_p99_sb3_over_deployed']:.1f}")
    return "\n".join(lines)
