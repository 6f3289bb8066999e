"""What the rig's loop does when it cannot hold its rate: a slow policy step, late telemetry;
and the real-time context."""

from __future__ import annotations

import gc
import os
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REALTIME

from mpa_gym.hardware import protocol as proto
from mpa_gym.hardware.emulator import Emulator, LinkFaults
from mpa_gym.hardware.env import HardwareLegEnv
from mpa_gym.hardware.realtime import realtime
from mpa_gym.hardware.transport import UDPServer

pytestmark = REALTIME  # a device loop in another process: conftest.REALTIME

TASK = {"episode_s": 2.0}
# stale_s relaxed to 0.2 s, as in test_hardware.py and test_rollout_safety.py: every wait below is
# either well inside it (≤ stale_s / 4) or well beyond it (2 × stale_s), so that a scheduling
# hiccup of the shared 2-core test machine (tens of ms) cannot move a step across it
STALE_S = 0.2
RIG = str(Path(__file__).resolve().parents[1] / "configs" / "rigs" / "offnominal.yaml")


@pytest.fixture
def rig():
    """(device URL, emulator) on UDP loopback, the emulator's watchdog relaxed to 2 s (beyond
    every wait of these tests) so that what the tests see is the env's own decision, not the
    device venting by itself."""
    link = UDPServer("127.0.0.1", 0)
    emu = Emulator(link, "nominal", watchdog_s=2.0)
    thread = emu.start_thread()
    yield f"udp://127.0.0.1:{link.address[1]}", emu
    emu.stop()
    thread.join(timeout=2.0)
    link.close()


def wait_for(condition, timeout_s=5.0):
    """Until ``condition()`` (the emulator's thread handles what was sent), or fail."""
    end = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < end, "not within the timeout"
        time.sleep(0.005)


def test_slow_policy_step_holds_then_stops(rig):
    url, emu = rig
    with HardwareLegEnv(url, task=TASK, stale_s=STALE_S) as hw:
        hw.reset(seed=0)
        hw.step(np.zeros(2))
        held, overruns = emu.cmd.copy(), hw.overruns
        time.sleep(STALE_S / 4)  # the policy takes 50 ms: five periods late, inside stale_s
        np.testing.assert_array_equal(emu.cmd, held)  # the device held the last command
        *_, term, _, info = hw.step(np.zeros(2))
        assert not term and "fault" not in info
        assert info["overruns"] >= overruns + 1  # counted, and the step went on
        commands = emu.stats.commands
        time.sleep(2 * STALE_S)  # the observation it acts on is older than stale_s
        *_, term, _, info = hw.step(np.zeros(2))
        assert term and "slow policy step" in info["fault"], info.get("fault")
        wait_for(lambda: emu.vented)  # the rig was vented ...
        assert emu.stats.watchdog_vents == 0  # ... by the env, not by the device's watchdog
        # the vent went out after the step; the stale action (before it) was never sent
        assert emu.stats.commands == commands


def test_late_telemetry_is_waited_for_then_stops_when_stale(rig):
    url, emu = rig
    with HardwareLegEnv(url, task=TASK, stale_s=STALE_S) as hw:
        hw.reset(seed=0)
        # every frame 50 ms late: five periods after the step's deadline, inside stale_s
        emu.faults = LinkFaults(latency_s=STALE_S / 4)
        late0 = hw.late_telemetry
        for _ in range(5):
            commands = emu.stats.commands
            *_, term, _, info = hw.step(np.zeros(2))
            assert not term and "fault" not in info
            assert emu.stats.commands == commands + 1  # one command per period, held
            assert hw.telemetry.ack_seq == hw._seq  # the observation shows this period's command
        # each step waited for its acknowledgement (one may escape the count: a stall of 40 ms
        # between its command and its deadline lets the late frame in on time)
        assert info["late_telemetry"] >= late0 + 4
        # the device keeps streaming telemetry but stops taking commands: frames arrive, none
        # acknowledges the period's command
        emu.faults = LinkFaults()
        handle = emu._handle
        emu._handle = lambda msg, now: None if isinstance(msg, proto.Command) else handle(msg, now)
        *_, term, _, info = hw.step(np.zeros(2))
        assert term and "late telemetry: no frame acknowledged" in info["fault"], info
        assert emu.stats.watchdog_vents == 0  # the env stopped, not the device's watchdog
        emu._handle = handle


