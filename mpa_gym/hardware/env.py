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
p_max + ``overpressure_margin_bar``, or when the device reports a fault; the step that ends it
carries the reason in ``info["fault"]``. ``close()``, an exception
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
from collections import deque
from collections.abc import Callable
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from mpa_gym.hardware import protocol as proto
from mpa_gym.hardware.transport import Transport, open_transport
from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params, check_range
from mpa_gym.task import contract as C
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.homing import HomingConfig, HomingError, home
from mpa_gym.task.kernels import (
    command_from_action,
    finish_step,
    observe,
    safe_command,
    task_settings,
)
from mpa_gym.task.plan import make_plan

# [Hz] the rig's control rate: the sim's control period by default; what the link and the
# device's watchdog allow at most
CONTROL_HZ = 1.0 / TaskConfig.dt_s
CONTROL_HZ_RANGE = (1.0, 500.0)
SPIN_S = 3e-4  # [s] the loop polls (spins) through this long before each deadline (wait_s)
# What the rig's step info holds beyond the sim envs' (``task.contract.step_info``): its timing
# and link figures, on every step; ``fault`` (why it stopped) on the step that stops it.
# ``command_sent_s`` and ``telemetry_arrived_s`` are on the episode's clock (the PC's monotonic
# time since its first period began): when the step's command went out (NaN: none was sent)
# and when the telemetry frame its observation shows arrived. A step's observation is read
# at the period's end, a period after the period began, but the command goes out when the
# caller answers, later by its compute time, and the newest frame at the period's end is up
# to one telemetry period old: identification (``agents/rig/identify.py``) times the log by
# these, not by the schedule.
LINK_INFO_KEYS = ("overruns", "period_s", "jitter_s", "latency_s", "corrupt_frames",
                  "late_telemetry", "device_faults", "command_sent_s", "telemetry_arrived_s")


def wait_s(left_s: float, spin_s: float) -> float:
    """[s] How long the loop may block in one read with ``left_s`` to its deadline: sleep in
    the select, but poll (spin) through the last ``spin_s``, since a sleeping process is woken
    whenever the OS (or the VM's host) gets round to it; at most 2 ms, to read telemetry as it
    comes."""
    return 0.0 if left_s < spin_s else min(left_s - spin_s, 0.002)


class HardwareFault(RuntimeError):
    """The rig was vented because of a safety stop; the message says which and why."""


def _vent_at_exit(ref: weakref.ReferenceType) -> None:
    env = ref()
    if env is not None:
        env.close()


