"""A device emulator that plays the rig: `mpa-gym emulate --serial | --udp`.

It runs the plant (the scenario's true plant, compiled RK4 in ≤ 1 ms steps, with its braid and
slider friction) in real time, applies each pressure command when it arrives plus the
regulator's dead time (to the microsecond, not rounded to a step), through the regulator's slew
limit and first-order lag, plays the scenario's ``disturbances`` (each impulse's mean force over
each step, as the sim's plan) on the session clock (plant time since the first command after the
start or a vent), streams telemetry every ``telemetry_period_s``, and behaves like firmware:
when commands stop for ``watchdog_s`` (40 ms, so that the vent lands within 50 ms of the last
command even when its own loop is a few ms late) it vents both MPAs and raises
``FAULT_WATCHDOG_VENT`` until commands resume; a ``Vent`` message vents at once. For tests it
injects what real links do: latency and jitter on telemetry, dropped, late and corrupt frames,
and sensor noise.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.hardware import protocol as proto
from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_range
from mpa_gym.task.config import END_STOPS_M

TELEMETRY_PERIOD_S = 0.001  # [s] the emulator streams telemetry at 1 kHz
# [s] it vents after this long without a command: within 50 ms of the last one even when its
# own loop is a few ms late (docs/firmware.md)
WATCHDOG_S = 0.04


@dataclass(frozen=True)
class LinkFaults:
    """What the emulated link and sensors do to telemetry (all off by default)."""

    latency_s: float = 0.0  # [s] every telemetry frame leaves this late
    jitter_s: float = 0.0  # [s] plus a uniform random extra delay in [0, jitter]
    drop_prob: float = 0.0  # probability a telemetry frame is lost
    late_prob: float = 0.0  # probability a frame is held back by ``late_s``
    late_s: float = 0.05  # [s]
    corrupt_prob: float = 0.0  # probability one byte of a frame is flipped
    position_noise_m: float = 0.0  # [m] std of encoder noise
    velocity_noise_mps: float = 0.0  # [m/s]
    pressure_noise_bar: float = 0.0  # [bar]

    def __post_init__(self) -> None:
        for name in ("latency_s", "jitter_s", "late_s"):
            check_range(f"faults.{name}", getattr(self, name), 0.0, 1.0, unit="s")
        for name in ("drop_prob", "late_prob", "corrupt_prob"):
            check_range(f"faults.{name}", getattr(self, name), 0.0, 1.0)
        check_range("faults.position_noise_m", self.position_noise_m, 0.0, 0.01, unit="m")
        check_range("faults.velocity_noise_mps", self.velocity_noise_mps, 0.0, 1.0, unit="m/s")
        check_range("faults.pressure_noise_bar", self.pressure_noise_bar, 0.0, 1.0, unit="bar")


@dataclass
class EmulatorStats:
    commands: int = 0
    telemetry_sent: int = 0
    dropped: int = 0
    corrupted: int = 0
    late: int = 0
    corrupt_received: int = 0
    watchdog_vents: int = 0
    last_command_time: float = math.nan  # [s] monotonic
    vent_time: float = math.nan  # [s] monotonic time of the last watchdog vent


class Emulator:
    """The rig on one end of a link (``link`` has send / recv(timeout_s) / close)."""

    def __init__(self, link: Any, scenario: Any = "nominal", params: Params = DEFAULT_PARAMS,
                 faults: LinkFaults | None = None,
                 telemetry_period_s: float = TELEMETRY_PERIOD_S, watchdog_s: float = WATCHDOG_S,
                 seed: int = 0, lockstep_dt_s: float | None = None,
                 initial_state: tuple[float, float, float, float] | None = None) -> None:
        check_range("telemetry_period_s", telemetry_period_s, 1e-4, 0.1, unit="s")
        check_range("watchdog_s", watchdog_s, 1e-3, 10.0, unit="s")
        self.link = link
        self.sc = load_scenario(scenario)
        self.consts = fast.pack(self.sc.plant_params(params))
        self.dead_time_s = self.sc.plant.pressure_dead_time_s
        self.faults = faults or LinkFaults()
        self.period = telemetry_period_s
        self.watchdog_s = watchdog_s
        # lockstep (tests): each command advances the plant by exactly lockstep_dt_s and is
        # answered at once, instead of the plant running on the wall clock
        self.lockstep_dt_s = lockstep_dt_s
        self.rng = np.random.default_rng(seed)
        self.decoder = proto.FrameDecoder()
        self.stats = EmulatorStats()
        self.lock = threading.Lock()
        x0, _ = self.sc.start_state()
        p0 = self.sc.design(params).pressures(0.0)
        # the leg rests at the start height with the design's initial pressures, unless
        # initial_state (X [m], V [m/s], P'_e, P'_f [Pa], the pressures also commanded) says
        if initial_state is None:
            self.state = np.array([x0, 0.0, p0[0], p0[1]])
        else:
            self.state = np.array(initial_state, dtype=float)
        self.cmd = self.state[2:].copy()  # the command the regulator acts on (after dead time)
        self.t = 0.0  # [s] plant time
        # the scenario's disturbances play on the session clock: plant time since the first
        # command after the start or a vent (None: no session yet), as the sim's plan plays them
        # on episode time
        self.kicks = tuple((d.t_s, d.t_s + d.duration_s, d.force_N) for d in self.sc.disturbances)
        self.session_t0: float | None = None
        self._pending: deque[tuple[float, float, float]] = deque()  # (t due, P'_e, P'_f)
        self.vented = False
        self.faults_flags = 0
        self._seq = 0
        self._last_cmd_seq = 0
        self._outbox: list[tuple[float, bytes]] = []
        self._stop = threading.Event()
        self._advance(0.0)  # compile (or load) the plant kernel before serving, not mid-episode

    # -- physics ----------------------------------------------------------------------------
    def _advance(self, dt: float) -> None:
        """Integrate the plant over dt [s] in RK4 steps of at most 1 ms; a command whose dead
        time ends inside a step takes over at that instant (the step is split there)."""
        n = max(1, math.ceil(dt / 1e-3 - 1e-9))
        h = dt / n
        X, V, Pe, Pf = self.state

        def hold(X: float, V: float, Pe: float, Pf: float, a: float, b: float) -> tuple:
            """One RK4 step from plant time ``a`` to ``b`` [s] under the command now in force
            and the disturbances' mean force over it (the sim's plan takes the same mean)."""
            ce, cf = self.cmd
            f_ext = 0.0
            if self.kicks and self.session_t0 is not None:
                s0, s1 = a - self.session_t0, b - self.session_t0
                f_ext = sum(f * max(0.0, min(s1, hi) - max(s0, lo))
                            for lo, hi, f in self.kicks) / (b - a)
            return fast.plant_step(X, V, Pe, Pf, ce, cf, ce, cf, 0.0, f_ext, b - a,
                                   self.consts, 1)

        for _ in range(n):
            a, b = self.t, self.t + h
            while self._pending and self._pending[0][0] <= b:
                due, ce, cf = self._pending.popleft()
                if due > a:
                    X, V, Pe, Pf = hold(X, V, Pe, Pf, a, due)
                    a = due
                self.cmd[:] = (ce, cf)
            if b > a:
                X, V, Pe, Pf = hold(X, V, Pe, Pf, a, b)
            self.t = b
        if not (math.isfinite(X) and math.isfinite(V)):
            self.faults_flags |= proto.FAULT_SENSOR
            return
        lo, hi = END_STOPS_M  # the leg rests on its end stops outside this range
        if X < lo or X > hi:
            X, V = min(max(X, lo), hi), 0.0
        self.state[:] = (X, V, Pe, Pf)

    def _vent(self, reason_flag: int) -> None:
        self._pending.clear()  # the vent valves open at once, whatever was in flight
        self.session_t0 = None  # the next command starts a new session (disturbance clock)
        self.cmd[:] = 0.0
        self.vented = True
        self.faults_flags |= reason_flag

    # -- link -------------------------------------------------------------------------------
    def _handle(self, msg: Any, now: float) -> None:
        if isinstance(msg, proto.Command):
            self.stats.commands += 1
            self.stats.last_command_time = now
            self._last_cmd_seq = msg.seq
            if self.session_t0 is None:
                self.session_t0 = self.t
            if not (math.isfinite(msg.pe_Pa) and math.isfinite(msg.pf_Pa)):
                self._vent(proto.FAULT_OVERPRESSURE)
                return
            self._pending.append((self.t + self.dead_time_s, min(max(msg.pe_Pa, 0.0), 10 * BAR),
                                  min(max(msg.pf_Pa, 0.0), 10 * BAR)))
            self.vented = False
            self.faults_flags &= ~(proto.FAULT_WATCHDOG_VENT | proto.FAULT_VENTED)
            if self.lockstep_dt_s is not None:
                self._advance(self.lockstep_dt_s)
                self._telemetry(now)
        elif isinstance(msg, proto.Vent):
            self._vent(proto.FAULT_VENTED)

    def _telemetry(self, now: float) -> None:
        f = self.faults
        X, V, Pe, Pf = self.state
        noise = self.rng.standard_normal(4) * [f.position_noise_m, f.velocity_noise_mps,
                                               f.pressure_noise_bar * BAR,
                                               f.pressure_noise_bar * BAR]
        self._seq += 1
        msg = proto.Telemetry(self._seq & 0xFFFFFFFF, int(now * 1e6), float(X + noise[0]),
                              float(V + noise[1]), float(Pe + noise[2]), float(Pf + noise[3]),
                              int(self.faults_flags), self._last_cmd_seq)
        data = bytearray(proto.encode(msg))
        if self.rng.random() < f.drop_prob:
            self.stats.dropped += 1
            return
        if self.rng.random() < f.corrupt_prob:
            i = int(self.rng.integers(2, len(data)))
            data[i] ^= 0xFF
            self.stats.corrupted += 1
        delay = f.latency_s + f.jitter_s * self.rng.random()
        if self.rng.random() < f.late_prob:
            delay += f.late_s
            self.stats.late += 1
        self._outbox.append((now + delay, bytes(data)))

    def _flush(self, now: float) -> None:
        due = [d for d in self._outbox if d[0] <= now]
        if due:
            self._outbox = [d for d in self._outbox if d[0] > now]
            for _, data in sorted(due, key=lambda d: d[0]):
                self.link.send(data)
                self.stats.telemetry_sent += 1

    def run(self, duration_s: float | None = None) -> None:
        """Serve until ``stop()`` (or for ``duration_s``): real-time plant, commands in,
        telemetry out, watchdog."""
        if duration_s is not None:
            check_range("duration_s", duration_s, 0.0, 1e7, low_open=True, unit="s")
        t_last = time.monotonic()
        next_tel = t_last
        t_end = math.inf if duration_s is None else t_last + duration_s
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= t_end:
                break
            wait = max(0.0, min(next_tel, *(d[0] for d in self._outbox)) - now) \
                if self._outbox else max(0.0, next_tel - now)
            data = self.link.recv(min(wait, self.period))
            now = time.monotonic()
            with self.lock:
                if self.lockstep_dt_s is None:
                    self._advance(now - t_last)
                t_last = now
                if data:
                    before = self.decoder.corrupt
                    for msg in self.decoder.feed(data):
                        self._handle(msg, now)
                    self.stats.corrupt_received += self.decoder.corrupt - before
                last = self.stats.last_command_time
                if not self.vented and math.isfinite(last) and now - last > self.watchdog_s:
                    self._vent(proto.FAULT_WATCHDOG_VENT)
                    self.stats.watchdog_vents += 1
                    self.stats.vent_time = now
                if now >= next_tel:
                    self._telemetry(now)
                    next_tel += self.period
                    if next_tel < now:  # fell behind: skip, do not burst
                        next_tel = now + self.period
                self._flush(now)

    def stop(self) -> None:
        self._stop.set()

    def start_thread(self) -> threading.Thread:
        """Serve in a daemon thread (tests, ``--dry-run``)."""
        th = threading.Thread(target=self.run, name="mpa-gym-emulator", daemon=True)
        th.start()
        return th


class EmulatorProcess:
    """``mpa-gym emulate --udp`` in a child process (benchmarks, tests): the rig on another
    process, as a real device is, so that its loop and the PC's do not share an interpreter.

    A context manager; :attr:`url` is the device URL. ``scenario`` is a name or YAML path (or a
    dict, written to a temporary file); ``args`` are further ``emulate`` flags.
    """

    def __init__(self, scenario: Any = "nominal", args: tuple[str, ...] = (),
                 start_timeout_s: float = 60.0) -> None:
        import subprocess
        import sys
        import tempfile

        import yaml

        self._tmp = None
        if isinstance(scenario, dict):
            self._tmp = tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False)
            yaml.safe_dump(scenario, self._tmp)
            self._tmp.close()
            scenario = self._tmp.name
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mpa_gym.agents.cli", "emulate", "--udp", "--scenario",
             str(scenario), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line, said = "", []
        deadline = time.monotonic() + start_timeout_s
        while "udp://" not in line and time.monotonic() < deadline:
            line = self.proc.stderr.readline()
            if line.strip():
                said.append(line.strip())
            if not line and self.proc.poll() is not None:
                break
        if "udp://" not in line:
            self.close()
            # the child's own last word: its one-line error, or the last line of a traceback
            why = said[-1] if said else f"exit code {self.proc.returncode}, nothing on stderr"
            if why.startswith("mpa-gym emulate: error: "):  # bad input: the caller's ValueError
                raise ValueError(why.removeprefix("mpa-gym emulate: error: "))
            raise RuntimeError(f"the emulator process did not start: {why}")
        self.url = line.split("at ", 1)[1].split()[0]

    def close(self) -> None:
        """Stop the child (SIGINT: the emulator's own Ctrl-C path) and wait for it."""
        import os
        import signal

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=5.0)
            except Exception:
                self.proc.kill()
                self.proc.wait()
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()
        if self._tmp is not None:
            os.unlink(self._tmp.name)
            self._tmp = None

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
