"""PPO training from an rl-zoo style config: `mpa-gym train [--config FILE] [--resume RUN_DIR]`.

Reads top to bottom like CleanRL's scripts: build the native vector env (the configured
tracking-error features and force–stiffness actions, the SB3 adapter, VecMonitor, VecNormalize),
the callbacks (held-out evaluation, checkpoints, tracking scalars for TensorBoard), the PPO model,
then learn.
A run folder holds ``config.yaml`` (the resolved config), ``model.zip``, ``vecnormalize.pkl``,
``eval/evaluations.npz`` + ``eval/evaluations.json``, ``best/``, ``checkpoints/`` and ``tb/``.
Whatever happens (Ctrl-C included), the model and normaliser reached so far are saved.
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import (
    BaseCallback,
    CallbackList,
    CheckpointCallback,
    EvalCallback,
)
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from agents.config import ConfigError, TrainConfig, load_config
from agents.evaluate import metrics, run_episode
from agents.policies import LearnedPolicy
from agents.wrappers import ForceStiffnessVectorAction, TrackingErrorVectorObservation
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.envs.sb3 import SB3VecEnv

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "ppo_residual.yaml"


def make_train_env(cfg: TrainConfig, seed: int) -> VecEnv:
    """Native vector env → (tracking-error features) → (force–stiffness actions) → SB3 adapter
    → VecMonitor → VecNormalize."""
    venv = gym.make_vec(cfg.env_id, num_envs=cfg.n_envs, vectorization_mode="vector_entry_point",
                        **cfg.env_kwargs)
    if cfg.observation_wrapper is not None:
        venv = TrackingErrorVectorObservation(venv, **cfg.observation_wrapper)
    if cfg.action_wrapper is not None:
        venv = ForceStiffnessVectorAction(venv, **cfg.action_wrapper)
    vec: VecEnv = VecMonitor(SB3VecEnv(venv))
    vec.seed(seed)
    if cfg.normalize:
        vec = VecNormalize(vec, gamma=cfg.ppo_kwargs.get("gamma", 0.99), **cfg.normalize)
    return vec


def _schedule(lr: Any) -> Any:
    if isinstance(lr, str) and lr.startswith("lin_"):
        start = float(lr[4:])
        return lambda progress: progress * start
    return lr


class TrackingMetrics(BaseCallback):
    """TensorBoard scalars per rollout: position RMSE [mm] and stiffness error [% of k̂]."""

    def _on_rollout_start(self) -> None:
        self._e2: list[np.ndarray] = []
        self._k2: list[np.ndarray] = []

    def _on_step(self) -> bool:
        infos = self.locals["infos"]
        self._e2.append(np.array([(i["x_m"] - i["x_ref_m"]) ** 2 for i in infos]))
        self._k2.append(np.array([((i["k_N_per_m"] - i["k_ref_N_per_m"]) / i["k_ref_N_per_m"])
                                  ** 2 for i in infos]))
        return True

    def _on_rollout_end(self) -> None:
        if self._e2:
            self.logger.record("tracking/position_rmse_mm",
                               float(np.sqrt(np.mean(self._e2)) * 1e3))
            self.logger.record("tracking/stiffness_err_pct",
                               float(np.sqrt(np.mean(self._k2)) * 100))


class HeldOutEval(EvalCallback):
    """SB3's EvalCallback on held-out scenarios, one deterministic episode each, with the
    tracking metrics of each scenario logged beside the return. Writes ``evaluations.npz`` in
    EvalCallback's format and ``evaluations.json`` with the per-scenario metrics."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, eval_freq_calls: int) -> None:
        placeholder = gym.make(cfg.env_id)  # EvalCallback wants an env; we roll out our own
        super().__init__(placeholder, eval_freq=eval_freq_calls, n_eval_episodes=1,
                         log_path=str(run_dir / "eval"),
                         best_model_save_path=str(run_dir / "best"), verbose=0, warn=False)
        self.cfg = cfg
        self.scenarios = [load_scenario(s) for s in cfg.eval_scenarios]
        self.history: list[dict[str, Any]] = []
        self.json_path = run_dir / "eval" / "evaluations.json"

    def _init_callback(self) -> None:
        # EvalCallback's own init compares env types; our rollouts use single envs, so only
        # create the folders here
        for path in (self.best_model_save_path, self.log_path):
            if path is not None:
                Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(self.best_model_save_path or ".").mkdir(parents=True, exist_ok=True)
        if self.json_path.is_file():  # a resumed run keeps its history
            self.history = json.loads(self.json_path.read_text())
            npz = np.load(f"{self.log_path}.npz")
            self.evaluations_timesteps = list(npz["timesteps"])
            self.evaluations_results = [list(r) for r in npz["results"]]
            self.evaluations_length = [list(r) for r in npz["ep_lengths"]]
            self.best_mean_reward = float(max(np.mean(r) for r in self.evaluations_results))

    def _on_training_start(self) -> None:
        if not self.history:  # a fresh run: evaluate the initial policy too (learning curves)
            self._evaluate()

    def _on_step(self) -> bool:
        if self.eval_freq > 0 and self.n_calls % self.eval_freq == 0:
            self._evaluate()
        return True

    def _evaluate(self) -> None:
        if not self.scenarios:
            return
        norm = self.model.get_vec_normalize_env()
        policy = LearnedPolicy.from_config(self.model, norm, self.cfg)
        entry: dict[str, Any] = {"timesteps": int(self.num_timesteps), "scenarios": {}}
        returns, lengths = [], []
        for sc in self.scenarios:
            task = {k: v for k, v in (self.cfg.env_kwargs.get("task") or {}).items()
                    if k != "episode_s"}
            env = gym.make(self.cfg.env_id, scenario=sc, task=task)
            tr = run_episode(env, policy, self.cfg.eval_seed)
            env.close()
            m = metrics(tr, sc.reference.period, None)
            entry["scenarios"][sc.name] = m
            returns.append(m["return"])
            lengths.append(len(tr.t))
            self.logger.record(f"eval/{sc.name}/position_rmse_mm", m["position_rmse_mm"])
            self.logger.record(f"eval/{sc.name}/stiffness_err_pct", m["stiffness_rmse_pct"])
        mean_ret = float(np.mean(returns))
        self.logger.record("eval/mean_reward", mean_ret)
        self.evaluations_timesteps.append(self.num_timesteps)
        self.evaluations_results.append(returns)
        self.evaluations_length.append(lengths)
        np.savez(self.log_path, timesteps=self.evaluations_timesteps,
                 results=self.evaluations_results, ep_lengths=self.evaluations_length)
        self.history.append(entry)
        self.json_path.write_text(json.dumps(self.history, indent=1))
        self.last_mean_reward = mean_ret
        if mean_ret > self.best_mean_reward:
            self.best_mean_reward = mean_ret
            assert self.best_model_save_path is not None
            self.model.save(Path(self.best_model_save_path) / "best_model")
            if norm is not None:
                norm.save(str(Path(self.best_model_save_path) / "vecnormalize.pkl"))


