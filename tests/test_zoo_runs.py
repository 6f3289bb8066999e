"""A run folder written by rl-baselines3-zoo evaluates (mpa_gym.agents.learned.runs:
run_files, read_run_config; policies.load_run).

``python -m rl_zoo3.train --algo ppo --env MPALegResidual-v0 --gym-packages mpa_gym -conf
configs/ppo_residual.yaml`` writes ``logs/ppo/MPALegResidual-v0_1/``: ``MPALegResidual-v0.zip``
(``model.save``), and in ``MPALegResidual-v0/`` ``config.yml`` (``yaml.dump`` of the sorted
hyper-parameters as an ``OrderedDict``), ``args.yml`` (the same of its command line) and
``vecnormalize.pkl`` (rl_zoo3's exp_manager.py: ``save_trained_model``, ``_save_config``).

The fixture writes that layout by hand from a tiny SB3 run trained the way rl-zoo trains
(``make_vec_env`` of ``gym.make`` with the config's single-env wrappers in its order, then
``VecNormalize``), its learning-rate schedule a class of a module that the evaluating process
cannot import (as rl_zoo3's schedules are where rl_zoo3 is not installed). So the test needs no
rl_zoo3; where it is installed, a second test trains with rl-zoo itself and checks that the
fixture's files are the ones rl-zoo writes.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import subprocess
import sys
from collections import OrderedDict
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import mpa_gym  # noqa: F401
from mpa_gym.agents.learned.config import EVAL_SEED
from mpa_gym.configs import DEFAULT_TRAIN_CONFIG

ENV = "MPALegResidual-v0"
SC = {"name": "zoo_check", "duration_s": 3.0, "plant": {"extra_mass_kg": 0.5},
      "reference": {"x0_m": 0.8, "amp_m": 0.02, "period_s": 1.0}}
ROOT = Path(__file__).resolve().parents[1]
SCHEDULE = '''
class LinearSchedule:
    """A stand-in for rl_zoo3.utils.SimpleLinearSchedule: pickled by reference."""

    def __init__(self, start):
        self.start = start

    def __call__(self, progress):
        return progress * self.start
'''


def tiny_hyperparams() -> dict:
    """The default config's section for the env, cut down to a tiny run (the values it trains
    are real; their quality does not matter here)."""
    hp = yaml.safe_load(DEFAULT_TRAIN_CONFIG.read_text())[ENV]
    hp.update(n_envs=2, n_timesteps=256, n_steps=64, batch_size=64, n_epochs=1)
    hp["env_kwargs"]["task"]["episode_s"] = 0.5
    return hp


def zoo_wrapper(hp: dict):
    """rl-zoo's ``get_wrapper_class``: each wrapper of ``env_wrapper``, in order, with its
    kwargs, around one env."""
    chain = []
    for item in hp["env_wrapper"]:
        ((name, kwargs),) = item.items()
        module, cls = name.rsplit(".", 1)
        chain.append((getattr(importlib.import_module(module), cls), kwargs))

    def wrap(env):
        for cls, kwargs in chain:
            env = cls(env, **kwargs)
        return env

    return wrap


@pytest.fixture(scope="module")
def zoo_run(tmp_path_factory):
    """(the run folder, the trained model, its hyper-parameters)."""
    tmp = tmp_path_factory.mktemp("zoo")
    (tmp / "zoo_schedules.py").write_text(SCHEDULE)
    sys.path.insert(0, str(tmp))
    try:
        schedule = importlib.import_module("zoo_schedules").LinearSchedule(5.39e-4)
        hp = tiny_hyperparams()
        venv = make_vec_env(ENV, n_envs=hp["n_envs"], seed=7, env_kwargs=hp["env_kwargs"],
                            wrapper_class=zoo_wrapper(hp))
        venv = VecNormalize(venv, gamma=hp["gamma"], norm_obs=True, norm_reward=True)
        model = PPO("MlpPolicy", venv, n_steps=hp["n_steps"], batch_size=hp["batch_size"],
                    n_epochs=hp["n_epochs"], gamma=hp["gamma"], gae_lambda=hp["gae_lambda"],
                    learning_rate=schedule, policy_kwargs={"net_arch": [64, 64],
                                                           "log_std_init": -1.51},
                    seed=7, device="cpu").learn(hp["n_timesteps"])
        save = tmp / "logs" / "ppo" / f"{ENV}_1"
        params = save / ENV
        params.mkdir(parents=True)
        model.save(save / ENV)
        venv.save(str(params / "vecnormalize.pkl"))
    finally:
        sys.path.remove(str(tmp))
        sys.modules.pop("zoo_schedules", None)
    with open(params / "config.yml", "w") as f:
        yaml.dump(OrderedDict(sorted(hp.items())), f)
    args = {"algo": "ppo", "env": ENV, "env_kwargs": None, "n_timesteps": hp["n_timesteps"],
            "seed": 7, "conf_file": str(DEFAULT_TRAIN_CONFIG), "gym_packages": ["mpa_gym"],
            "log_folder": "logs", "vec_env": "dummy", "eval_freq": 25000}
    with open(params / "args.yml", "w") as f:
        yaml.dump(OrderedDict(sorted(args.items())), f)
    (params / "command.txt").write_text(f"python -m rl_zoo3.train --algo ppo --env {ENV}")
    return save, model, hp


def evaluate_cli(run: Path, tmp: Path, capsys) -> dict:
    """``mpa-gym evaluate --policy RUN ff --json`` (the fixture's schedule module is no longer
    importable: the fixture took it off the path)."""
    from mpa_gym.agents.cli import main

    assert importlib.util.find_spec("zoo_schedules") is None
    scen = tmp / "sc.yaml"
    scen.write_text(yaml.safe_dump(SC))
    code = main(["evaluate", "--policy", str(run), "ff", "--scenarios", str(scen),
                 "--no-robustness", "--out", str(tmp / "rep"), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


def test_a_zoo_run_folder_evaluates_to_its_models_own_episode(zoo_run, tmp_path, capsys):
    """The report's row of the zoo run is the trained model's episode on the zoo's own wrapper
    chain (single env, the config's wrappers, the saved normaliser, SB3's deterministic
    predict), on the same scenario and episode seed."""
    run, model, hp = zoo_run
    out = evaluate_cli(run, tmp_path, capsys)
    row = out["results"]["zoo_check"][run.name]
    assert not row["terminated"] and row["policy_share"] == 1.0
    summary = out["summary"]["groups"]["other"]["controllers"][run.name]
    assert summary["kind"] == "policy"  # rl-zoo ran no supervisor: the policy alone

    task = {k: v for k, v in hp["env_kwargs"]["task"].items() if k != "episode_s"}
    env = zoo_wrapper(hp)(gym.make(ENV, scenario=SC, task=task))
    norm = VecNormalize.load(str(run / ENV / "vecnormalize.pkl"),
                             DummyVecEnv([lambda: zoo_wrapper(hp)(gym.make(ENV))]))
    norm.training = False
    obs, info = env.reset(seed=EVAL_SEED)
    err, done = [], False
    while not done:
        action, _ = model.predict(norm.normalize_obs(obs[None]), deterministic=True)
        obs, _, term, trunc, info = env.step(action[0])
        err.append(info["x_m"] - info["x_ref_m"])
        done = term or trunc
    dt = task.get("dt_s", 0.01)
    last3 = round(3 * SC["reference"]["period_s"] / dt)  # the report's window: 3 periods
    rmse_mm = float(np.sqrt(np.mean(np.square(err[-last3:]))) * 1e3)
    # the same operations in another order (batched rows, the policy's own mean action):
    # equal to rounding
    np.testing.assert_allclose(row["position_rmse_mm"], rmse_mm, rtol=1e-9)
    # the report says what trained it
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "trained by rl-baselines3-zoo" in md


def test_a_folder_of_neither_layout_is_named(tmp_path, capsys):
    from mpa_gym.agents.cli import main

    (tmp_path / "empty").mkdir()
    assert main(["evaluate", "--policy", str(tmp_path / "empty"), "--scenarios", "nominal",
                 "--out", str(tmp_path / "rep")]) == 2
    err = capsys.readouterr().err
    assert "neither config.yaml" in err and "rl-baselines3-zoo" in err and "Traceback" not in err


def test_rl_zoo_itself_writes_the_fixtures_layout(zoo_run, tmp_path, capsys):
    """With rl_zoo3 installed (the ``zoo`` extra): rl-zoo trains the default config for a few
    hundred steps; its folder holds the fixture's files and evaluates."""
    pytest.importorskip("rl_zoo3")
    cfg = yaml.safe_load(DEFAULT_TRAIN_CONFIG.read_text())
    cfg[ENV] = tiny_hyperparams()
    conf = tmp_path / "tiny.yaml"
    conf.write_text(yaml.safe_dump(cfg))
    r = subprocess.run([sys.executable, "-m", "rl_zoo3.train", "--algo", "ppo", "--env", ENV,
                        "--gym-packages", "mpa_gym", "-conf", str(conf), "--seed", "3",
                        "--eval-freq", "-1"], capture_output=True, text=True, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-3000:]
    run = tmp_path / "logs" / "ppo" / f"{ENV}_1"

    def files(folder):
        return {str(p.relative_to(folder)) for p in folder.rglob("*")
                if p.is_file() and not p.name.endswith(".monitor.csv")}

    assert files(run) == files(zoo_run[0])
    out = evaluate_cli(run, tmp_path, capsys)
    assert not out["results"]["zoo_check"][run.name]["terminated"]