def test_deferred_work_runs_after_the_command_went_out_once_and_in_order(rig):
    """``defer`` moves work (the rollout's log write) off the path from telemetry to command:
    it runs inside the next step, after that step's command reached the link, and a failing
    step (which vents) or ``close`` still runs what is pending."""
    url, _emu = rig
    seen: list[tuple[str, int]] = []
    with HardwareLegEnv(url, task=TASK, stale_s=STALE_S) as hw:
        hw.reset(seed=0)
        hw.step(np.zeros(2))
        for tag in ("a", "b"):  # both run in the next step, in order, each with the seq then
            hw.defer(lambda tag=tag: seen.append((tag, hw._seq)))
        assert seen == []  # nothing runs when handed over
        sent_before = hw._seq
        hw.step(np.zeros(2))
        # the next step's command had been sent (its seq taken) before the work ran
        assert seen == [("a", sent_before + 1), ("b", sent_before + 1)]
        hw.step(np.zeros(2))
        assert len(seen) == 2  # once only
        hw.defer(lambda: seen.append(("c", hw._seq)))
        with pytest.raises(ValueError, match="must be finite"):  # refused before any command
            hw.step(np.array([np.nan, 0.0]))
        assert len(seen) == 2  # still pending: the episode goes on
        hw.step(np.zeros(2))
        assert seen[-1][0] == "c"

        def fail(*_):
            raise OSError("link down")
        hw.defer(lambda: seen.append(("d", hw._seq)))
        hw.link.send, send = fail, hw.link.send
        with pytest.raises(OSError, match="link down"):
            hw.step(np.zeros(2))  # the command cannot go out: the step fails and vents ...
        hw.link.send = send
        assert seen[-1][0] == "d"  # ... and the work handed over still ran
        hw.defer(lambda: seen.append(("e", -1)))
    assert seen[-1] == ("e", -1)  # close() runs what is left


def test_realtime_context_restores_what_it_changed():
    before = os.sched_getscheduler(0) if hasattr(os, "sched_getscheduler") else None
    assert gc.isenabled()
    with realtime(10) as rt:
        assert not gc.isenabled()
        assert rt["sched_fifo"] or rt["notes"]  # granted, or it says why not
        if rt["sched_fifo"]:
            assert os.sched_getscheduler(0) == os.SCHED_FIFO
    assert gc.isenabled()
    if before is not None:
        assert os.sched_getscheduler(0) == before
    with realtime(sched_fifo=False) as rt:  # what every rollout runs in: the collector off only
        assert not gc.isenabled() and rt == {"sched_fifo": False, "gc_disabled": True,
                                             "notes": []}
        if before is not None:
            assert os.sched_getscheduler(0) == before
    assert gc.isenabled()
    with pytest.raises(ValueError, match=r"priority=0 is outside the allowed range \[1, 99\]"):
        with realtime(0):
            pass


def test_loop_benchmark_puts_each_run_beside_the_machines_floor():
    """``mpa-gym bench --loop``: a rollout against an emulator process, paired with the wait
    alone; the figures are what the rollout's timing says, the floor a real wait."""
    from mpa_gym.agents.rig.rollout import loop_benchmark, wait_floor

    floor = wait_floor(200.0, 0.5)
    assert floor["steps"] == 100 and 0.0 <= floor["overrun_pct"] <= 100.0
    assert floor["p99_late_ms"] >= 0.0  # a wait never ends before its deadline
    # the emulator plays a leg unlike the model: +0.6 kg, C1 −10 %, dead time, lag, slew, friction
    o = loop_benchmark("pid", control_hz=100.0, loop_s=1.0, repeats=1, rig=RIG)
    (pair,) = o["pairs"]
    assert pair["loop"]["steps"] == 100 and pair["loop"]["stopped"] is None
    # homed, then tracking under feedback: a third of the feedforward's 15 mm there at most
    assert pair["loop"]["position_rmse_mm"] < 5.0
    assert o["median"]["loop_overrun_pct"] == pair["loop"]["overrun_pct"]
    with pytest.raises(ValueError, match=r"--repeats=0 must be a whole number in \[1, 100\]"):
        loop_benchmark("pid", repeats=0)