def _resolved(cfg: TrainConfig, seed: int) -> dict[str, Any]:
    data = copy.deepcopy(cfg.raw)
    data.setdefault("mpa_gym", {})["seed"] = seed
    return data


def train(config: str | Path | None = None, run_dir: str | Path | None = None,
          seed: int | None = None, resume: str | Path | None = None,
          n_timesteps: int | None = None, progress: bool = True, verbose: int = 0) -> Path:
    """Train (or resume) PPO; returns the run folder."""
    if resume is not None:
        run = Path(resume)
        if not (run / "config.yaml").is_file() or not (run / "model.zip").is_file():
            raise ConfigError(f"--resume {run}: not a run folder (needs config.yaml and "
                              "model.zip)")
        cfg = load_config(run / "config.yaml")
        seed = cfg.seed if seed is None else seed
    else:
        cfg = load_config(config or DEFAULT_CONFIG)
        seed = cfg.seed if seed is None else seed
        stamp = time.strftime("%Y%m%d-%H%M%S")
        run = Path(run_dir) if run_dir else Path("runs") / f"{cfg.env_id}-{stamp}-s{seed}"
        if (run / "model.zip").exists():
            raise ConfigError(f"run folder {run} already holds a model; use --resume {run}")
        run.mkdir(parents=True, exist_ok=True)
        (run / "config.yaml").write_text(yaml.safe_dump(_resolved(cfg, seed), sort_keys=False))

    env = make_train_env(cfg, seed)
    if resume is not None:
        if isinstance(env, VecNormalize):
            env = VecNormalize.load(str(run / "vecnormalize.pkl"), env.venv)
        model = PPO.load(run / "model.zip", env=env, device="cpu", tensorboard_log=str(run / "tb"))
        done = int(model.num_timesteps)
        steps = n_timesteps if n_timesteps is not None else cfg.n_timesteps - done
        if steps <= 0:
            raise ConfigError(f"run {run} already reached n_timesteps={cfg.n_timesteps} "
                              f"({done} done); pass --n-timesteps N to train N more")
    else:
        ppo_kwargs = {**cfg.ppo_kwargs}
        if "learning_rate" in ppo_kwargs:
            ppo_kwargs["learning_rate"] = _schedule(ppo_kwargs["learning_rate"])
        pk = dict(cfg.policy_kwargs)
        if "activation_fn" in pk:
            import torch.nn as nn

            pk["activation_fn"] = getattr(nn, pk["activation_fn"].split(".")[1])
        model = PPO(cfg.policy, env, policy_kwargs=pk, seed=seed, device="cpu",
                    tensorboard_log=str(run / "tb"), verbose=verbose, **ppo_kwargs)
        steps = n_timesteps if n_timesteps is not None else cfg.n_timesteps

    calls = lambda every: max(1, every // cfg.n_envs)  # noqa: E731  (env steps → callback calls)
    callbacks = CallbackList([
        TrackingMetrics(),
        HeldOutEval(cfg, run, calls(cfg.eval_freq)),
        CheckpointCallback(calls(cfg.checkpoint_freq), str(run / "checkpoints"), "ppo",
                           save_vecnormalize=True),
    ])
    try:
        model.learn(steps, callback=callbacks, progress_bar=progress,
                    reset_num_timesteps=resume is None, tb_log_name="PPO")
    finally:  # Ctrl-C or an error: keep what was learned
        model.save(run / "model.zip")
        if isinstance(env, VecNormalize):
            env.save(str(run / "vecnormalize.pkl"))
        env.close()
    return run
