"""PPO training from an rl-zoo style config: `mpa-gym train [--config FILE] [--resume RUN_DIR]`.

Reads top to bottom like CleanRL's scripts: build the native vector env (the configured
tracking-error features and force–stiffness actions, the SB3 adapter, VecMonitor, VecNormalize),
the callbacks (held-out evaluation, checkpoints, tracking scalars for TensorBoard, the NaN guard,
the stop request), the PPO model, then learn.

A run folder holds ``config.yaml`` (the resolved config), ``model.zip``, ``vecnormalize.pkl``,
``eval/evaluations.npz`` + ``eval/evaluations.json``, ``best/``, ``checkpoints/`` and ``tb/``.

Nothing is lost and nothing rewinds silently:

- every file is written atomically (temporary file + rename): a kill leaves the old complete
  file or the new one;
- a checkpoint is ``checkpoints/ppo_<N>_steps.zip`` + ``ppo_vecnormalize_<N>_steps.pkl`` and,
  written last, ``ppo_<N>_steps.json`` (the step count and the files' sizes): only a checkpoint
  with its ``.json`` is complete;
- Ctrl-C and SIGTERM stop at the next env step and save a checkpoint and ``model.zip`` like a
  normal end (the CLI then exits 130 / 143); SIGKILL loses at most the steps since the last
  checkpoint (``checkpoint_freq``);
- ``--resume`` continues from the newest complete state (checkpoint or ``model.zip``: model,
  normaliser, step count) and cuts the evaluation history back to it, saying what it dropped; a
  ``best/`` saved by a dropped evaluation is re-derived from the checkpoint at the best kept one,
  or removed, and said;
- ``config.yaml`` records the step budget (``--n-timesteps``; on resume, the steps done + N), so
  a plain ``--resume`` after a kill trains to the budget the run was started with;
- a model with a non-finite weight (NaN guard, after every PPO update including the last) stops
  training and is never saved: ``model.zip`` and the checkpoints keep the last finite state.
"""

from __future__ import annotations

import contextlib
import copy
import io
import os
import pickle
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml
from mpa_gym.agents.evaluation.episodes import Job, eval_task, metrics, run_episodes
from mpa_gym.agents.evaluation.seeds import cores
from mpa_gym.agents.learned.anchor import RestAnchoredPolicy, RestObservation, rest_for_save
from mpa_gym.agents.learned.config import (
    DEFAULT_CONFIG,
    ConfigError,
    TrainConfig,
    load_config,
    parse_config,
)
from mpa_gym.agents.learned.policies import LearnedPolicy
from mpa_gym.agents.learned.runs import (
    cut_eval_history,
    latest_state,
    read_eval_history,
    reconcile_best,
    save_final,
    save_state,
    write_checkpoint,
    write_eval_history,
)
from mpa_gym.agents.learned.wrappers import (
    ForceStiffnessVectorAction,
    TrackingErrorVectorObservation,
)
from mpa_gym.agents.worker import Worker, WorkerStopped
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import (
    BaseCallback,
    CallbackList,
    EvalCallback,
)
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.envs.sb3 import SB3VecEnv
from mpa_gym.files import (
    DamagedFileError,
    atomic_save,
    atomic_write_text,
    read_yaml,
    remove_stale_temporaries,
)


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


def held_out_metrics(cfg: TrainConfig, scenarios: list[Any], model: Any, normalizer: Any
                     ) -> list[tuple[dict[str, Any], int]]:
    """(metrics, episode length) of ``model``'s deterministic episode on each held-out scenario:
    all at once, one batched policy call per step
    (``mpa_gym.agents.evaluation.episodes.run_episodes``)."""
    policy = LearnedPolicy.from_config(model, normalizer, cfg)
    task = eval_task(cfg)
    traces = run_episodes([Job(sc, policy, cfg.env_id, task) for sc in scenarios], cfg.eval_seed)
    return [(metrics(tr, sc.reference.period, None), len(tr.t))
            for sc, tr in zip(scenarios, traces, strict=True)]


