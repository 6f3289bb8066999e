"""Roll a controller out on the rig: `mpa-gym rollout --policy P --device URL [--dry-run]`.

Pre-flight (link, sensor sanity, low-pressure test), then the episodes. The log is JSON lines,
appended to and flushed step by step, so a killed process leaves it readable up to its last step
but one: a step's record is written in the slack of the next control period, right after that
period's command went out (``HardwareLegEnv.defer``), so the write never delays a command.
Each session (one ``rollout`` call) starts with a ``{"event": "session", ...}`` header naming its
policy, scenario and rate, so sessions appended to one file stay apart; ``read_log`` skips a torn
line (a kill mid-write) and goes on, and says how many it skipped.

Every stop is written to the log as ``{"event": "stopped", "fault": reason}`` and returned as
``stopped``: a safety stop of the env (position bound, stale telemetry, over-pressure, device
fault: the rest of the session is not run), a fault in the pre-flight or a reset, Ctrl-C or
SIGTERM. The rig is vented in each case. ``--dry-run`` starts the device emulator on UDP
loopback and rolls out against it.

A supervised run (``mpa_gym.agents.controllers.supervisor``) logs ``{"event": "fallback", ...}`` at
the step its fallback takes over and ``{"event": "last_resort", ...}`` at the step its last resort
does; each step's ``fallback`` field is the stage that drove it (0 the policy, 1 the fallback, 2 the
last resort).
"""

from __future__ import annotations

import datetime
import functools
import json
import math
import os
import signal
import tempfile
import time
from pathlib import Path
from typing import IO, Any

import numpy as np

from mpa_gym.agents.controllers.gains import Gains
from mpa_gym.agents.controllers.supervisor import (
    FALLBACK,
    POLICY,
    Supervised,
    hand_overs,
    took_over,
)
from mpa_gym.agents.evaluation.episodes import Trace, metrics
from mpa_gym.agents.evaluation.select import choose_starts
from mpa_gym.agents.learned.policies import known_delays, load_policy
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.hardware.emulator import EmulatorProcess
from mpa_gym.hardware.env import (
    CONTROL_HZ,
    CONTROL_HZ_RANGE,
    SPIN_S,
    HardwareFault,
    HardwareLegEnv,
    wait_s,
)
from mpa_gym.hardware.realtime import realtime as rt_context
from mpa_gym.hardware.transport import UDPServer
from mpa_gym.model.params import BAR, check_range
from mpa_gym.task.config import END_STOPS_M
from mpa_gym.task.contract import SAFETY_CLIPPED

PREFLIGHT_TOLERANCE_BAR = 0.2  # [bar] the low-pressure test's allowed |measured − commanded|
PREFLIGHT_MAX_V_MPS = 0.5  # [m/s] the encoder's speed of a leg at rest, at most


def preflight(env: HardwareLegEnv, test_bar: float = 0.5, hold_s: float = 0.3,
              link_timeout_s: float = 2.0) -> dict[str, Any]:
    """Link, sensor sanity and a low-pressure test; raises HardwareFault naming what failed."""
    t0 = time.monotonic()
    while env.telemetry is None and time.monotonic() - t0 < link_timeout_s:
        env.vent()  # also tells a UDP device where to send its telemetry
        env.poll(0.05)
    if env.telemetry is None:
        raise HardwareFault(f"pre-flight: no telemetry within {link_timeout_s:g} s: check the "
                            "device is on, the URL, cable / network, and that nothing else "
                            "holds the port")
    settle_end = time.monotonic() + 3.0  # a vented leg sinks onto its end stop: let it rest
    while abs(env.telemetry.v_mps) > 0.05 and time.monotonic() < settle_end:
        env.vent()
        env.poll(0.05)
    t = env.telemetry
    lo, hi = END_STOPS_M
    if not (lo <= t.x_m <= hi and math.isfinite(t.v_mps) and abs(t.v_mps) < PREFLIGHT_MAX_V_MPS):
        raise HardwareFault(f"pre-flight: implausible encoder reading X = {t.x_m:.4f} m, V = "
                            f"{t.v_mps:.3f} m/s (expected X in [{lo}, {hi}] m, the end stops, "
                            f"|V| < {PREFLIGHT_MAX_V_MPS:g} m/s)")
    tel = env.hold(test_bar, test_bar, hold_s)  # both MPAs at a low pressure
    env.vent()
    p = np.array([tel.pe_Pa, tel.pf_Pa]) / BAR
    if np.any(np.abs(p - test_bar) > PREFLIGHT_TOLERANCE_BAR):
        raise HardwareFault(f"pre-flight: low-pressure test commanded {test_bar} bar, measured "
                            f"({p[0]:.2f}, {p[1]:.2f}) bar: check supply and regulators")
    return {"x_m": t.x_m, "v_mps": t.v_mps, "test_pressure_bar": p.tolist()}


