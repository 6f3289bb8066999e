"""Native vector env: agreement with the single env, same-step autoreset, the SB3 adapter."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import mpa_gym  # noqa: F401
from mpa_gym.envs.sb3 import SB3VecEnv, make_sb3_vec_env

REALISTIC = {
    "name": "realistic", "duration_s": 0.6,
    "plant": {"pressure_lag_s": 0.03, "pressure_dead_time_s": 0.02, "position_noise_m": 5e-5,
              "velocity_noise_mps": 1e-3, "pressure_noise_bar": 0.005,
              "pressure_quantum_bar": 0.01, "encoder_resolution_m": 2e-5},
    "randomize": {"mass_kg": [3.5, 4.2], "gamma_Ns_per_m": [20, 40], "C2_Pa": [0, 5e3],
                  "initial_x_offset_m": [-0.01, 0.01],
                  # each leg its own dead time (grows the history at an autoreset), slew
                  # limit, braid and slider friction
                  "pressure_dead_time_s": [0.0, 0.045], "pressure_slew_bar_per_s": [5, 50],
                  "braid_friction_ratio": [0.0, 0.05], "slider_friction_N": [0.0, 2.0],
                  "slider_viscous_Ns_per_m": [0.0, 5.0],
                  # each leg its own random kick, on top of the plan's impulse
                  "kick_force_N": {"range": [-30.0, 30.0], "p_off": 0.3},
                  "kick_t_s": [0.1, 0.5], "kick_duration_s": [0.0, 0.08]},
    "disturbances": [{"type": "impulse", "t_s": 0.2, "force_N": 10.0, "duration_s": 0.05}],
}


@pytest.mark.parametrize("env_id", ["MPALeg-v0", "MPALegResidual-v0"])
@pytest.mark.parametrize("num_envs", [1, 3, 300])  # 300 uses the multi-core kernel
def test_vector_env_agrees_with_single_envs_step_for_step(env_id, num_envs):
    # Sub-env i is the single env seeded with seed + i (Gymnasium's convention), through
    # randomisation, noise, lag, dead time, an impulse and autoresets (60-step episodes).
    seed, n_steps = 11, 130
    venv = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                        scenario=REALISTIC)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    check = [0, num_envs - 1]
    singles = [gym.make(env_id, scenario=REALISTIC) for _ in check]
    vobs, _ = venv.reset(seed=seed)
    sobs = [s.reset(seed=seed + i)[0] for s, i in zip(singles, check, strict=True)]
    rng = np.random.default_rng(0)
    for _ in range(n_steps):
        acts = rng.uniform(-0.4, 0.4, (num_envs, 2))
        vobs, vrew, vterm, vtrunc, vinfo = venv.step(acts)
        for k, (s, i) in enumerate(zip(singles, check, strict=True)):
            o, r, te, tr, info = s.step(acts[i])
            assert r == vrew[i] and te == vterm[i] and tr == vtrunc[i]
            if te or tr:  # SyncVectorEnv's convention: the last step's obs and info as final_*
                assert np.array_equal(o, vinfo["final_obs"][i])
                assert info["x_m"] == vinfo["final_info"]["x_m"][i]
                assert vinfo["_final_info"][i]
                o, info = s.reset()
            assert info["x_m"] == vinfo["x_m"][i]
            assert np.array_equal(o, vobs[i]), f"sub-env {i} diverged"
            sobs[k] = o


def test_vector_env_rejects_bad_actions():
    venv = gym.make_vec("MPALeg-v0", num_envs=4, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions have shape \(3, 2\); expected \(4, 2\)"):
        venv.step(np.zeros((3, 2)))
    bad = np.zeros((4, 2))
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"action\[2\]=\[0.0, nan\] must be finite"):
        venv.step(bad)
    with pytest.raises(ValueError, match=r"num_envs=0 must be a whole number"):
        gym.make_vec("MPALeg-v0", num_envs=0, vectorization_mode="vector_entry_point")


def test_sb3_adapter_conventions():
    vec = make_sb3_vec_env("MPALegResidual-v0", n_envs=3, seed=5, task={"episode_s": 0.05})
    assert isinstance(vec, SB3VecEnv)
    obs = vec.reset()
    assert obs.shape == (3, 9)
    for step in range(5):
        vec.step_async(np.zeros((3, 2)))
        obs, rew, dones, infos = vec.step_wait()
        assert rew.dtype == np.float32 and len(infos) == 3
        # one dict per env, each with its own row (a finished env's: its last step's, not the
        # reset's, which would be t = 0)
        assert [info["t_s"] for info in infos] == pytest.approx([0.01 * (step + 1)] * 3)
        assert all(info["pressure_bar"].shape == (2,) for info in infos)
        if step == 4:  # 5 steps of 10 ms: every env truncates and resets in this step
            assert dones.all()
            for i, info in enumerate(infos):
                assert info["TimeLimit.truncated"] is True
                term_obs = info["terminal_observation"]
                assert term_obs.shape == (9,)
                # the returned observation is the new episode's first: back at t = 0 (phase 0)
                assert obs[i, 4] == 0.0 and obs[i, 5] == 1.0
                assert term_obs[4] != 0.0
        else:
            assert not dones.any()


def test_ppo_trains_on_the_adapter():
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    vec = VecNormalize(VecMonitor(make_sb3_vec_env("MPALegResidual-v0", n_envs=2, seed=0,
                                                   task={"episode_s": 0.5})))
    model = PPO("MlpPolicy", vec, n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(128)
    assert model.num_timesteps == 128


def test_several_designs_one_per_episode_and_vector_agreement():
    # stiffness=[None, "kmax", "kmin"]: each episode follows one design, drawn at reset from
    # the env's generator; the vector env still matches single envs step for step.
    designs = [None, "kmax", "kmin"]
    task = {"episode_s": 0.2}
    env = gym.make("MPALegResidual-v0", stiffness=designs, task=task)
    seen = set()
    for seed in range(12):
        env.reset(seed=seed)
        plan = env.unwrapped.plan
        seen.add(getattr(plan.design.stiffness, "kind", "own"))
        *_, info = env.step(np.zeros(2))  # a zero residual applies this episode's feedforward
        np.testing.assert_allclose(info["pressure_cmd_bar"], plan.ff[0] / 1e5, rtol=1e-15)
    assert seen == {"own", "kmax", "kmin"}
    venv = gym.make_vec("MPALegResidual-v0", num_envs=3, vectorization_mode="vector_entry_point",
                        stiffness=designs, task=task)
    singles = [gym.make("MPALegResidual-v0", stiffness=designs, task=task) for _ in range(3)]
    vobs, _ = venv.reset(seed=5)
    for i, s in enumerate(singles):
        assert np.array_equal(s.reset(seed=5 + i)[0], vobs[i])
    for _ in range(50):  # 20-step episodes: two autoresets with fresh design draws
        vobs, *_ = venv.step(np.zeros((3, 2)))
        for i, s in enumerate(singles):
            o, _, te, tr, _ = s.step(np.zeros(2))
            if te or tr:
                o, _ = s.reset()
            assert np.array_equal(o, vobs[i])