class _PolicyOnly:
    """What ``LearnedPolicy`` uses of an SB3 model (``policy``, ``predict``), for a policy
    unpickled in the evaluation worker without its algorithm."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, Any]:
        return self.policy.predict(obs, deterministic=deterministic)


_WORKER: dict[str, Any] = {}  # the evaluation worker's config and loaded scenarios


def _worker_init(cfg: TrainConfig) -> None:
    import torch

    torch.set_num_threads(1)  # the worker is the second core; one thread is the whole of it
    _WORKER.update(cfg=cfg, scenarios=[load_scenario(s) for s in cfg.eval_scenarios])


def _evaluate_pickled(cfg: TrainConfig, scenarios: list[Any], snapshot: tuple[bytes, bytes | None]
                      ) -> list[tuple[dict[str, Any], int]]:
    policy, normalizer = snapshot
    norm = pickle.loads(normalizer) if normalizer is not None else None
    return held_out_metrics(cfg, scenarios, _PolicyOnly(pickle.loads(policy)), norm)


def _worker_evaluate(snapshot: tuple[bytes, bytes | None]) -> list[tuple[dict[str, Any], int]]:
    return _evaluate_pickled(_WORKER["cfg"], _WORKER["scenarios"], snapshot)


class EvalWorker(Worker):
    """A spawned process (``mpa_gym.agents.worker.Worker``: it ignores Ctrl-C and exits with the
    training process, even a SIGKILLed one) that runs held-out evaluations while training goes on.

    Each evaluation gets a pickled copy of the policy and its normaliser as they are at the
    evaluation's step (``snapshot``), so its figures are those of an evaluation in the training
    process, bit for bit (tested)."""

    def __init__(self, cfg: TrainConfig) -> None:
        super().__init__(_worker_init, (cfg,))

    @staticmethod
    def snapshot(model: Any, normalizer: Any) -> tuple[bytes, bytes | None]:
        """The policy and normaliser as they are now, pickled."""
        return (pickle.dumps(model.policy),
                pickle.dumps(normalizer) if normalizer is not None else None)

    def evaluate(self, snapshot: tuple[bytes, bytes | None]) -> Any:
        """Start an evaluation of ``snapshot``; returns its ``Future``."""
        return self.submit(_worker_evaluate, snapshot)


# env steps of the default config per second are ~1e4 on one core: an interval of 1e4 steps
# lasts about as long as the worker takes to start (the default's 2.5e5 lasts ~30 s)
WORKER_MIN_EVAL_FREQ = 10_000


def eval_worker_pays(cfg: TrainConfig, steps: int, on_evaluation: Any) -> bool:
    """Whether held-out evaluations go to an ``EvalWorker`` when the caller does not say.

    Yes when this process may use a second core, there are scenarios to evaluate, the budget
    spans at least two evaluation intervals of at least ``WORKER_MIN_EVAL_FREQ`` env steps each
    (the worker's start, a few seconds of imports on the second core, is then paid back: a
    shorter interval passes before the worker has answered, and training waits for it) and
    nobody acts on an evaluation's result at its step (``on_evaluation``, e.g. tuning's pruner,
    wants training stopped where it evaluated)."""

    return (cores() >= 2 and bool(cfg.eval_scenarios) and on_evaluation is None
            and cfg.eval_freq >= WORKER_MIN_EVAL_FREQ and steps >= 2 * cfg.eval_freq)



class HeldOutEval(EvalCallback):
    """SB3's EvalCallback on held-out scenarios, one deterministic episode each, with the
    tracking metrics of each scenario logged beside the return. Writes ``evaluations.npz`` in
    EvalCallback's format and ``evaluations.json`` with the per-scenario metrics.

    With ``worker`` the evaluations run in an ``EvalWorker`` while training goes on: each is
    recorded (history, TensorBoard, ``best/``) when its result arrives, in order, the last one
    at the end of training; ``best/`` gets the model as it was at the evaluation's step."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, eval_freq_calls: int,
                 on_evaluation: Callable[[dict[str, Any]], bool] | None = None,
                 worker: bool = False) -> None:
        placeholder = gym.make(cfg.env_id)  # EvalCallback wants an env; we roll out our own
        super().__init__(placeholder, eval_freq=eval_freq_calls, n_eval_episodes=1,
                         log_path=str(run_dir / "eval"),
                         best_model_save_path=str(run_dir / "best"), verbose=0, warn=False)
        self.cfg = cfg
        self.scenarios = [load_scenario(s) for s in cfg.eval_scenarios]
        self.history: list[dict[str, Any]] = []
        self.json_path = run_dir / "eval" / "evaluations.json"
        # called with each evaluation's entry; returning False stops training (tuning's pruner)
        self.on_evaluation = on_evaluation
        self._go_on = True
        self._worker = EvalWorker(cfg) if worker and self.scenarios else None
        # the evaluation under way in the worker: (step, snapshot, Future, best/'s writer)
        self._pending: tuple[int, Any, Any, Callable[[], None] | None] | None = None

    def _init_callback(self) -> None:
        # EvalCallback's own init compares env types; our rollouts use single envs, so only
        # create the folders here
        for path in (self.best_model_save_path, self.log_path):
            if path is not None:
                Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(self.best_model_save_path or ".").mkdir(parents=True, exist_ok=True)
        if self.json_path.is_file():  # a resumed run keeps its history
            self.history, ts, res, lens = read_eval_history(self.json_path.parent)
            self.evaluations_timesteps, self.evaluations_results = ts, res
            self.evaluations_length = lens
            # the best kept evaluation is the bar to beat while best/ holds its model; without
            # one (removed by reconcile_best) the next evaluation writes best/
            if res and (Path(self.best_model_save_path or ".") / "best_model.zip").is_file():
                self.best_mean_reward = float(max(np.mean(r) for r in res))

    def _on_training_start(self) -> None:
        if not self.history:  # a fresh run: evaluate the initial policy too (learning curves)
            self._evaluate()

    def _on_step(self) -> bool:
        if self._pending is not None and self._pending[2].done():
            self._collect()
        if self.eval_freq > 0 and self.n_calls % self.eval_freq == 0:
            self._evaluate()
        return self._go_on

    def _on_training_end(self) -> None:
        if self._pending is not None:
            self._collect()
            self.logger.dump(self.num_timesteps)  # no rollout end follows to write its scalars

    def close(self, wait: bool = True) -> None:
        """Record the evaluation still under way (``wait``; else drop it) and stop the worker."""
        if self._worker is None:
            return
        try:
            if wait and self._pending is not None:
                self._collect()
        finally:
            self._pending = None
            self._worker.close(wait)
            self._worker = None

    def _evaluate(self) -> None:
        if not self.scenarios:
            return
        norm = self.model.get_vec_normalize_env()
        folder = Path(self.best_model_save_path or ".")
        if self._worker is None:
            live = None
            if model_is_finite(self.model):
                def live() -> None:
                    save_state(self.model, folder / "best_model.zip", folder / "vecnormalize.pkl")
            self._record(int(self.num_timesteps),
                         held_out_metrics(self.cfg, self.scenarios, self.model, norm), live)
            return
        if self._pending is not None:  # evaluations are recorded in order
            self._collect()
        saved = None
        if model_is_finite(self.model):  # what best/ gets if this evaluation is the best
            buf = io.BytesIO()
            with rest_for_save(self.model):
                self.model.save(buf)
            model_bytes = buf.getvalue()
            norm_bytes = pickle.dumps(norm) if norm is not None else None

            def saved() -> None:  # in save_state's order
                atomic_save(folder / "best_model.zip", lambda f: f.write(model_bytes))
                if norm_bytes is not None:
                    atomic_save(folder / "vecnormalize.pkl", lambda f: f.write(norm_bytes))
        snap = EvalWorker.snapshot(self.model, norm)
        self._pending = (int(self.num_timesteps), snap, self._worker.evaluate(snap), saved)

    def _collect(self) -> None:
        """Wait for the worker's evaluation under way and record it. If the worker died (or
        could not start: a ``__main__`` a spawned process cannot import), this evaluation and
        the later ones run in the training process, and it is said."""
        assert self._pending is not None and self._worker is not None
        steps, snap, future, saved = self._pending
        self._pending = None
        try:
            results = self._worker.result(future)
        except WorkerStopped as e:
            _say(f"the evaluation worker stopped ({e}); evaluating in this process from the "
                 f"evaluation at step {steps} on")
            self._worker.close(wait=False)
            self._worker = None
            results = _evaluate_pickled(self.cfg, self.scenarios, snap)
        self._record(steps, results, saved)

    def _record(self, steps: int, results: list[tuple[dict[str, Any], int]],
                save_best: Callable[[], None] | None) -> None:
        """The evaluation at ``steps`` into the history and TensorBoard; ``save_best`` (None
        for a non-finite model) writes ``best/`` if it is the best so far."""
        entry: dict[str, Any] = {"timesteps": steps, "scenarios": {}}
        returns = []
        for sc, (m, _) in zip(self.scenarios, results, strict=True):
            entry["scenarios"][sc.name] = m
            returns.append(m["return"])
            self.logger.record(f"eval/{sc.name}/position_rmse_mm", m["position_rmse_mm"])
            self.logger.record(f"eval/{sc.name}/stiffness_err_pct", m["stiffness_rmse_pct"])
        mean_ret = float(np.mean(returns))
        self.logger.record("eval/mean_reward", mean_ret)
        self.evaluations_timesteps.append(steps)
        self.evaluations_results.append(returns)
        self.evaluations_length.append([n for _, n in results])
        self.history.append(entry)
        write_eval_history(self.json_path.parent, self.history, self.evaluations_timesteps,
                           self.evaluations_results, self.evaluations_length)
        if self.on_evaluation is not None:
            self._go_on = bool(self.on_evaluation(entry))
        self.last_mean_reward = mean_ret
        if mean_ret > self.best_mean_reward and save_best is not None:
            self.best_mean_reward = mean_ret
            save_best()


