"""The single env's step reads its results on fast paths of its own (the action check on two
Python floats, the info from one ``tolist`` per row, truncation from Python ints); the vector
env reads the same compiled step through the array paths (``check_action(..., n)``, the batch
branch of ``step_info``, ``SimEngine.truncated``). Both must give the same numbers, bit for bit,
on every step: through terminations, truncations, noise, dead time and randomised plants."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import mpa_gym  # noqa: F401
from mpa_gym.task.contract import check_action

SCENARIO = {
    "name": "identity", "duration_s": 0.4,
    "plant": {"pressure_lag_s": 0.02, "pressure_dead_time_s": 0.015, "position_noise_m": 5e-5,
              "pressure_noise_bar": 0.005, "pressure_quantum_bar": 0.01,
              "encoder_resolution_m": 2e-5},
    "randomize": {"mass_kg": [3.5, 4.2], "initial_x_offset_m": [-0.01, 0.01]},
}


def same(a, b) -> bool:
    """Bit-identical numbers (a Python float against one entry of the vector env's array)."""
    return np.asarray(a, dtype=np.float64).tobytes() == np.asarray(b, dtype=np.float64).tobytes()


@pytest.mark.parametrize("env_id", ["MPALeg-v0", "MPALegResidual-v0"])
def test_single_env_step_is_the_batch_step_bit_for_bit(env_id):
    # slew limit off and actions of up to ±1.5: the direct env collapses past x_min within a few
    # dozen steps (terminations), the residual one runs its 40-step episodes out (truncations)
    task = {"slew_bar_per_s": 1e4}
    single = gym.make(env_id, scenario=SCENARIO, task=task)
    venv = gym.make_vec(env_id, num_envs=1, vectorization_mode="vector_entry_point",
                        scenario=SCENARIO, task=task)
    obs, info = single.reset(seed=5)
    vobs, _ = venv.reset(seed=5)
    assert np.array_equal(obs, vobs[0])
    rng = np.random.default_rng(0)
    ends = {"terminated": 0, "truncated": 0}
    for k in range(300):
        a = rng.uniform(-1.5, 1.5, 2)
        # alternate float32 arrays (what a policy gives), float64 arrays and plain lists
        given = a.astype(np.float32) if k % 3 == 0 else (a if k % 3 == 1 else a.tolist())
        obs, r, te, tr, info = single.step(given)
        vobs, vr, vte, vtr, vinfo = venv.step(np.asarray(given, dtype=np.float64)[None])
        assert type(r) is float and type(te) is bool and type(tr) is bool
        assert same(r, vr[0]) and te == vte[0] and tr == vtr[0]
        if te or tr:
            ends["terminated" if te else "truncated"] += 1
            vobs, vinfo = vinfo["final_obs"][0], vinfo["final_info"]
        assert obs.dtype == np.float32 and np.array_equal(obs, vobs if te or tr else vobs[0])
        assert set(info) <= set(vinfo)
        for key, value in info.items():
            assert same(value, vinfo[key][0]), (k, key, value, vinfo[key][0])
        if te or tr:
            obs, info = single.reset()
    # the comparison ran through both kinds of episode end (else it would not test them)
    assert ends["terminated" if env_id == "MPALeg-v0" else "truncated"] >= 3, ends


def test_info_is_fresh_on_every_step():
    env = gym.make("MPALegResidual-v0")
    env.reset(seed=0)
    first = env.step(np.zeros(2))[4]
    kept = first["pressure_bar"].copy()
    first["pressure_bar"][:] = -1.0  # a caller that writes into its info changes nothing else
    second = env.step(np.zeros(2))[4]
    assert second is not first and second["pressure_bar"] is not first["pressure_bar"]
    assert np.all(second["pressure_bar"] > 0.0) and np.all(kept > 0.0)


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64, np.longdouble, np.int64,
                                   np.uint8, "list"])
def test_the_single_action_check_is_the_batch_check(dtype):
    """``check_action(a)`` (the per-step fast path) returns what the batch check returns for
    the same action as a batch of one: float64, the same clip, −0.0 kept."""
    rng = np.random.default_rng(1)
    raw = np.concatenate([rng.uniform(-3.0, 3.0, (200, 2)), [[-0.0, 0.0], [1.0, -1.0],
                                                               [6e4, -6e4]]])  # 6e4: within float16
    for row in raw:
        a = row.tolist() if dtype == "list" else np.asarray(
            np.round(row) if np.dtype(dtype).kind in "iu" else row, dtype=dtype)
        if np.dtype(getattr(a, "dtype", np.float64)).kind == "u" and np.any(row < 0):
            continue
        one, batch = check_action(a), check_action(np.asarray(a)[None], 1)[0]
        assert one.dtype == np.float64 and one.shape == (2,)
        assert one.tobytes() == batch.tobytes(), (a, one, batch)
    for bad in ([np.nan, 0.0], [0.0, -np.inf]):
        with pytest.raises(ValueError, match=r"action=\[.*\] must be finite"):
            check_action(np.array(bad, dtype=np.float32))
