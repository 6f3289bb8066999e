"""The callbacks of a training run (``mpa_gym.agents.training.train``) and the evaluation worker
they use: TensorBoard tracking scalars, held-out evaluations (in a spawned worker process beside
training where a core is free), complete checkpoints, the NaN guard and the stop request."""

from __future__ import annotations

import io
import pickle
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import (
    BaseCallback,
    EvalCallback,
)

from mpa_gym.agents.evaluation.episodes import Job, eval_task, metrics, run_episodes, stack_jobs
from mpa_gym.agents.evaluation.seeds import cores
from mpa_gym.agents.learned.anchor import rest_for_save
from mpa_gym.agents.learned.config import (
    TrainConfig,
)
from mpa_gym.agents.learned.policies import LearnedPolicy, supervise, tell_delays
from mpa_gym.agents.learned.runs import (
    read_eval_history,
    save_state,
    write_checkpoint,
    write_eval_history,
)
from mpa_gym.agents.worker import Worker, WorkerStopped
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.files import (
    atomic_save,
)


def say(msg: str) -> None:
    """One line on stderr, as ``mpa-gym train`` says things."""
    print(f"mpa-gym train: {msg}", file=sys.stderr, flush=True)


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
    """(metrics, episode length) of ``model``'s deterministic episode on each held-out scenario,
    the policy alone: all at once, one batched policy call per step
    (``mpa_gym.agents.evaluation.episodes.run_episodes``). With a ``supervisor`` in the config
    the supervised policy runs beside it, and each scenario's metrics say when its fallback
    took over (``supervised_fallback_s``, None: it did not): the hand-over rate is a training
    metric (``eval/hand_over_rate``). The policy starts every one of these episodes (no start
    is chosen on the model, ``mpa_gym.agents.evaluation.select``): the rate is that of the
    monitors firing on the policy's own loop."""
    policy = LearnedPolicy.from_config(model, normalizer, cfg)
    told = policy.features is not None and policy.features.delay_observation
    # one policy for all the scenarios (a batch), or one each told its plant's delays
    own = [tell_delays(LearnedPolicy.from_config(model, normalizer, cfg), sc) if told
           else policy for sc in scenarios]
    task = eval_task(cfg)
    jobs = [Job(sc, p, cfg.env_id, task) for sc, p in zip(scenarios, own, strict=True)]
    if cfg.supervisor is not None:
        jobs += [Job(sc, supervise(p, cfg, {"scenario": sc}), cfg.env_id, task)
                 for sc, p in zip(scenarios, own, strict=True)]
    n = len(scenarios)  # the policies told their delays, and the supervisors, as stacks
    traces = run_episodes(stack_jobs(jobs, [list(range(n)), list(range(n, len(jobs)))]),
                          cfg.eval_seed)
    out = [(metrics(tr, sc.reference.period, None), len(tr.t))
           for sc, tr in zip(scenarios, traces, strict=False)]
    for sc, (m, _), tr in zip(scenarios, out, traces[len(scenarios):], strict=False):
        m["supervised_fallback_s"] = metrics(tr, sc.reference.period, None)["fallback_s"]
    return out


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


# an evaluation interval shorter than this ends before a spawned worker has started, and
# training would wait for it
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
    at the end of training; ``best/`` gets the model as it was at the evaluation's step.
    :meth:`final` adds the evaluation at the last step once training has reached its budget."""

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

    @property
    def stopped_training(self) -> bool:
        """Whether ``on_evaluation`` asked training to stop (tuning's pruner)."""
        return not self._go_on

    def final(self) -> dict[str, Any] | None:
        """The held-out evaluation of the model as training left it, recorded like the periodic
        ones (history, TensorBoard, ``best/``), unless one was made at its step; returns the
        last entry of the history (None without scenarios). Called once ``learn`` has returned
        with a finite model, so that a run shorter than ``eval_freq`` is evaluated at its end
        and not only at step 0."""
        if not self.scenarios:
            return None
        if self._pending is not None:
            self._collect()
        steps = int(self.model.num_timesteps)
        if not self.evaluations_timesteps or self.evaluations_timesteps[-1] != steps:
            self.num_timesteps = steps
            self._evaluate()
            if self._pending is not None:
                self._collect()
            self.logger.dump(steps)
        return self.history[-1]

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
                    save_state(self.model, folder / "best_model.zip", folder / "vecnormalize.pkl",
                               prepare=rest_for_save)
            with rest_for_save(self.model):  # the policy as best/ and model.zip save it
                results = held_out_metrics(self.cfg, self.scenarios, self.model, norm)
            self._record(int(self.num_timesteps), results, live)
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
        with rest_for_save(self.model):  # the policy as best/ and model.zip save it
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
            say(f"the evaluation worker stopped ({e}); evaluating in this process from the "
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
        handed = [m["supervised_fallback_s"] is not None for m, _ in results
                  if "supervised_fallback_s" in m]
        if handed:  # the share of held-out episodes the supervisor took from the policy
            entry["hand_over_rate"] = float(np.mean(handed))
            self.logger.record("eval/hand_over_rate", entry["hand_over_rate"])
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
            write_checkpoint(self.model, self.run, prepare=rest_for_save)
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