# ----------------------------------------------------------------------------- run-folder state


class TrainingStopped(Exception):
    """Training stopped early; what was reached is saved (``run``, ``timesteps``).

    ``signum``: the signal that asked for the stop (SIGINT, SIGTERM), or None when the NaN guard
    stopped it (``reason`` says why)."""

    def __init__(self, run: Path, timesteps: int, reason: str, signum: int | None = None
                 ) -> None:
        super().__init__(reason)
        self.run, self.timesteps, self.reason, self.signum = run, timesteps, reason, signum


class NonFiniteModel(RuntimeError):
    """The NaN guard found a non-finite weight or normaliser statistic."""


def model_is_finite(model: Any) -> bool:
    """Every policy weight and (if any) every VecNormalize statistic is finite."""
    import torch

    with torch.no_grad():
        if not all(bool(torch.isfinite(p).all()) for p in model.policy.parameters()):
            return False
    norm = model.get_vec_normalize_env()
    if norm is not None:
        stats = [norm.obs_rms.mean, norm.obs_rms.var, norm.ret_rms.mean, norm.ret_rms.var]
        if not all(np.all(np.isfinite(s)) for s in stats):
            return False
    return True


class CompleteCheckpoints(BaseCallback):
    """A complete checkpoint (``write_checkpoint``) every ``every`` callback calls."""

    def __init__(self, run: Path, every: int) -> None:
        super().__init__()
        self.run, self.every = run, every

    def _on_step(self) -> bool:
        if self.n_calls % self.every == 0:
            write_checkpoint(self.model, self.run)
        return True