class HardwareLegEnv(gym.Env[np.ndarray, np.ndarray]):
    """
    ## Description

    The MPA leg rig (`MPALegHardware-v0`) behind the interface of `MPALeg-v0` and
    `MPALegResidual-v0`: the same task layer (spaces, reward, safety layer, `info` keys, the
    step contract of `mpa_gym.task.contract`), with the plant being whatever answers on the link
    (the device emulator, `mpa-gym emulate`, plays it). Commands and telemetry travel in the
    framed wire protocol of `mpa_gym.hardware.protocol`. The loop keeps a fixed rate against
    monotonic-clock deadlines (module docstring).

    ## Action Space

    `Box(-1, 1, (2,), float32)`, extensor first: the pressures (`residual=False`, as
    `MPALeg-v0`) or a residual on the feedforward (`residual=True`, as `MPALegResidual-v0`),
    then the safety layer (slew limit, clip to [0, p_max]). Out-of-range values are clipped to
    [−1, 1]; NaN, ±inf, non-numbers and wrong shapes raise `ValueError` (the rig is not vented).

    ## Observation Space

    `Box(float32, (8,))` (`(9,)` with `residual=True`) from the newest telemetry: X and V from
    the rig's sensors, the measured pressures, and the plan's reference, phase and k̂:

    <observation table>

    ## Rewards

    As the sim envs, composed by the same `mpa_gym.task.kernels.finish_step` (reward, its
    terms, termination; a terminating step earns 0 with all terms 0, whatever stopped it); k
    is Eq. (23) of the *nominal* model at the measured state and pressures (the rig has no
    stiffness sensor).

    ## Starting State

    `reset` brings the leg from wherever it rests to X̂(0) by closed-loop homing
    (`mpa_gym.task.homing.home`, the loop the sim envs' homing runs too: feedforward + a
    slew-limited PI on position, settings in `HomingConfig`), holds it at rest there and hands over:
    the first step's slew limit counts from the homing's last command. If no telemetry has arrived
    yet it vents once first (the one safe command; it also tells a UDP device where to answer). A
    homing failure vents the rig and raises `HardwareFault` naming what was measured. With
    `homing=None` it instead holds the design's start pressures open-loop for at least `settle_s`
    until the leg rests within 5 mm of X̂(0), failing after `settle_timeout_s` more (only a leg that
    matches the model starts that way; the tests that compare the rig with the sim step for step use
    it). `reset(options={"homing": ...})` overrides the setting for one episode; the rig's plant
    cannot be set. `info["homing_s"]` says how long the reset took.

    ## Episode End

    - Termination (the rig is vented, `info["fault"]` says why): X leaves
      [`x_min_m`, `x_max_m`]; no fresh telemetry for `stale_s`; a measured pressure above
      p_max + `overpressure_margin_bar`; a device fault flag; a policy step that acts on
      telemetry older than `stale_s`; no telemetry acknowledging the period's command within
      `stale_s` of the period's end.
    - Timing: a step called more than a quarter period late is an overrun (`info["overruns"]`):
      the device holds the last command meanwhile and the schedule re-anchors at that step (no
      catch-up burst). Telemetry acknowledging a command that is not in at the period's end is
      waited for up to `stale_s` (`info["late_telemetry"]`; the device holds the command), then
      the episode stops.
    - Truncation: after `episode_s` (default: the scenario's `duration_s`).
    - `close()`, an exception inside `step` / `reset`, Ctrl-C and the interpreter exiting with
      the env open vent both MPAs.

    ## Arguments

    - `device`: `"serial:///dev/ttyACM0"`, `"udp://HOST:PORT"` or an open `Transport`.
    - `scenario`, `stiffness`, `task`: as for the sim envs (the period is `1 / control_hz`,
      so `task` takes no `dt_s`).
    - `residual`: the `MPALegResidual-v0` action and observation.
    - `control_hz` (1…500), `stale_s` (telemetry age that stops the episode), `settle_s`,
      `settle_timeout_s`, `overpressure_margin_bar`, `connect_timeout_s`.

    Between episodes, pre-flight checks and tools use the link through `telemetry` (the
    newest frame), `poll(duration_s)`, `hold(pe_bar, pf_bar, duration_s)` and `vent()`.
    During one, `defer(fn)` hands work that need not delay a command (writing the last step's
    log record) to the slack of the next period: it runs right after that step's command is
    sent, while the loop waits for the period's end, instead of between the telemetry and the
    command.

    `info` on every step: the sim envs' keys and `overruns`, `period_s`, `jitter_s`,
    `latency_s` (command to acknowledging telemetry), `corrupt_frames`, `late_telemetry`,
    `device_faults`, `command_sent_s` and `telemetry_arrived_s` (when the step's command went
    out and its observation's frame arrived, on the episode's clock; `LINK_INFO_KEYS`), and
    `fault` when the rig stopped.

    ## Version History

    - v0: initial version.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, device: str | Transport, scenario: Any = "nominal", stiffness: Any = None,
                 task: dict[str, Any] | None = None, residual: bool = False,
                 control_hz: float = CONTROL_HZ, stale_s: float = 0.03, settle_s: float = 0.5,
                 overpressure_margin_bar: float = 0.5, connect_timeout_s: float = 2.0,
                 settle_timeout_s: float = 10.0, params: Params = DEFAULT_PARAMS,
                 homing: HomingConfig | dict[str, Any] | bool | None = True,
                 spin_s: float = SPIN_S) -> None:
        check_range("control_hz", control_hz, *CONTROL_HZ_RANGE, unit="Hz")
        check_range("stale_s", stale_s, 1e-3, 1.0, unit="s")
        check_range("settle_s", settle_s, 0.0, 30.0, unit="s")
        check_range("overpressure_margin_bar", overpressure_margin_bar, 0.0, 3.0, unit="bar")
        task = dict(task or {})
        if "dt_s" in task:
            raise ValueError("task.dt_s: the hardware env's period is 1/control_hz")
        self.cfg = TaskConfig.from_kwargs({**task, "dt_s": 1.0 / control_hz})
        self.plan = make_plan(scenario, stiffness, self.cfg, params)
        self.residual = bool(residual)
        self.action_space = C.action_space()
        self.observation_space = C.observation_space(self.cfg, self.residual)
        self._spec = C.obs_spec(self.residual)  # the observation layout (task.contract)
        self._table = self.plan.table()
        self._settings = task_settings(self.cfg, self.residual)  # what finish_step reads
        self._no_noise = np.zeros(len(C.STATE))  # the rig's sensors add their own
        self.nominal = fast.pack(params)
        self.params = params
        self.homing = HomingConfig.from_option(homing)
        # compile (or load) the task kernels now: a first call inside step() would take longer
        # than the device's watchdog allows between two commands
        command_from_action(0.0, 0.0, True, 1.0, 1.0)
        safe_command(0.0, 0.0, 1.0, 1.0)
        x_rest = params.leg.x_rest
        finish_step(np.zeros(len(C.OUT)), x_rest, 1.0, self._table[0], 0.0, 0.0, self._settings,
                    False)
        fast.force_and_stiffness(x_rest, 0.0, 0.0, 0.0, self.nominal)
        observe(np.zeros(self._spec.shape[0]), x_rest, 0.0, 0.0, 0.0, self._table[0],
                self._no_noise, self._spec)
        self.stale_s, self.settle_s = stale_s, settle_s
        self.spin_s = check_range("spin_s", spin_s, 0.0, 0.5 / control_hz, unit="s",
                                  note="at most half a period")
        self.settle_timeout_s = check_range("settle_timeout_s", settle_timeout_s, 0.0, 600.0,
                                            unit="s")
        self.p_limit = (self.cfg.p_max_bar + overpressure_margin_bar) * BAR
        self.link = device if isinstance(device, Transport) else open_transport(
            device, connect_timeout_s)
        self.decoder = proto.FrameDecoder()
        self._seq = 0
        self._tel: Any = None  # newest telemetry
        self._tel_time = -math.inf  # [s] monotonic time it arrived
        self._t0 = math.nan  # [s] monotonic time the episode's first period began
        self._sent: dict[int, float] = {}  # command seq -> send time, for latency
        self._latency: list[float] = []
        self._closed = False
        self._done = True
        self.overruns = 0  # this episode's (info["overruns"])
        self.session_overruns = 0  # since the env was made, like late_telemetry and timing
        self.late_telemetry = 0
        self.timing: dict[str, list[float]] = {"period_s": [], "latency_s": []}
        self._deferred: deque[Callable[[], Any]] = deque()  # defer(): run in the next slack
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
            data = self.link.recv(wait_s(until - time.monotonic(), self.spin_s))
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

    # -- public link API (pre-flight checks, tools) -------------------------------------------
    @property
    def telemetry(self) -> proto.Telemetry | None:
        """The newest telemetry frame received (None before the first)."""
        return self._tel

    def poll(self, duration_s: float) -> proto.Telemetry | None:
        """Read telemetry for ``duration_s`` (at least one poll) without commanding; returns the
        newest frame. The device's watchdog vents if no command follows within its limit."""
        self._read(time.monotonic() + duration_s)
        return self._tel

    def hold(self, pe_bar: float, pf_bar: float, duration_s: float) -> proto.Telemetry | None:
        """Command (P'_e, P'_f) [bar] once per control period for ``duration_s`` (feeding the
        device's watchdog), reading telemetry; returns the newest frame. Outside an episode
        only (``reset`` / ``step`` own the link during one); the pressures must lie in
        [0, p_max]."""
        if not self._done:
            raise RuntimeError("hold() during an episode: the episode's steps command the rig")
        for name, v in (("pe_bar", pe_bar), ("pf_bar", pf_bar)):
            check_range(name, v, 0.0, self.cfg.p_max_bar, unit="bar")
        end = time.monotonic() + duration_s
        while True:
            self._send(proto.Command, pe_bar * BAR, pf_bar * BAR)
            self._read(min(end, time.monotonic() + self.cfg.dt_s))
            if time.monotonic() >= end:
                return self._tel

    def vent(self) -> None:
        """Vent both MPAs (sent three times: UDP may lose one)."""
        for _ in range(3):
            try:
                self._send(proto.Vent)
            except OSError:
                return

    def defer(self, fn: Callable[[], Any]) -> None:
        """Run ``fn()`` in the slack of the next control period: right after the next
        ``step`` has sent its command, while it waits for the period's end (a log write,
        bookkeeping), so that it does not delay the command. Deferred work runs once, in the
        order given; ``reset``, ``close``, a step that sends no command and a step that fails
        (after venting) run what is pending too, so nothing handed over is lost."""
        self._deferred.append(fn)

    def run_deferred(self) -> None:
        """Run the work ``defer`` handed over that has not run yet, now."""
        while self._deferred:
            self._deferred.popleft()()

    # -- safety -----------------------------------------------------------------------------
    def _check(self, stale_s: float | None = None, watchdog: bool = True) -> str | None:
        """The reason to stop, or None (telemetry older than ``stale_s``, default the env's;
        ``watchdog``: a watchdog vent of the device stops too)."""
        now = time.monotonic()
        stale_s = self.stale_s if stale_s is None else stale_s
        if self._tel is None or now - self._tel_time > stale_s:
            age = now - self._tel_time
            return (f"stale telemetry: newest is {age * 1e3:.1f} ms old (limit "
                    f"{stale_s * 1e3:.0f} ms); check the link and the device")
        t = self._tel
        if not all(math.isfinite(v) for v in (t.x_m, t.v_mps, t.pe_Pa, t.pf_Pa)):
            return f"sensor fault: non-finite telemetry {t}"
        if max(t.pe_Pa, t.pf_Pa) > self.p_limit:
            return (f"over-pressure: measured ({t.pe_Pa / BAR:.2f}, {t.pf_Pa / BAR:.2f}) bar "
                    f"> limit {self.p_limit / BAR:.2f} bar")
        stops = proto.FAULT_OVERPRESSURE | proto.FAULT_SENSOR
        if watchdog:
            stops |= proto.FAULT_WATCHDOG_VENT
        if t.faults & stops:
            names = ", ".join(proto.fault_names(t.faults & stops))
            return (f"device fault flags 0x{t.faults:02x} ({names})" + (
                "; the device's watchdog vented: no command reached it within its limit (the PC "
                "or the link stalled)" if t.faults & proto.FAULT_WATCHDOG_VENT & stops else ""))
        return None

    # -- gym API ----------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.run_deferred()
        options = dict(options or {})
        if set(options) - {"homing"}:
            raise ValueError(f"reset options {sorted(options)}: the rig's plant cannot be set; "
                             "the hardware env takes only 'homing'")
        homing = (HomingConfig.from_option(options["homing"]) if "homing" in options
                  else self.homing)
        t0 = time.monotonic()
        try:
            self._wake()
            if homing is None:
                p_hold = self._settle_open_loop()
            else:
                p_hold = self._home(homing)
            reason = self._check()
            if reason is not None:
                raise HardwareFault(reason)
        except BaseException:
            self.vent()
            raise
        self._prev = p_hold.astype(float).copy()
        self._j = 0
        self._deadline = time.monotonic()  # the first period starts now
        self._t0 = self._deadline  # the episode clock's zero (command_sent_s, ...)
        self._obs_time = self._tel_time  # arrival of the telemetry the observation shows
        self._last_start = math.nan
        self.overruns = 0
        self._done = False
        obs = self._observe()
        t = self._tel
        out = np.zeros(len(C.OUT))  # no reward before a step
        out[C.O_CMDE:C.O_CMDF + 1] = p_hold
        out[C.O_K] = fast.force_and_stiffness(t.x_m, t.v_mps, t.pe_Pa, t.pf_Pa, self.nominal)[1]
        info = self._info(out)
        info["homing_s"] = time.monotonic() - t0
        return obs, info

    def _wake(self) -> None:
        """Make sure telemetry flows: wait briefly, then vent once (safe, and a UDP device
        learns where to answer) and wait up to ``stale_s``-bounded polls for a frame."""
        if self._tel is not None and time.monotonic() - self._tel_time < self.stale_s:
            return
        self._read(time.monotonic() + 0.05)
        if self._tel is None or time.monotonic() - self._tel_time > self.stale_s:
            self.vent()
            end = time.monotonic() + 1.0
            while time.monotonic() < end and (self._tel is None or
                                             time.monotonic() - self._tel_time > self.stale_s):
                self._read(time.monotonic() + 0.01)
        if self._tel is None:
            raise HardwareFault("reset: no telemetry from the device within 1 s of venting; "
                                "check the link and that the device is on")

    def _home(self, cfg: HomingConfig) -> np.ndarray:
        """Closed-loop homing (``mpa_gym.task.homing.home``, the sim's loop too); returns the
        holding command [Pa]."""
        deadline = time.monotonic()

        def period(cmd: np.ndarray) -> tuple[float, float]:
            """Send the command, read telemetry until the period's end; the newest (X, V)."""
            nonlocal deadline
            self._send(proto.Command, float(cmd[0]), float(cmd[1]))
            deadline = max(deadline + self.cfg.dt_s, time.monotonic())
            self._read(deadline)
            # a watchdog vent (the PC stalled for 40 ms) does not stop homing: it drops the leg,
            # which homing then brings back, as from any rest; the timeout still bounds it
            reason = self._check(max(self.stale_s, cfg.stale_s), watchdog=False)
            if reason is not None:
                raise HardwareFault(f"reset (homing): {reason}")
            return self._tel.x_m, self._tel.v_mps

        t = self._tel
        try:
            ctrl = home(cfg, self.plan, self.cfg, self.params, t.x_m, t.v_mps,
                        np.array([t.pe_Pa, t.pf_Pa]), period)
        except HomingError as e:
            raise HardwareFault(f"reset: {e}") from None
        return ctrl.cmd.copy()

    def _settle_open_loop(self) -> np.ndarray:
        """Hold the design's start pressures until the leg rests within 5 mm of the start."""
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
                return p0
            if waited > self.settle_s + self.settle_timeout_s:
                where = "no telemetry" if tel is None else (
                    f"X = {tel.x_m:.4f} m, V = {tel.v_mps:.3f} m/s")
                raise HardwareFault(f"reset: the leg did not come to rest at X = "
                                    f"{x_start:.3f} m within {waited:.1f} s ({where}); "
                                    "check the link, the supply pressure and the leg")

    def _observe(self) -> np.ndarray:
        """The newest telemetry and the plan's row, in the layout of ``task.contract``."""
        t = self._tel
        obs = np.empty(self._spec.shape[0])
        observe(obs, t.x_m, t.v_mps, t.pe_Pa, t.pf_Pa, self._table[self._j], self._no_noise,
                self._spec)
        return obs.astype(np.float32)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._done:
            raise RuntimeError("step() on a finished (or never started) episode: call reset()")
        a = C.check_action(action)  # a refused action: the episode (and deferred work) waits
        try:
            return self._step(a)
        except BaseException:
            self.vent()
            self._done = True
            self.run_deferred()
            raise

    def _step(self, a: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        c, p, j = self.cfg, self.plan, self._j
        start = time.monotonic()
        # the period started at self._deadline; a caller that needs more than a quarter period
        # to answer sends its command late: an overrun. The device holds the last command
        # meanwhile, and the schedule re-anchors at this step (no burst of short periods to
        # catch up). An action computed from telemetry older than stale_s stops the episode
        # instead (the device's watchdog would vent soon after anyway).
        late = start - self._deadline
        if late > 0.25 * c.dt_s:
            self.overruns += 1
            self.session_overruns += 1
        slow = None
        age = start - self._obs_time
        if age > self.stale_s:
            slow = (f"slow policy step: it acted on telemetry {age * 1e3:.1f} ms old (limit "
                    f"stale_s = {self.stale_s * 1e3:.0f} ms); the device held the last command "
                    "meanwhile")
        period = start - self._last_start
        self._last_start = start
        cmd, flags, late_ack, sent_at = self._prev, 0, None, math.nan
        if slow is None:
            cmd = np.zeros(2)
            for m in range(2):
                raw = command_from_action(a[m], p.ff[j, m], self.residual,
                                          c.residual_scale_bar * BAR, c.p_max_bar * BAR)
                cmd[m], f = safe_command(raw, self._prev[m], c.p_max_bar * BAR, c.max_delta_Pa)
                flags |= f
            self._prev = cmd
            self._send(proto.Command, float(cmd[0]), float(cmd[1]))
            sent, sent_at = self._seq, self._sent[self._seq]
            self.run_deferred()  # the command is out: the rest of the period is slack
            # this period's end: one period on, or, after an overrun, one period after this
            # (late) start, so the command still gets a whole period before it is observed
            self._deadline = (start if late > 0.25 * c.dt_s else self._deadline) + c.dt_s
            self._read(self._deadline)
            # the observation must show this period's command applied; if the acknowledging
            # telemetry is late, hold (the device keeps the command) and wait for it up to
            # stale_s (a late period, counted); if it does not come, stop
            give_up = self._deadline + self.stale_s
            if self._tel is not None and self._tel.ack_seq != sent:
                self.late_telemetry += 1
                while (self._tel is None or self._tel.ack_seq != sent) and \
                        time.monotonic() < give_up:
                    self._read(time.monotonic() + 0.001)
            if self._tel is not None and self._tel.ack_seq != sent:
                late_ack = (f"late telemetry: no frame acknowledged this period's command within "
                        f"stale_s = {self.stale_s * 1e3:.0f} ms of the period's end (the newest "
                        f"acknowledges command #{self._tel.ack_seq}, sent #{sent}); check the "
                        "link and the device")
        else:
            self.run_deferred()
            self._read(start)  # the newest telemetry, for the record
        self._j = j = j + 1
        reason = slow or self._check() or late_ack  # silence reads as stale, not late
        self._obs_time = self._tel_time
        t = self._tel
        _, k = fast.force_and_stiffness(t.x_m, t.v_mps, t.pe_Pa, t.pf_Pa, self.nominal)
        out = np.zeros(len(C.OUT))
        out[C.O_CMDE:C.O_CMDF + 1] = cmd
        out[C.O_FLAGS] = flags
        # reward, its terms and termination: the sim's composition (task.kernels.finish_step)
        terminated = finish_step(out, t.x_m, k, self._table[j], a[0], a[1], self._settings,
                                 reason is not None)
        if reason is None and terminated:
            reason = (f"position bound: X = {t.x_m:.4f} m left [{c.x_min_m:g}, "
                      f"{c.x_max_m:g}] m (unstable or too aggressive controller?)")
        truncated = j >= p.n_steps and not terminated
        if math.isfinite(period):
            self.timing["period_s"].append(period)
        latency = self._latency[-1] if self._latency else math.nan
        self.timing["latency_s"].append(latency)
        info = self._info(out, period, latency, sent_at)
        if reason is not None:
            info["fault"] = reason
        if terminated:
            self.vent()
        self._done = terminated or truncated
        return self._observe(), float(out[C.O_R]), terminated, truncated, info

    def _info(self, out: np.ndarray, period: float = math.nan, latency: float = math.nan,
              sent_at: float = math.nan) -> dict[str, Any]:
        """The sim envs' info (``task.contract.step_info`` of the output row ``out`` and the
        newest telemetry) and the rig's ``LINK_INFO_KEYS``."""
        t, j = self._tel, self._j
        state = np.array([getattr(t, name) for name in C.STATE])  # telemetry fields by name
        return {
            **C.step_info(out, state, self._table[j], j * self.cfg.dt_s),
            "overruns": self.overruns, "period_s": period,
            "jitter_s": period - self.cfg.dt_s if math.isfinite(period) else math.nan,
            "latency_s": latency, "corrupt_frames": self.decoder.corrupt,
            "late_telemetry": self.late_telemetry,
            "device_faults": int(t.faults),
            "command_sent_s": sent_at - self._t0,
            "telemetry_arrived_s": self._tel_time - self._t0,
        }

    def close(self) -> None:
        """Vent both MPAs and close the link (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.vent()
        finally:
            try:
                self.run_deferred()
            finally:
                self.link.close()

    def __enter__(self) -> HardwareLegEnv:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# The observation table of the docstring is the step contract's (task.contract).
HardwareLegEnv.__doc__ = (HardwareLegEnv.__doc__ or "").replace(
    "<observation table>", C.obs_table(True).replace("\n", "\n    "))