class LogRecords(list):  # type: ignore[type-arg]
    """The complete records of a rollout log, in order; ``skipped``: torn lines left out."""

    skipped: int = 0


def read_log(path: str | Path) -> LogRecords:
    """Every complete record of a rollout log; a torn line (a kill mid-write) is skipped and
    counted in ``.skipped``, and reading goes on past it."""
    out = LogRecords()
    with Path(path).open("rb") as f:
        for line in f:
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except (json.JSONDecodeError, UnicodeDecodeError):
                out.skipped += 1
                continue
            if isinstance(rec, dict):
                out.append(rec)
            else:
                out.skipped += 1
    return out


def _is_record(line: bytes) -> bool:
    try:
        return isinstance(json.loads(line), dict)
    except ValueError:  # not JSON, not UTF-8
        return False


def open_log(path: str | Path) -> IO[str]:
    """The log opened for appending (line-buffered), after a newline if the file ends in a torn
    line, so the next record starts on a line of its own. Fails before the rig is touched."""
    log = Path(path)
    if log.is_dir():
        raise ValueError(f"--log {str(log)!r} is a folder; give a file (e.g. {log}/rollout.jsonl)")
    torn = False
    if log.is_file() and log.stat().st_size > 0:
        # appending to a file that is not a log would corrupt it (a config given by mistake)
        with log.open("rb") as g:
            head = [g.readline(1 << 20) for _ in range(3)]
            g.seek(-1, 2)
            torn = g.read(1) != b"\n"
        # a log: one of its first lines a JSON record (the first may be torn by a kill or a
        # full disk, and a session appended after it), or a lone torn record
        is_log = any(_is_record(ln) for ln in head) or (
            not head[0].endswith(b"\n") and head[0].lstrip().startswith(b"{"))
        if not is_log:
            raise ValueError(f"--log {str(log)!r} exists and is not a rollout log (its first "
                             "line is not a JSON record); give a new file or a log of "
                             "mpa-gym rollout to append to")
    try:
        log.parent.mkdir(parents=True, exist_ok=True)
        f = log.open("a", buffering=1)
    except OSError as e:
        raise ValueError(f"--log {str(log)!r} cannot be opened for writing: {e.strerror}"
                         ) from None
    if torn:
        f.write("\n")
    return f


def stop_reason(exc: BaseException, vented: bool = True) -> str:
    """What stopped a rollout, as written to the log (``vented``: the vent after it went out)."""
    if isinstance(exc, KeyboardInterrupt):
        signum = getattr(exc, "signum", signal.SIGINT)
        return (f"interrupted by {signal.Signals(signum).name}; "
                + ("rig vented" if vented else "venting FAILED"))
    return f"{type(exc).__name__}: {exc}"