class NaNGuard(BaseCallback):
    """Before each rollout (so after each PPO update): every weight and normaliser statistic
    finite, or ``NonFiniteModel`` stops training before a NaN policy acts or is saved."""

    def _on_rollout_start(self) -> None:
        if not model_is_finite(self.model):
            raise NonFiniteModel(f"the PPO update before step {self.model.num_timesteps} made a "
                                 "weight or a normaliser statistic non-finite")

    def _on_step(self) -> bool:
        return True


class StopRequest(BaseCallback):
    """Ends ``learn`` at the next env step once a signal asked for it (``requested``)."""

    def __init__(self) -> None:
        super().__init__()
        self.requested: int | None = None

    def _on_step(self) -> bool:
        return self.requested is None


@contextlib.contextmanager
def _unvalidated_distributions() -> Iterator[None]:
    """torch checks a distribution's parameters each time one is built, and SB3 builds one per
    policy call (each vector step, each minibatch); the check (finite mean, positive std) cost
    6 % of the wall time of a 1e5-step run of the default config (the weights came out bit for
    bit the same without it). NaNGuard already stops training before a non-finite weight acts,
    and a finite network's mean is finite, so the check is off while ``learn`` runs and the
    previous default comes back afterwards."""
    import torch.distributions as td

    before = td.Distribution._validate_args
    td.Distribution.set_default_validate_args(False)
    try:
        yield
    finally:
        td.Distribution.set_default_validate_args(before)


