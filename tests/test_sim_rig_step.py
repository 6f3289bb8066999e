"""One step for sim and rig: the same terminating step driven through ``MPALeg-v0`` and through
``MPALegHardware-v0`` against the device emulator in another process (``mpa-gym emulate``)
gives the same ``info``, key for key: the reward, its terms, termination and the info dict are
composed once (``task.kernels.finish_step``, ``task.contract.step_info``) for both."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from conftest import REALTIME

import mpa_gym  # noqa: F401
from mpa_gym.hardware.emulator import EmulatorProcess
from mpa_gym.hardware.env import LINK_INFO_KEYS, HardwareLegEnv
from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS
from mpa_gym.task.contract import ST_PE, ST_PF, ST_V, ST_X

# Extensor vented, flexor full, with the slew limit out of the way: the nominal leg, at rest at
# X̂(0) = 0.8 m, falls 2.5 mm in the first period and 7.2 mm more in the second (at ~1 m/s).
COLLAPSE = np.array([-1.0, 1.0])
SLEW = {"episode_s": 1.0, "slew_bar_per_s": 1e4}
# The rig homes to X̂(0) within 0.2 mm and 2 mm/s (the defaults' 1 mm, 10 mm/s would do, but
# tighter keeps the two starts closer than the margins below need)
HOMING = {"tolerance_m": 2e-4, "velocity_tolerance_mps": 2e-3}


def falls() -> tuple[float, float]:
    """[m] X after the first and the second COLLAPSE step of the sim, from rest at X̂(0)."""
    sim = gym.make("MPALeg-v0", task=SLEW)
    sim.reset(seed=0, options={"initial_state": {"x_m": 0.8, "v_mps": 0.0}})
    return sim.step(COLLAPSE)[4]["x_m"], sim.step(COLLAPSE)[4]["x_m"]


@REALTIME
def test_the_same_terminating_step_gives_the_same_info_in_the_sim_and_on_the_rig():
    # The lower bound halfway between the sim's X after steps 1 and 2: both envs terminate on
    # step 2 as long as their X differ by less than half that fall (3.6 mm), which the start
    # (within 0.2 mm and 2 mm/s, so < 0.3 mm apart after 20 ms) and the real-time emulator's
    # timing (a few 0.1 ms at ~1 m/s, bounded below) leave by a wide margin.
    x1, x2 = falls()
    x_min = 0.5 * (x1 + x2)
    assert x1 - x2 > 5e-3
    task = {**SLEW, "x_min_m": x_min}
    sim = gym.make("MPALeg-v0", task=task)
    sim.reset(seed=0)
    sim.step(np.zeros(2))  # compiled now, not between the rig's steps
    # the emulator's watchdog and the env's stale_s relaxed, as in the other rig tests: a
    # scheduling hiccup of the shared test machine must not stop the episode
    with EmulatorProcess("nominal", ("--watchdog", "0.5")) as emu, \
            HardwareLegEnv(emu.url, task=task, stale_s=0.2, homing=HOMING) as hw:
        _, hinfo0 = hw.reset(seed=0)
        start = {"x_m": hinfo0["x_m"], "v_mps": hw.telemetry.v_mps}
        rig = [hw.step(COLLAPSE) for _ in range(2)]
        tel = hw.telemetry  # the frame the terminating step observed
    sim.reset(seed=0, options={"initial_state": start})
    ours = [sim.step(COLLAPSE) for _ in range(2)]
    e = sim.unwrapped.engine

    # both go on after step 1 and terminate on step 2 (not truncated)
    assert [r[2:4] for r in rig] == [r[2:4] for r in ours] == [(False, False), (True, False)], \
        rig[-1][4].get("fault")
    (_, r_rig, *_, hi), (_, r_sim, *_, si) = rig[1], ours[1]
    assert hi["fault"].startswith("position bound: X = ")
    # the same keys: the rig's are the sim's and its link figures, and why it stopped
    assert set(hi) == set(si) | set(LINK_INFO_KEYS) | {"fault"}
    assert set(rig[0][4]) == set(ours[0][4]) | set(LINK_INFO_KEYS)

    # functions of the plan, the step index and the action alone: equal
    for key in ("x_ref_m", "k_ref_N_per_m", "t_s", "safety"):
        assert hi[key] == si[key], key
    np.testing.assert_array_equal(hi["pressure_cmd_bar"], si["pressure_cmd_bar"])
    np.testing.assert_array_equal(si["pressure_cmd_bar"], [0.0, 7.0])  # the commands asked for
    # a terminating step earns 0 and so do its terms, in both (finish_step)
    assert r_rig == r_sim == 0.0
    for key in ("reward_position", "reward_stiffness", "reward_effort"):
        assert hi[key] == si[key] == 0.0, key
    # the regulators follow at once (no lag in the nominal plant), and 0 and 7 bar are exact in
    # the wire's float32: the measured pressures are equal too
    np.testing.assert_array_equal(hi["pressure_bar"], si["pressure_bar"])

    # the state: the emulator runs in real time, its command taking effect when it arrives and
    # its telemetry up to one 1 ms tick old, and the loop's timing slips (period error, command
    # latency) shift when the fall starts and when it is observed; as in test_hardware's
    # real-time comparison, |ΔX| ≤ (2 ms + 2 × slip) × max|V| + 5e-5 m (the start's own offset)
    periods = np.array([r[4]["period_s"] for r in rig])
    slip = np.nanmax(np.abs(periods - hw.cfg.dt_s)) + max(r[4]["latency_s"] for r in rig)
    vmax = max(abs(float(r[0][1])) for r in ours)
    assert abs(hi["x_m"] - si["x_m"]) < (2e-3 + 2 * slip) * vmax + 5e-5, (hi["x_m"], si["x_m"],
                                                                          slip, vmax)
    # k is Eq. (23) at each env's own state: the plant's (here the nominal model's) in the sim,
    # the nominal model's at the measured telemetry on the rig; so the two differ by the
    # states' difference above and nothing else
    nominal = fast.pack(DEFAULT_PARAMS)
    assert hi["k_N_per_m"] == fast.force_and_stiffness(tel.x_m, tel.v_mps, tel.pe_Pa, tel.pf_Pa,
                                                       nominal)[1]
    s = e.state[0]
    assert si["k_N_per_m"] == fast.force_and_stiffness(s[ST_X], s[ST_V], s[ST_PE], s[ST_PF],
                                                       e.consts[0])[1]
    np.testing.assert_array_equal(e.consts[0], nominal)
    assert hi["x_m"] == tel.x_m and tuple(hi["pressure_bar"] * BAR) == (tel.pe_Pa, tel.pf_Pa)


@pytest.mark.parametrize("env_id", ["MPALeg-v0", "MPALegResidual-v0"])
def test_the_reward_is_the_sum_of_its_terms_on_every_step(env_id):
    """Through tracking steps and the terminating one (which earns 0 with all terms 0)."""
    # a residual of ±7 bar: COLLAPSE vents the extensor and fills the flexor in both ids
    env = gym.make(env_id, task={"slew_bar_per_s": 1e4, "residual_scale_bar": 7.0})
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for k in range(200):
        a = COLLAPSE if k >= 20 else rng.uniform(-0.2, 0.2, 2)  # track a while, then collapse
        _, r, terminated, _, info = env.step(a)
        assert r == info["reward_position"] + info["reward_stiffness"] + info["reward_effort"]
        if terminated:
            assert r == info["reward_position"] == info["reward_stiffness"] == \
                info["reward_effort"] == 0.0
            break
        assert info["reward_effort"] < 0.0 and info["reward_position"] > 0.0
    assert terminated