def rollout(policy_spec: str, device: Any, log_path: str | Path, episodes: int = 1,
            scenario: Any = "nominal", control_hz: float = CONTROL_HZ,
            episode_s: float | None = None, seed: int = 0, realtime: bool = False,
            gains: Gains | None = None, flag: str = "--policy") -> dict[str, Any]:
    """Run ``episodes`` of ``policy_spec`` (a baseline with its entry of ``gains``, a run
    folder, your own ``module:Class``; ``flag`` names it in errors) on ``device``; returns
    metrics and timing, and
    ``stopped`` (the reason) if the env's safety layer ended an episode early. For a supervised
    run, ``stages`` names its supervisor's controllers and each episode's metrics say who drove
    (``policy_share``, ``fallback_s``, ``last_resort_s`` and ``hand_overs``, the same in words:
    empty where the policy drove every step); ``RUN_DIR:alone`` rolls the policy out without
    its supervisor.

    The episodes run with the garbage collector off (its full collections pause longer than
    the device's watchdog allows); ``realtime`` adds real-time scheduling, as far as permitted
    (``mpa_gym.hardware.realtime``; the timing says what was granted)."""
    check_range("--control-hz", control_hz, *CONTROL_HZ_RANGE, unit="Hz")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or not 1 <= episodes <= 10_000:
        raise ValueError(f"--episodes={episodes!r} must be a whole number in [1, 10000]")
    if episode_s is not None:
        check_range("--episode-s", episode_s, 1.0 / control_hz, 3600.0, unit="s")
    # a baseline's integrator and feedforward timing follow the rig's control period; a run is
    # refused at a rate other than its training one (load_policy), before the rig is touched
    policy, env_id, run_cfg = load_policy(policy_spec, {"scenario": scenario,
                                                        "task": {"dt_s": 1.0 / control_hz}},
                                          deployed=True,  # a run: its compiled action path
                                          gains=gains, flag=flag)
    # a policy that observes the rig's delays is told the scenario's plant's (identify --out's)
    told = known_delays(policy)
    # a supervisor that chooses its start does so on the scenario's plant (identify --out's),
    # in simulation before the rig is touched, with the run's batch path (select.choose_starts)
    supervised = isinstance(policy, Supervised)
    stages = [s.controller for s in run_cfg.supervisor.stages] if supervised else None
    first = POLICY  # the supervisor's stage every episode starts at
    # {stage: [mm]} and {stage: [%]} predicted on the model, where the start was chosen
    predicted = predicted_pct = None
    if supervised and policy.spec.select is not None:
        model = load_policy(policy_spec, {"scenario": scenario,
                                          "task": {"dt_s": 1.0 / control_hz}}, gains=gains)
        mm, pct = choose_starts([model], [scenario], [None])[0]
        first = policy.choose(mm, pct)
        # JSON has no infinity: None is unstable
        predicted, predicted_pct = ({st: (None if math.isinf(v) else v)
                                     for st, v in zip(stages, f, strict=True)} for f in (mm, pct))
    task = dict((run_cfg.env_kwargs.get("task") or {}) if run_cfg else {})
    task.pop("dt_s", None)
    task["episode_s"] = episode_s if episode_s is not None else task.get("episode_s")
    if task["episode_s"] is None:
        task.pop("episode_s")
    f = open_log(log_path)
    results: list[dict[str, Any]] = []
    stopped: str | None = None
    try:
        env = HardwareLegEnv(device, scenario=scenario, task=task,
                             residual=env_id == "MPALegResidual-v0", control_hz=control_hz)
    except BaseException as e:
        _write(f, {"event": "stopped", "fault": stop_reason(e)})
        f.close()
        raise
    with env, f, rt_context(sched_fifo=realtime) as rt_report:
        _write(f, {"event": "session", "started_utc": datetime.datetime.now(datetime.timezone.utc)
                   .isoformat(timespec="seconds"), "pid": os.getpid(), "policy": policy_spec,
                   "scenario": env.plan.scenario.name, "control_hz": control_hz,
                   "episodes": episodes, "seed": seed, "told_delays_s": told})
        if predicted is not None:  # the start chosen on the model, and on what figures
            _write(f, {"event": "chosen", "start": stages[first], "predicted_mm": predicted,
                       "predicted_stiffness_pct": predicted_pct,
                       "supervisor": run_cfg.supervisor.describe()})
        try:
            pre = preflight(env)
            _write(f, {"event": "preflight", **pre})
            for ep in range(episodes):
                obs, info = env.reset(seed=seed + ep)
                state, start = None, np.array([True])
                rows: list[dict[str, Any]] = []
                # the supervisor's stage this episode (mpa_gym.agents.controllers.supervisor)
                fell = first
                while True:
                    action, state = policy.predict(obs, state, start, deterministic=True)
                    start = np.array([False])
                    obs, r, term, trunc, info = env.step(action)
                    if (flags := took_over(policy, state)) is not None:
                        if flags[0] > fell:  # the step a stage took over: say so in the log
                            fell = int(flags[0])
                            env.defer(functools.partial(_write, f, {
                                "event": "fallback" if fell == FALLBACK else "last_resort",
                                "episode": ep, "t_s": info["t_s"],
                                "supervisor": run_cfg.supervisor.describe()}))
                        info = {**info, "fallback": int(flags[0])}
                    # the record is written in the slack of the next period, after its command
                    # went out (env.defer), not between this telemetry and that command
                    record = functools.partial(_log_step, f, rows, ep, r, term, info)
                    if term or trunc:
                        record()
                        break
                    env.defer(record)
                os.fsync(f.fileno())
                results.append(_episode_metrics(rows, env, first))
                if term:  # a safety stop: the rig is vented, the session ends here
                    stopped = f"episode {ep}: {info.get('fault', 'terminated')}"
                    _write(f, {"event": "stopped", "episode": ep, "fault": stopped})
                    break
        except BaseException as e:  # a fault, Ctrl-C, SIGTERM: vent, then say why in the log
            try:
                env.vent()
            except BaseException as v:  # a dead link, a second Ctrl-C: the reason still goes
                env.run_deferred()  # the last step's record, before the stop's
                _write(f, {"event": "stopped", "fault": stop_reason(e, vented=False),
                           "vent_fault": stop_reason(v, vented=False)})
                raise  # the vent's failure (the original as its context): the rig may be live
            env.run_deferred()
            _write(f, {"event": "stopped", "fault": stop_reason(e)})
            raise
    period = np.array(env.timing["period_s"])
    jitter = np.abs(period - env.cfg.dt_s)
    if stages is not None:  # who drove each episode, for the summary
        for m in results:
            m["hand_overs"] = hand_overs(m, stages)
    out: dict[str, Any] = {
        "episodes": results, "log": str(log_path), "stages": stages, "told_delays_s": told,
        "predicted_mm": predicted, "predicted_stiffness_pct": predicted_pct,
        "scenario": env.plan.scenario.name,
        "timing": {"control_hz": control_hz, "overruns": env.session_overruns,
                   "steps": len(env.timing["latency_s"]), "realtime": rt_report,
                   "p99_jitter_ms": float(np.percentile(jitter, 99) * 1e3) if jitter.size
                   else None,
                   "median_latency_ms": float(np.nanmedian(env.timing["latency_s"]) * 1e3)
                   if env.timing["latency_s"] else None}}
    if stopped is not None:
        out["stopped"] = stopped
    return out