@contextlib.contextmanager
def _signals_stop(stop: StopRequest) -> Iterator[None]:
    """SIGINT / SIGTERM ask ``stop`` to end training at the next step (a second Ctrl-C raises
    KeyboardInterrupt at once); the previous handlers come back afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        if stop.requested is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        stop.requested = signum

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _say(msg: str) -> None:
    print(f"mpa-gym train: {msg}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- training
def _resolved(cfg: TrainConfig, seed: int, n_timesteps: int | None = None) -> dict[str, Any]:
    """The config as the run uses it: its seed and its step budget (``--n-timesteps``), so a
    resumed run continues with both."""
    data = copy.deepcopy(cfg.raw)
    data.setdefault("mpa_gym", {})["seed"] = seed
    if n_timesteps is not None:
        data[cfg.env_id]["n_timesteps"] = int(n_timesteps)
    return data


def _new_model(cfg: TrainConfig, env: VecEnv, run: Path, seed: int, verbose: int) -> PPO:
    ppo_kwargs = {**cfg.ppo_kwargs}
    for key in ("learning_rate", "clip_range", "clip_range_vf"):
        if ppo_kwargs.get(key) is not None:
            ppo_kwargs[key] = _schedule(ppo_kwargs[key])
    pk = dict(cfg.policy_kwargs)
    if "activation_fn" in pk:
        import torch.nn as nn

        pk["activation_fn"] = getattr(nn, pk["activation_fn"].split(".")[1])
    policy: Any = cfg.policy
    if cfg.anchor_at_rest:

        policy = RestAnchoredPolicy
    return PPO(policy, env, policy_kwargs=pk, seed=seed, device="cpu",
               tensorboard_log=str(run / "tb"), verbose=verbose, **ppo_kwargs)


def with_scenario(config: str | Path | None, scenario: str | Path) -> TrainConfig:
    """The config with its training scenario (``env_kwargs.scenario``) replaced by ``scenario``:
    a built-in name is kept as the name, a YAML file (``mpa-gym identify --out``) is copied in,
    so the run folder's config.yaml holds the plants it was trained on."""
    sc = load_scenario(scenario)  # a missing file or a bad scenario: its error, before anything
    src = str(config or DEFAULT_CONFIG)
    cfg = load_config(src)
    entry: Any = str(scenario) if not Path(scenario).suffix else read_yaml(
        scenario, "scenario file", ConfigError)
    if isinstance(entry, dict):
        entry.setdefault("name", sc.name)
    data = copy.deepcopy(cfg.raw)
    data[cfg.env_id].setdefault("env_kwargs", {})["scenario"] = entry
    return parse_config(data, f"{src} with --scenario {scenario}")


