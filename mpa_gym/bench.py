"""`mpa-gym bench`: step rates of the MPA envs beside Gymnasium's classic-control envs, measured
in the same run, and the integrator's accuracy at the env's control step.

Single envs go through ``gymnasium.make`` (with its default wrappers, as users get them); vector
envs through ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``. Every env is
stepped with actions drawn beforehand from its action space, after a warm-up (compilation,
caches), so only stepping is timed.
"""

from __future__ import annotations

import time
from typing import Any

import gymnasium as gym
import numpy as np

import mpa_gym  # noqa: F401  (registers the envs)
from mpa_gym.model.dynamics import integrate_reference, plant_rhs
from mpa_gym.model.params import BAR, DEFAULT_PARAMS
from mpa_gym.task.contract import ST_V, ST_X

SINGLE_IDS = ("MPALeg-v0", "MPALegResidual-v0", "CartPole-v1", "Pendulum-v1")
VECTOR_IDS = ("MPALeg-v0", "MPALegResidual-v0", "CartPole-v1")
VECTOR_SIZES = (1, 64, 1024, 4096)


def _rate(step: Any, reset: Any, actions: np.ndarray, seconds: float) -> float:
    """Steps per second of ``step`` over at least ``seconds`` (resetting when done)."""
    n, i, t0 = 0, 0, time.perf_counter()
    while True:
        for _ in range(200):
            if step(actions[i % len(actions)]):
                reset()
            i += 1
        n += 200
        dt = time.perf_counter() - t0
        if dt >= seconds:
            return n / dt


def single_rate(env_id: str, seconds: float) -> float:
    env = gym.make(env_id)
    env.reset(seed=0)
    actions = np.array([env.action_space.sample() for _ in range(1000)])

    def step(a: np.ndarray) -> bool:
        _, _, te, tr, _ = env.step(a)
        return te or tr

    _rate(step, lambda: env.reset(), actions, 0.2)  # warm-up
    r = _rate(step, lambda: env.reset(), actions, seconds)
    env.close()
    return r


def vector_rate(env_id: str, n: int, seconds: float) -> float:
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    venv.action_space.seed(0)
    actions = np.array([venv.action_space.sample() for _ in range(16)])
    _rate(lambda a: bool(venv.step(a) and False), lambda: None, actions, 0.2)
    r = _rate(lambda a: bool(venv.step(a) and False), lambda: None, actions, seconds) * n
    venv.close()
    return r


def integrator_error(duration_s: float = 30.0, residual_bar: float = 0.3) -> float:
    """[m] max |X_env − X_solve_ivp| of ``MPALegResidual-v0``'s integrator (RK4, its default
    substeps per 10 ms), from Fig. 4(a)'s initial error with a smooth residual of
    ``residual_bar`` on the feedforward (what a trained policy adds), against scipy DOP853
    (rtol 1e-10) integrating every 10 ms segment with the same held command."""

    env = gym.make("MPALegResidual-v0", scenario="initial_error",
                   task={"episode_s": duration_s})
    env.reset(seed=0)
    engine = env.unwrapped.engine
    y = engine.state[0, [ST_X, ST_V]]  # (X, V): the reference integrates the mechanics
    scale = residual_bar / env.unwrapped.cfg.residual_scale_bar
    err = 0.0
    for i in range(env.unwrapped.plan.n_steps):
        a = scale * np.array([np.sin(2 * np.pi * i / 100), np.cos(np.pi * i / 100)])
        *_, info = env.step(a)
        u = np.array([*(info["pressure_cmd_bar"] * BAR), 0.0])
        y = integrate_reference(lambda t, yy, u=u: plant_rhs(yy, u, DEFAULT_PARAMS), [0.0, 0.01],
                                y)[-1]
        err = max(err, abs(y[0] - info["x_m"]))
    return err


def run(seconds: float = 1.0, sizes: tuple[int, ...] = VECTOR_SIZES) -> dict[str, Any]:
    single = {i: single_rate(i, seconds) for i in SINGLE_IDS}
    vector = {i: {n: vector_rate(i, n, seconds) for n in sizes} for i in VECTOR_IDS}
    return {
        "single_steps_per_s": single,
        "single_ratio_to_pendulum": {i: single[i] / single["Pendulum-v1"] for i in SINGLE_IDS},
        "vector_env_steps_per_s": {i: {str(n): v for n, v in d.items()} for i, d in
                                   vector.items()},
        "vector_ratio_to_cartpole": {i: {str(n): vector[i][n] / vector["CartPole-v1"][n]
                                         for n in sizes} for i in VECTOR_IDS},
        "env_integrator_max_err_m_30s": integrator_error(),  # target < 1e-6 m
    }


def show(o: dict[str, Any]) -> str:
    lines = ["single env (gymnasium.make), steps/s:"]
    for i, r in o["single_steps_per_s"].items():
        lines.append(f"  {i:<20} {r:>12,.0f}   x{o['single_ratio_to_pendulum'][i]:.2f} of "
                     "Pendulum-v1")
    lines.append("vector env (vector_entry_point), env-steps/s:")
    sizes = list(next(iter(o["vector_env_steps_per_s"].values())))
    lines.append("  " + f"{'':<28}" + "".join(f"{'n=' + n:>14}" for n in sizes))
    for i, d in o["vector_env_steps_per_s"].items():
        lines.append("  " + f"{i:<28}" + "".join(f"{v:>14,.0f}" for v in d.values()))
    for i, d in o["vector_ratio_to_cartpole"].items():
        if i != "CartPole-v1":
            lines.append("  " + f"{i + ' / CartPole':<28}" + "".join(f"{v:>14.2f}"
                                                                    for v in d.values()))
    lines.append("env integrator (MPALegResidual-v0, initial error + 0.3 bar residual): "
                 f"max |X - X_solve_ivp| over 30 s = {o['env_integrator_max_err_m_30s']:.2e} m")
    return "\n".join(lines)