def _log_step(f: IO[str], rows: list[dict[str, Any]], episode: int, reward: float,
              terminated: bool, info: dict[str, Any]) -> None:
    """One step's record, appended to the log (line-buffered: one write, no sync) and to
    ``rows``."""
    rec = {"episode": episode, "reward": reward, "terminated": terminated,
           **{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in info.items()}}
    f.write(json.dumps(rec, allow_nan=True) + "\n")
    rows.append(rec)


def _write(f: IO[str], rec: dict[str, Any]) -> None:
    """One record, flushed and synced (events are rare; steps are written without the sync)."""
    f.write(json.dumps(rec, allow_nan=True) + "\n")
    f.flush()
    os.fsync(f.fileno())


def _episode_metrics(rows: list[dict[str, Any]], env: HardwareLegEnv, start: int = POLICY
                     ) -> dict[str, Any]:
    col = lambda k: np.array([r[k] for r in rows])  # noqa: E731
    tr = Trace(col("t_s"), col("x_m"), col("x_ref_m"), col("k_N_per_m"), col("k_ref_N_per_m"),
               col("pressure_bar"), col("pressure_cmd_bar"), (col("safety") & SAFETY_CLIPPED) > 0,
               col("reward"), bool(rows[-1]["terminated"]))
    if "fallback" in rows[0]:  # a supervised run: which steps its fallback drove
        tr.fallback, tr.start = col("fallback"), start
    m = metrics(tr, env.plan.design.reference.period, None)
    if "fault" in rows[-1]:
        m["fault"] = rows[-1]["fault"]
    return m


def wait_floor(control_hz: float, duration_s: float, spin_s: float = SPIN_S
               ) -> dict[str, Any]:
    """How late the OS alone lets the rig loop's wait end: ``duration_s`` of the wait of
    ``HardwareLegEnv`` (the same link read, ``mpa_gym.hardware.env.wait_s``) on a loopback
    socket that nothing sends to, with no work between deadlines. Its overrun fraction is what
    no loop can beat on this machine at this moment."""

    dt = 1.0 / control_hz
    late = np.empty(max(1, round(duration_s * control_hz)))
    link = UDPServer("127.0.0.1", 0)
    try:
        deadline = time.monotonic() + dt
        for i in range(late.size):
            while (left := deadline - time.monotonic()) > 0.0:
                link.recv(wait_s(left, spin_s))
            late[i] = time.monotonic() - deadline
            deadline += dt
    finally:
        link.close()
    return {"steps": int(late.size), "overrun_pct": float(np.mean(late > 0.25 * dt) * 100),
            "p99_late_ms": float(np.percentile(late, 99) * 1e3)}


