"""Closed-loop homing: the law, the sim envs' option, and the rig's reset against the emulator
playing legs that are not the nominal model."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
import pytest
from conftest import REALTIME

import mpa_gym  # noqa: F401
from mpa_gym.hardware import protocol as proto
from mpa_gym.hardware.emulator import Emulator, EmulatorProcess
from mpa_gym.hardware.env import HardwareFault, HardwareLegEnv
from mpa_gym.hardware.transport import UDPServer
from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.homing import HomingConfig, HomingController, HomingError, vented_rest
from mpa_gym.task.plan import make_plan

pytestmark = REALTIME  # a device loop in another process: conftest.REALTIME

TASK = {"episode_s": 1.0}
C1 = DEFAULT_PARAMS.mpa.C1
M = DEFAULT_PARAMS.leg.m
# the off-nominal rig's offsets (docs/design.md#reference-plants): +0.6 kg, C1 10 % lower
HEAVY = {"extra_mass_kg": 0.6, "C1_Pa": 0.9 * C1}


def test_holding_pressure_balances_the_weight_on_the_nominal_model():
    # Eq. (5) at V = 0 with the returned extensor pressure gives F = m g (F is affine in P'_e,
    # so the one-division solve is exact up to round-off)
    plan = make_plan()
    ctrl = HomingController(HomingConfig(), 0.8, plan.p0, 0.01, 7 * BAR)
    c = fast.pack(DEFAULT_PARAMS)
    for x in (0.74, 0.78, 0.8, 0.83):
        pe = ctrl.holding_pressure(x)
        f = fast.ground_force(x, 0.0, pe, plan.p0[1], c)
        np.testing.assert_allclose(f, M * DEFAULT_PARAMS.leg.g, rtol=1e-10)


def test_vented_rest_is_a_static_equilibrium():
    c = fast.pack(DEFAULT_PARAMS)
    x = vented_rest(c)
    assert 0.69 < x < 0.8
    np.testing.assert_allclose(fast.ground_force(x, 0.0, 0.0, 0.0, c), M * DEFAULT_PARAMS.leg.g,
                               rtol=1e-8)


# corners of the plausible-rig box (mass −20 … +50 %, muscles ±20 %), with a slow regulator:
# 40 ms lag and 30 ms dead time (3 control periods)
CORNERS = [{"mass_kg": M * dm, "C1_Pa": C1 * dc} for dm in (0.8, 1.5) for dc in (0.8, 1.2)]


@pytest.mark.parametrize("plant", [*CORNERS, HEAVY], ids=lambda p: str(p))
def test_sim_homing_brings_any_plausible_leg_to_the_start_and_hands_over(plant):
    cfg = HomingConfig()
    env = gym.make("MPALegResidual-v0", task=TASK,
                   scenario={"name": "slow", "duration_s": 1.0,
                             "plant": {"pressure_lag_s": 0.04, "pressure_dead_time_s": 0.03}})
    obs, info = env.reset(seed=0, options={"homing": True, "plant": plant})
    x_start = env.unwrapped.plan.x_ref[0]
    assert abs(obs[0] - x_start) < cfg.tolerance_m
    assert abs(obs[1]) < cfg.velocity_tolerance_mps
    assert 0.0 < info["homing_s"] <= cfg.timeout_s
    held = info["pressure_cmd_bar"]
    # hand-over: the first command of the episode is slew-limited from the held one
    *_, info1 = env.step(np.ones(2))
    max_step = TaskConfig(**TASK).max_delta_Pa / BAR
    assert np.all(np.abs(info1["pressure_cmd_bar"] - held) <= max_step + 1e-9)


def test_sim_homing_failure_names_what_was_measured():
    env = gym.make("MPALegResidual-v0", task=TASK)
    with pytest.raises(HomingError, match=r"within 0.5 s \(measured X = 0\.\d+ m, V = "):
        env.reset(seed=0, options={"homing": {"timeout_s": 0.5}})


def test_homing_settings_are_validated():
    with pytest.raises(ValueError, match=r"homing.kp_bar_per_m=-1 bar/m is outside the allowed "
                                         r"range \[0, 200\]"):
        HomingConfig(kp_bar_per_m=-1)
    with pytest.raises(ValueError, match=r"homing: unknown key\(s\) \['gain'\]"):
        HomingConfig.from_option({"gain": 3})
    env = gym.make("MPALegResidual-v0", task=TASK)
    with pytest.raises(ValueError, match=r"homing.timeout_s=0 s is outside"):
        env.reset(options={"homing": {"timeout_s": 0}})


def serve(scenario, **kw):
    link = UDPServer("127.0.0.1", 0)
    emu = Emulator(link, scenario, **kw)
    return f"udp://127.0.0.1:{link.address[1]}", emu, link, emu.start_thread()


def heavy_scenario():
    return {"name": "heavy", "duration_s": 30.0, "plant": HEAVY}


def test_rig_reset_homes_a_heavy_leg_from_its_vented_rest_in_another_process():
    # The emulator, in its own process, plays a leg 0.6 kg heavier with 10 % softer muscles;
    # the reset vents first (no telemetry yet), so the leg starts from where it rests vented.
    cfg = HomingConfig()
    with EmulatorProcess(heavy_scenario()) as emu, \
            HardwareLegEnv(emu.url, residual=True, task=TASK, stale_s=0.1) as hw:
        obs, info = hw.reset(seed=0)
        x_start = hw.plan.x_ref[0]
        assert abs(obs[0] - x_start) < cfg.tolerance_m, obs[0]
        assert abs(obs[1]) < cfg.velocity_tolerance_mps
        # the heavy leg needs more than the design's start pressure to stay at the start
        assert info["pressure_cmd_bar"][0] > hw.plan.p0[0] / BAR + 0.2
        held = info["pressure_cmd_bar"]
        *_, info1 = hw.step(np.zeros(2))
        assert "fault" not in info1
        assert np.all(np.abs(info1["pressure_cmd_bar"] - held) <= hw.cfg.max_delta_Pa / BAR
                      + 1e-6)  # float32 on the wire


@pytest.mark.parametrize("state", ["lower", "upper"])
def test_rig_homes_from_either_side(state):
    # resting low (vented, on the muscles' elastic stop) or held high (3.6 bar: X ≈ 0.815 m)
    c = fast.pack(DEFAULT_PARAMS)
    init = (vented_rest(c), 0.0, 0.0, 0.0) if state == "lower" else None
    if state == "upper":
        ctrl = HomingController(HomingConfig(), 0.8, make_plan().p0, 0.01, 7 * BAR)
        x = 0.815
        init = (x, 0.0, ctrl.holding_pressure(x), make_plan().p0[1])
    url, emu, link, thread = serve("nominal", initial_state=init)
    try:
        with HardwareLegEnv(url, task=TASK, stale_s=0.1) as hw:
            obs, _ = hw.reset(seed=0)
            assert abs(obs[0] - hw.plan.x_ref[0]) < HomingConfig().tolerance_m
    finally:
        emu.stop()
        thread.join(timeout=2.0)
        link.close()


def test_rig_homing_failure_vents_and_names_what_was_measured():
    url, emu, link, thread = serve(heavy_scenario())
    try:
        with HardwareLegEnv(url, task=TASK, stale_s=0.1,
                            homing={"timeout_s": 0.3}) as hw:
            with pytest.raises(HardwareFault, match=r"reset: homing: .* within 0.3 s "
                                                    r"\(measured X = 0\.\d{4} m, V = "):
                hw.reset(seed=0)
            time.sleep(0.02)
            assert emu.vented and emu.faults_flags & proto.FAULT_VENTED
    finally:
        emu.stop()
        thread.join(timeout=2.0)
        link.close()
