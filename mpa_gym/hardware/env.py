"""``HardwareLegEnv`` (``MPALegHardware-v0``): the sim envs' interface on the real rig.

Same spaces, reward, safety layer and ``info`` keys as ``MPALeg-v0`` / ``MPALegResidual-v0``
(``residual=True``), from the same task layer; the plant is whatever answers on the link. The
loop runs at a fixed rate (``control_hz``, 100 Hz default, up to 500 Hz) against monotonic-clock
deadlines: each ``step`` sends its command, waits for the next deadline while reading telemetry,
and observes the newest telemetry. Overruns, command-to-acknowledge latency and period jitter
go into ``info``.

Safety, in the order it acts: the action is clipped to [−1, 1]; the command is slew-limited and
clipped to [0, p_max]; the episode ends (and the rig is vented) when X leaves its bounds, when
no fresh telemetry arrived for ``stale_s`` (lost or late link), when a measured pressure exceeds
p_max + ``overpressure_margin_bar``, or when the device reports a fault. ``close()``, an exception
inside ``step`` / ``reset`` and Ctrl-C vent both MPAs; so does the interpreter exiting with the
env open. The device's own watchdog vents when commands stop (the emulator plays it).

The joint stiffness in ``info["k_N_per_m"]`` (and the stiffness reward) is Eq. (23) of the
*nominal* model at the measured state and pressures: the rig has no stiffness sensor.
"""

from __future__ import annotations

import atexit
import math
import time
import weakref
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from mpa_gym.hardware import protocol as proto
from mpa_gym.hardware.transport import Transport, open_transport
from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_range
from mpa_gym.task.config import TaskConfig, action_space, observation_space
from mpa_gym.task.kernels import command_from_action, reward_terms, safe_command
from mpa_gym.task.plan import make_plan


class HardwareFault(RuntimeError):
    """The rig was vented because of a safety stop; the message says which and why."""


def _vent_at_exit(ref: weakref.ReferenceType) -> None:
    env = ref()
    if env is not None:
        env.close()