class LoopStopped(RuntimeError):
    """``bench --loop`` stopped: the emulated rig failed a safety check (the rig is vented);
    the message names ``--rig`` and what was measured."""


def loop_benchmark(policy_spec: str, control_hz: float = 100.0, loop_s: float = 10.0,
                   repeats: int = 3, rig: Any = "nominal", scenario: Any = "nominal",
                   gains: Gains | None = None) -> dict[str, Any]:
    """The rig loop's timing (``mpa-gym bench --loop``): ``repeats`` pairs, each the machine's
    floor (``wait_floor``) then a ``loop_s`` rollout of ``policy_spec`` at ``control_hz``
    against a device emulator in another process playing ``rig``, side by side so that both
    see the same machine. Returns each pair and the medians of overrun %, p99 jitter and
    median command latency."""
    check_range("--control-hz", control_hz, *CONTROL_HZ_RANGE, unit="Hz")
    check_range("--loop-s", loop_s, 1.0, 600.0, unit="s")
    if isinstance(repeats, bool) or not isinstance(repeats, int) or not 1 <= repeats <= 100:
        raise ValueError(f"--repeats={repeats!r} must be a whole number in [1, 100]")
    try:  # the emulator process loads the same scenario: refused here, before any work
        load_scenario(rig)
    except ValueError as e:
        raise ValueError(f"--rig: {e}") from None
    # the controller is checked (built once) before the first measurement
    load_policy(policy_spec, {"scenario": scenario, "task": {"dt_s": 1.0 / control_hz}},
                gains=gains, flag="--loop")
    pairs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeats):
            floor = wait_floor(control_hz, loop_s)
            with EmulatorProcess(rig) as emu:
                try:
                    out = rollout(policy_spec, emu.url, Path(tmp) / f"loop{i}.jsonl",
                                  scenario=scenario, control_hz=control_hz, episode_s=loop_s,
                                  gains=gains, flag="--loop")
                except HardwareFault as e:  # the rig of --rig fails the pre-flight or homing
                    raise LoopStopped(f"--rig {rig!r}: {e}") from None
            t = out["timing"]
            pairs.append({"floor": floor, "loop": {
                "steps": t["steps"], "overrun_pct": 100.0 * t["overruns"] / max(1, t["steps"]),
                "p99_jitter_ms": t["p99_jitter_ms"], "median_latency_ms": t["median_latency_ms"],
                "position_rmse_mm": out["episodes"][0]["position_rmse_mm"],
                "stopped": out.get("stopped")}})
    med = lambda side, key: float(np.median([p[side][key] for p in pairs]))  # noqa: E731
    return {"policy": policy_spec, "control_hz": control_hz, "loop_s": loop_s,
            "rig": rig if isinstance(rig, str) else "(dict)", "pairs": pairs,
            "median": {"floor_overrun_pct": med("floor", "overrun_pct"),
                       "floor_p99_late_ms": med("floor", "p99_late_ms"),
                       "loop_overrun_pct": med("loop", "overrun_pct"),
                       "loop_p99_jitter_ms": med("loop", "p99_jitter_ms"),
                       "loop_median_latency_ms": med("loop", "median_latency_ms")}}


def show_loop_benchmark(o: dict[str, Any]) -> str:
    lines = [f"rig loop of {o['policy']} at {o['control_hz']:g} Hz against an emulator process "
             f"({o['rig']}), {o['loop_s']:g} s per run; floor: the same wait with no work"]
    for i, p in enumerate(o["pairs"]):
        f, lp = p["floor"], p["loop"]
        lines.append(f"  pair {i}: floor {f['overrun_pct']:.2f} % late (p99 {f['p99_late_ms']:.3f}"
                     f" ms) | loop {lp['overrun_pct']:.2f} % overruns, p99 jitter "
                     f"{lp['p99_jitter_ms']:.3f} ms, median latency "
                     f"{lp['median_latency_ms']:.3f} ms, RMSE {lp['position_rmse_mm']:.3f} mm"
                     + (f", STOPPED: {lp['stopped']}" if lp["stopped"] else ""))
    m = o["median"]
    lines.append(f"median: floor {m['floor_overrun_pct']:.2f} %, loop {m['loop_overrun_pct']:.2f} "
                 f"% overruns (p99 jitter {m['loop_p99_jitter_ms']:.3f} ms, median latency "
                 f"{m['loop_median_latency_ms']:.3f} ms)")
    return "\n".join(lines)