def train(config: str | Path | None = None, run_dir: str | Path | None = None,
          seed: int | None = None, resume: str | Path | None = None,
          n_timesteps: int | None = None, progress: bool = True, verbose: int = 0,
          on_evaluation: Callable[[dict[str, Any]], bool] | None = None,
          scenario: str | Path | None = None, eval_worker: bool | None = None) -> Path:
    """Train (or resume) PPO; returns the run folder. ``on_evaluation`` is called with each
    held-out evaluation (``eval/evaluations.json``'s entry); returning False stops training.
    ``scenario`` replaces the config's training scenario (:func:`with_scenario`).
    ``eval_worker``: the held-out evaluations run in a second process while training goes on
    (``HeldOutEval``); None decides by :func:`eval_worker_pays`.

    Raises ``TrainingStopped`` after saving when a signal (Ctrl-C, SIGTERM) or the NaN guard
    ended training early."""
    state = None
    if resume is not None:
        run = Path(resume)
        if not (run / "config.yaml").is_file():
            raise ConfigError(f"--resume {run}: not a run folder (needs config.yaml)")
        cfg = load_config(run / "config.yaml")
        if seed is not None and seed != cfg.seed:
            raise ConfigError(f"seed={seed}: a resumed run keeps the seed of its config.yaml "
                              f"({cfg.seed})")
        seed = cfg.seed
        for folder in (run, run / "checkpoints", run / "eval", run / "best"):
            if folder.is_dir():
                remove_stale_temporaries(folder)
        state = latest_state(run, bool(cfg.normalize))
        if state is None:
            _say(f"{run} holds no complete checkpoint yet (killed before the first one): "
                 "training it from step 0")
        else:
            for note in state[3]:
                _say(note)
    else:
        cfg = (load_config(config or DEFAULT_CONFIG) if scenario is None
               else with_scenario(config, scenario))
        seed = cfg.seed if seed is None else seed
        stamp = time.strftime("%Y%m%d-%H%M%S")
        run = Path(run_dir) if run_dir else Path("runs") / f"{cfg.env_id}-{stamp}-s{seed}"
        if run.exists() and not run.is_dir():
            raise ConfigError(f"--run-dir {run} is a file, not a folder")
        if (run / "model.zip").exists() or list((run / "checkpoints").glob("ppo_*_steps.json")):
            raise ConfigError(f"run folder {run} already holds a model; use --resume {run}")
        if (run / "config.yaml").exists():
            raise ConfigError(f"run folder {run} already holds a started run (config.yaml, no "
                              f"checkpoint yet); use --resume {run} to train it from step 0, "
                              "or another --run-dir")
        run.mkdir(parents=True, exist_ok=True)
        atomic_write_text(run / "config.yaml",
                          yaml.safe_dump(_resolved(cfg, seed, n_timesteps), sort_keys=False))

    done = 0 if state is None else state[0]
    steps = n_timesteps if n_timesteps is not None else cfg.n_timesteps - done
    if steps <= 0:
        raise ConfigError(f"run {run} already reached n_timesteps={cfg.n_timesteps} "
                          f"({done} done); pass --n-timesteps N to train N more")
    if resume is not None and n_timesteps is not None and done + steps != cfg.n_timesteps:
        # the run's budget is now done + N: a kill and a plain --resume continue to it
        atomic_write_text(run / "config.yaml", yaml.safe_dump(
            _resolved(cfg, cfg.seed, done + steps), sort_keys=False))
        _say(f"config.yaml: n_timesteps {cfg.n_timesteps} -> {done + steps} (--n-timesteps "
             f"{steps} more from step {done})")
    if state is not None or resume is not None:
        dropped = cut_eval_history(run / "eval", done)
        if dropped:
            _say(f"dropped {dropped} evaluation(s) made after step {done} by the interrupted "
                 "run (their model was not saved)")
        note = reconcile_best(run, done, bool(cfg.normalize))
        if note:
            _say(note)
    if "OMP_NUM_THREADS" not in os.environ:
        # a 64-wide MLP gains nothing from a second torch thread: measured 50.9 s on one thread
        # against 53.5 s on two for the default config, at half the CPU; OMP_NUM_THREADS rules
        import torch

        torch.set_num_threads(1)
    env = make_train_env(cfg, seed)
    if state is not None:
        done, model_path, norm_path, _ = state
        if isinstance(env, VecNormalize):
            assert norm_path is not None
            try:
                with norm_path.open("rb") as f:
                    norm = pickle.load(f)
            except Exception as e:  # a truncated pickle raises EOFError, UnpicklingError, …
                env.close()
                raise DamagedFileError(f"{norm_path} is damaged ({type(e).__name__}: {e})"
                                       ) from None
            norm.set_venv(env.venv)
            env = norm
        try:
            model = PPO.load(model_path, env=env, device="cpu", tensorboard_log=str(run / "tb"))
        except Exception as e:
            env.close()
            raise DamagedFileError(f"{model_path} is damaged ({type(e).__name__}: {e})") from None
        _say(f"resuming {run} from {model_path.relative_to(run)} at {done} env steps")
    else:
        model = _new_model(cfg, env, run, seed, verbose)

    calls = lambda every: max(1, every // cfg.n_envs)  # noqa: E731  (env steps → callback calls)
    stop = StopRequest()
    if eval_worker is None:
        eval_worker = eval_worker_pays(cfg, steps, on_evaluation)
    held_out = HeldOutEval(cfg, run, calls(cfg.eval_freq), on_evaluation, eval_worker)
    callbacks = CallbackList([
        stop,
        NaNGuard(),
        TrackingMetrics(),
        RestObservation(),
        held_out,
        CompleteCheckpoints(run, calls(cfg.checkpoint_freq)),
    ])
    try:
        with _signals_stop(stop), _unvalidated_distributions():
            try:
                model.learn(steps, callback=callbacks, progress_bar=progress,
                            reset_num_timesteps=state is None, tb_log_name="PPO")
                # the NaN guard runs before each rollout: the last update is checked here
                if not model_is_finite(model):
                    raise NonFiniteModel(f"the last PPO update (after step "
                                         f"{model.num_timesteps}) made a weight or a normaliser "
                                         "statistic non-finite")
            except NonFiniteModel as e:
                last = latest_state(run, bool(cfg.normalize))
                kept = (f"kept the last finite state, {last[1].relative_to(run)} at {last[0]} "
                        "steps" if last else "no finite state was saved")
                raise TrainingStopped(run, last[0] if last else 0,
                                      f"NaN guard: {e}; {kept} (check learning_rate, "
                                      "max_grad_norm, ent_coef and the rewards)") from None
            finally:
                if model_is_finite(model):  # Ctrl-C, SIGTERM or an error: keep what was learned
                    save_final(model, run)
    except KeyboardInterrupt:  # a second Ctrl-C: nobody waits for the evaluation under way
        held_out.close(wait=False)
        raise
    finally:
        held_out.close()  # an evaluation still under way is recorded (a fault loses nothing)
        env.close()
    if stop.requested is not None:
        name = signal.Signals(stop.requested).name
        raise TrainingStopped(run, int(model.num_timesteps),
                              f"stopped by {name} at {model.num_timesteps} env steps; saved "
                              f"{run / 'model.zip'}; continue with --resume {run}",
                              stop.requested)
    return run