class HardwareLegEnv(gym.Env[np.ndarray, np.ndarray]):
    """The MPA leg rig behind the sim envs' interface (module docstring).

    Arguments: ``device`` (``"serial:///dev/ttyACM0"``, ``"udp://HOST:PORT"`` or an open
    ``Transport``), ``scenario``, ``stiffness`` and ``task`` as for the sim envs, ``residual``
    (the ``MPALegResidual-v0`` action), ``control_hz`` (1…500), ``stale_s`` (telemetry age that
    stops the episode), ``settle_s`` (how long ``reset`` holds the start pressures),
    ``overpressure_margin_bar``, ``connect_timeout_s``, ``settle_timeout_s`` (how long
    ``reset`` may wait beyond ``settle_s`` for the leg to rest within 5 mm of the start).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, device: str | Transport, scenario: Any = "nominal", stiffness: Any = None,
                 task: dict[str, Any] | None = None, residual: bool = False,
                 control_hz: float = 100.0, stale_s: float = 0.03, settle_s: float = 0.5,
                 overpressure_margin_bar: float = 0.5, connect_timeout_s: float = 2.0,
                 settle_timeout_s: float = 10.0, params: Params = DEFAULT_PARAMS) -> None:
        check_range("control_hz", control_hz, 1.0, 500.0, unit="Hz")
        check_range("stale_s", stale_s, 1e-3, 1.0, unit="s")
        check_range("settle_s", settle_s, 0.0, 30.0, unit="s")
        check_range("overpressure_margin_bar", overpressure_margin_bar, 0.0, 3.0, unit="bar")
        task = dict(task or {})
        if "dt_s" in task:
            raise ValueError("task.dt_s: the hardware env's period is 1/control_hz")
        self.cfg = TaskConfig.from_kwargs({**task, "dt_s": 1.0 / control_hz})
        self.plan = make_plan(scenario, stiffness, self.cfg, params)
        self.residual = bool(residual)
        self.action_space = action_space()
        self.observation_space = observation_space(self.cfg, self.residual)
        self.nominal = fast.pack(params)
        # compile (or load) the task kernels now: a first call inside step() would take longer
        # than the device's watchdog allows between two commands
        command_from_action(0.0, 0.0, True, 1.0, 1.0)
        safe_command(0.0, 0.0, 1.0, 1.0)
        reward_terms(0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.5, 0.1)
        fast.force_and_stiffness(0.8, 0.0, 0.0, 0.0, self.nominal)
        self.stale_s, self.settle_s = stale_s, settle_s
        self.settle_timeout_s = check_range("settle_timeout_s", settle_timeout_s, 0.0, 600.0,
                                            unit="s")
        self.p_limit = (self.cfg.p_max_bar + overpressure_margin_bar) * BAR
        self.link = device if isinstance(device, Transport) else open_transport(
            device, connect_timeout_s)
        self.decoder = proto.FrameDecoder()
        self._seq = 0
        self._tel: Any = None  # newest telemetry
        self._tel_time = -math.inf  # [s] monotonic time it arrived
        self._sent: dict[int, float] = {}  # command seq -> send time, for latency
        self._latency: list[float] = []
        self._closed = False
        self._done = True
        self.overruns = 0
        self.late_telemetry = 0
        self.timing: dict[str, list[float]] = {"period_s": [], "latency_s": []}
        atexit.register(_vent_at_exit, weakref.ref(self))

    # -- link -------------------------------------------------------------------------------
    def _send(self, msg_type: type, *payload: float) -> None:
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        now = time.monotonic()
        self.link.send(proto.encode(msg_type(self._seq, int(now * 1e6), *payload)))
        if msg_type is proto.Command:
            self._sent[self._seq] = now

    def _read(self, until: float) -> None:
        """Read telemetry until the monotonic time ``until`` (at least one poll)."""
        while True:
            now = time.monotonic()
            data = self.link.recv(max(0.0, min(until - now, 0.002)))
            t = time.monotonic()
            for msg in self.decoder.feed(data) if data else ():
                if isinstance(msg, proto.Telemetry):
                    if self._tel is None or msg.seq > self._tel.seq:
                        self._tel, self._tel_time = msg, t
                    if msg.ack_seq in self._sent:  # first word that the command was applied
                        self._latency.append(t - self._sent.pop(msg.ack_seq))
                        self._sent = {s: v for s, v in self._sent.items() if s > msg.ack_seq}
            if t >= until:
                return

    def vent(self) -> None:
        """Vent both MPAs (sent three times: UDP may lose one)."""
        for _ in range(3):
            try:
                self._send(proto.Vent)
            except OSError:
                return

    # -- safety -----------------------------------------------------------------------------
    def _check(self) -> str | None:
        """The reason to stop, or None."""
        now = time.monotonic()
        if self._tel is None or now - self._tel_time > self.stale_s:
            age = now - self._tel_time
            return (f"stale telemetry: newest is {age * 1e3:.1f} ms old (limit "
                    f"{self.stale_s * 1e3:.0f} ms); check the link and the device")
        t = self._tel
        if not all(math.isfinite(v) for v in (t.x_m, t.v_mps, t.pe_Pa, t.pf_Pa)):
            return f"sensor fault: non-finite telemetry {t}"
        if max(t.pe_Pa, t.pf_Pa) > self.p_limit:
            return (f"over-pressure: measured ({t.pe_Pa / BAR:.2f}, {t.pf_Pa / BAR:.2f}) bar "
                    f"> limit {self.p_limit / BAR:.2f} bar")
        if t.faults & (proto.FAULT_WATCHDOG_VENT | proto.FAULT_OVERPRESSURE
                       | proto.FAULT_SENSOR):
            return f"device fault flags 0x{t.faults:02x}"
        return None

    # -- gym API ----------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if options:
            raise ValueError(f"reset options {sorted(options)}: the rig's plant cannot be set; "
                             "the hardware env takes no options")
        try:
            p0 = self.plan.p0
            x_start = float(self.plan.x_ref[0])
            t0 = time.monotonic()
            while True:  # hold the start pressures (feeding the device's watchdog) until the
                # leg rests near the start height, at least settle_s
                self._send(proto.Command, float(p0[0]), float(p0[1]))
                self._read(time.monotonic() + self.cfg.dt_s)
                waited = time.monotonic() - t0
                tel = self._tel
                at_rest = tel is not None and abs(tel.x_m - x_start) < 0.005 and \
                    abs(tel.v_mps) < 0.02
                if waited >= self.settle_s and at_rest:
                    break
                if waited > self.settle_s + self.settle_timeout_s:
                    where = "no telemetry" if tel is None else (
                        f"X = {tel.x_m:.4f} m, V = {tel.v_mps:.3f} m/s")
                    raise HardwareFault(f"reset: the leg did not come to rest at X = "
                                        f"{x_start:.3f} m within {waited:.1f} s ({where}); "
                                        "check the link, the supply pressure and the leg")
            reason = self._check()
            if reason is not None:
                raise HardwareFault(reason)
        except BaseException:
            self.vent()
            raise
        self._prev = p0.astype(float).copy()
        self._j = 0
        self._deadline = time.monotonic()  # the first period starts now
        self._last_start = math.nan
        self.overruns = 0
        self._done = False
        obs = self._observe()
        t = self._tel
        k0 = fast.force_and_stiffness(t.x_m, t.v_mps, t.pe_Pa, t.pf_Pa, self.nominal)[1]
        return obs, self._info(np.zeros(4), 0, p0, k0)

    def _observe(self) -> np.ndarray:
        t, p, j = self._tel, self.plan, self._j
        obs = [t.x_m, t.v_mps, p.x_ref[j], p.v_ref[j], p.sin_phase[j], p.cos_phase[j],
               t.pe_Pa / BAR, t.pf_Pa / BAR]
        if self.residual:
            obs.append(p.k_ref[j] / 1000.0)
        return np.array(obs, dtype=np.float32)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._done:
            raise RuntimeError("step() on a finished (or never started) episode: call reset()")
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (2,):
            raise ValueError(f"action has shape {a.shape}; expected (2,) (extensor, flexor) in "
                             "[-1, 1]")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action={a.tolist()} must be finite; allowed range [-1, 1]")
        a = np.clip(a, -1.0, 1.0)
        try:
            return self._step(a)
        except BaseException:
            self.vent()
            self._done = True
            raise

    def _step(self, a: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        c, p, j = self.cfg, self.plan, self._j
        start = time.monotonic()
        # the period started at self._deadline; a caller that needs more than a quarter period
        # to answer sends its command late: an overrun
        if start - self._deadline > 0.25 * c.dt_s:
            self.overruns += 1
        period = start - self._last_start
        self._last_start = start
        cmd, flags = np.zeros(2), 0
        for m in range(2):
            raw = command_from_action(a[m], p.ff[j, m], self.residual,
                                      c.residual_scale_bar * BAR, c.p_max_bar * BAR)
            cmd[m], f = safe_command(raw, self._prev[m], c.p_max_bar * BAR, c.max_delta_Pa)
            flags |= f
        self._prev = cmd
        self._send(proto.Command, float(cmd[0]), float(cmd[1]))
        sent = self._seq
        self._deadline = max(self._deadline + c.dt_s, start)  # this period's end
        self._read(self._deadline)
        # the observation must show this period's command applied; if the acknowledging
        # telemetry is late, wait for it up to stale_s (a late period, counted)
        give_up = self._deadline + self.stale_s
        if self._tel is not None and self._tel.ack_seq != sent:
            self.late_telemetry += 1
            while (self._tel is None or self._tel.ack_seq != sent) and \
                    time.monotonic() < give_up:
                self._read(time.monotonic() + 0.001)
        self._j = j = j + 1
        reason = self._check()
        t = self._tel
        _, k = fast.force_and_stiffness(t.x_m, t.v_mps, t.pe_Pa, t.pf_Pa, self.nominal)
        r = reward_terms(t.x_m - p.x_ref[j], k, p.k_ref[j], a[0], a[1], c.sigma_x_m, c.sigma_k,
                         c.stiffness_weight(self.residual), c.w_effort)
        out_of_bounds = not (c.x_min_m <= t.x_m <= c.x_max_m)
        terminated = out_of_bounds or reason is not None
        truncated = j >= p.n_steps and not terminated
        if math.isfinite(period):
            self.timing["period_s"].append(period)
        latency = self._latency[-1] if self._latency else math.nan
        self.timing["latency_s"].append(latency)
        info = self._info(np.array(r), flags, cmd, k, period, latency)
        if reason is not None:
            info["fault"] = reason
        if terminated:
            self.vent()
        self._done = terminated or truncated
        reward = float(r[0]) if not terminated else 0.0
        return self._observe(), reward, terminated, truncated, info

    def _info(self, r: np.ndarray, flags: int, cmd: np.ndarray, k: float,
              period: float = math.nan, latency: float = math.nan) -> dict[str, Any]:
        t, p, j = self._tel, self.plan, self._j
        return {
            "x_m": float(t.x_m), "x_ref_m": float(p.x_ref[j]), "k_N_per_m": float(k),
            "k_ref_N_per_m": float(p.k_ref[j]), "pressure_cmd_bar": np.asarray(cmd) / BAR,
            "pressure_bar": np.array([t.pe_Pa, t.pf_Pa]) / BAR,
            "reward_position": float(r[1]), "reward_stiffness": float(r[2]),
            "reward_effort": float(r[3]), "safety": int(flags), "t_s": j * self.cfg.dt_s,
            "overruns": self.overruns, "period_s": period,
            "jitter_s": period - self.cfg.dt_s if math.isfinite(period) else math.nan,
            "latency_s": latency, "corrupt_frames": self.decoder.corrupt,
            "late_telemetry": self.late_telemetry,
            "device_faults": int(t.faults),
        }

    def close(self) -> None:
        """Vent both MPAs and close the link (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.vent()
        finally:
            self.link.close()

    def __enter__(self) -> HardwareLegEnv:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
