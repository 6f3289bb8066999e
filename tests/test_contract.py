"""The step contract (``mpa_gym.task.contract``) is the one definition every env reads: a column
added there appears in the single env, the vector env and the rig's env (against an emulator in
another process), and the info, safety flags and action check are the same everywhere."""

from __future__ import annotations

import inspect
import re
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from conftest import REALTIME

import mpa_gym
from mpa_gym.hardware.env import HardwareLegEnv
from mpa_gym.task import contract
from mpa_gym.task.contract import ObsColumn

TASK = {"episode_s": 1.0}
# Two columns no env knows of: a measured signal in mm and a plan signal in mm.
DUMMIES = (ObsColumn("dummy_x_mm", "X in mm", "mm", 0.0, 1000.0, "x_m", 1e-3),
           ObsColumn("dummy_x_ref_mm", "X̂ in mm", "mm", 0.0, 1000.0, "x_ref_m", 1e-3))


@pytest.fixture
def emulator_url():
    """A device emulator in another process (the CLI's), on a UDP loopback port."""
    # the device's watchdog relaxed to 0.5 s, as in the other rig tests: a stall of the loaded
    # test machine must not vent the leg (these tests check the layout, not the timing)
    proc = subprocess.Popen([sys.executable, "-m", "mpa_gym.agents.cli", "emulate", "--udp",
                             "--port", "0", "--duration", "60", "--watchdog", "0.5"],
                            stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()
        m = re.search(r"udp://\S+", line)
        assert m, f"the emulator did not say where it listens: {line!r}"
        yield m.group(0)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        proc.stderr.close()


def check_dummies(obs, info, residual):
    """The dummy columns sit after the id's own ones and show X and X̂ in mm."""
    n = len(contract.obs_names(residual))
    assert obs.shape == (n,) and n == (9 if residual else 8) + len(DUMMIES)
    i = contract.obs_index("dummy_x_mm", residual)
    assert i == n - 2
    # both sides are float32 roundings of the same float64 value (one of them scaled by 1e3
    # after rounding): at most two float32 half-ulps apart, 2 × 6e-8 relative; 1e-6 has margin
    np.testing.assert_allclose(obs[i], obs[contract.obs_index("x_m", residual)] * 1e3, rtol=1e-6)
    np.testing.assert_allclose(obs[i + 1], info["x_ref_m"] * 1e3, rtol=1e-6)


@pytest.mark.parametrize("residual", [False, True])
def test_a_column_added_to_the_contract_appears_in_the_sim_envs(monkeypatch, residual):
    monkeypatch.setattr(contract, "OBS_COLUMNS", (*contract.OBS_COLUMNS, *DUMMIES))
    env_id = "MPALegResidual-v0" if residual else "MPALeg-v0"
    env = gym.make(env_id, scenario="impulse", task=TASK)
    assert env.observation_space.shape == (len(contract.obs_names(residual)),)
    obs, info = env.reset(seed=0)
    check_dummies(obs, info, residual)
    env.action_space.seed(0)
    for _ in range(20):
        obs, _, terminated, _, info = env.step(env.action_space.sample())
        check_dummies(obs, info, residual)
        if terminated:  # random pressures may push the leg past a bound: still observed
            break
        assert env.observation_space.contains(obs)
    if residual:  # the classical controllers read the contract's columns, the new ones too
        from mpa_gym.agents.learned.policies import load_policy

        pid = load_policy("pid", {"scenario": "impulse", "task": TASK})[0]
        obs, info = env.reset(seed=0)
        state, start = None, np.ones(1, dtype=bool)
        for _ in range(5):
            action, state = pid.predict(obs, state, start, deterministic=True)
            start = np.zeros(1, dtype=bool)
            obs, _, terminated, _, info = env.step(action)
            assert not terminated
            check_dummies(obs, info, residual)
    venv = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point",
                        scenario="impulse", task=TASK)
    vobs, vinfo = venv.reset(seed=0)
    for _ in range(5):
        vobs, _, _, _, vinfo = venv.step(np.zeros((3, 2)))
        for k in range(3):
            check_dummies(vobs[k], {"x_ref_m": vinfo["x_ref_m"][k]}, residual)


@REALTIME
def test_a_column_added_to_the_contract_appears_on_the_rig(monkeypatch, emulator_url):
    monkeypatch.setattr(contract, "OBS_COLUMNS", (*contract.OBS_COLUMNS, *DUMMIES))
    # stale_s relaxed: a scheduling hiccup of the shared test machine must not stop the episode
    with HardwareLegEnv(emulator_url, residual=True, task=TASK, settle_s=0.2,
                        stale_s=0.2) as hw:
        assert hw.observation_space.shape == (11,)
        obs, info = hw.reset(seed=0)
        check_dummies(obs, info, True)
        for _ in range(10):
            obs, _, terminated, _, info = hw.step(np.zeros(2))
            assert not terminated, info.get("fault")
            check_dummies(obs, info, True)


@REALTIME
def test_every_env_fills_the_same_info_keys(emulator_url):
    env = gym.make("MPALegResidual-v0", task=TASK)
    env.reset(seed=0)
    single = env.step(np.zeros(2))[4]
    venv = gym.make_vec("MPALegResidual-v0", num_envs=2, vectorization_mode="vector_entry_point",
                        task=TASK)
    venv.reset(seed=0)
    vector = venv.step(np.zeros((2, 2)))[4]
    with HardwareLegEnv(emulator_url, residual=True, task=TASK, settle_s=0.2, stale_s=0.2) as hw:
        hw.reset(seed=0)
        rig = hw.step(np.zeros(2))[4]
    keys = set(contract.step_info(np.zeros(len(contract.OUT)), np.zeros(len(contract.STATE)),
                                  np.zeros(len(contract.PLAN)), 0.0))
    assert set(contract.INFO_KEYS) | set(contract.REWARD_KEYS) <= keys
    assert set(single) == keys
    assert set(vector) == keys
    assert keys <= set(rig)  # the rig adds its timing and link figures


def test_the_safety_flags_are_the_contract_bits():
    """A residual of −1 bar on a feedforward below 1 bar is clipped at 0 (SAFETY_CLIPPED); a
    jump of the command larger than the slew limit allows is slew-limited (SAFETY_SLEW)."""
    env = gym.make("MPALegResidual-v0", task={"episode_s": 1.0, "slew_bar_per_s": 1000.0})
    env.reset(seed=0)
    info = env.step(np.array([0.0, -1.0]))[4]  # flexor feedforward 0.5 bar: −1 bar clips
    assert info["safety"] == contract.SAFETY_CLIPPED
    assert info["pressure_cmd_bar"][1] == 0.0
    slow = gym.make("MPALegResidual-v0", task={"episode_s": 1.0, "slew_bar_per_s": 1.0})
    slow.reset(seed=0)
    info = slow.step(np.array([1.0, 0.0]))[4]  # +1 bar in 10 ms at 1 bar/s: limited
    assert info["safety"] == contract.SAFETY_SLEW


@pytest.mark.parametrize("bad", [["0.1", "0.2"], np.array([1 + 1j, 0]), np.array([True, False]),
                                 [None, 0.0]])
def test_the_action_check_refuses_non_numbers_in_every_env(bad):
    env = gym.make("MPALeg-v0", task=TASK)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action=.* must be real numbers"):
        env.step(bad)
    with pytest.raises(ValueError, match=r"must be real numbers"):
        contract.check_action([bad, bad], 2)


def test_the_observation_table_of_the_docs_is_the_contract():
    table = contract.obs_table(True)
    for i, c in enumerate(contract.obs_columns(True)):
        assert f"| {i} | {c.label} | {c.unit} |" in table
    for env, residual in ((mpa_gym.envs.MPALegEnv, False), (mpa_gym.envs.MPALegResidualEnv, True),
                          (HardwareLegEnv, True)):
        assert contract.obs_table(residual) in inspect.cleandoc(env.__doc__ or "")


def test_sensor_noise_is_in_the_signals_units_whatever_the_columns_divisor(monkeypatch):
    """Noise is drawn in SI per measured signal and divided with it: a column showing X in mm
    carries the same noise as X in m, times 1000 (a noise added after the divisor would not)."""
    monkeypatch.setattr(contract, "OBS_COLUMNS", (*contract.OBS_COLUMNS, *DUMMIES))
    sc = {"name": "noisy", "duration_s": 3.0, "plant": {"position_noise_m": 1e-3,
                                                        "pressure_noise_bar": 0.05}}
    env = gym.make("MPALegResidual-v0", scenario=sc)
    obs, info = env.reset(seed=0)
    noise_m = []
    for _ in range(200):
        obs, _, _, _, info = env.step(np.zeros(2))
        noise_m.append(obs[contract.obs_index("x_m")] - info["x_m"])
        # the same draw seen in mm (two float32 roundings, as in check_dummies)
        np.testing.assert_allclose(obs[contract.obs_index("dummy_x_mm")],
                                   obs[contract.obs_index("x_m")] * 1e3, rtol=1e-6)
    # 200 draws of σ = 1 mm: the sample std lies within ±25 % of σ with overwhelming odds (its
    # relative standard error is 1/√400 = 5 %)
    assert 0.75e-3 < np.std(noise_m) < 1.25e-3
