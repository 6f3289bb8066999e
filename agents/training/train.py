"""PPO training from an rl-zoo style config: `mpa-gym train [--config FILE] [--resume RUN_DIR]`.

Reads top to bottom: the native vector env (the configured tracking-error features and
force–stiffness actions, the SB3 adapter, VecMonitor, VecNormalize), the PPO model, the callbacks
(``mpa_gym.agents.training.callbacks``: held-out evaluation, checkpoints, tracking scalars for
TensorBoard, the NaN guard, the stop request), then learn. What the run folder holds and how its
files are written is ``mpa_gym.agents.learned.runs``.

Nothing is lost and nothing rewinds silently:

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

A run that reaches its budget ends with a held-out evaluation at its last step (unless a
periodic one fell there), after ``model.zip`` is saved, recorded like the periodic ones
(``eval/evaluations.{json,npz}``, TensorBoard, ``best/``): ``mpa-gym train`` prints it as
``last_evaluation``.
"""

from __future__ import annotations

import contextlib
import copy
import os
import pickle
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import (
    CallbackList,
)
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from mpa_gym.agents.learned.anchor import RestAnchoredPolicy, RestObservation, rest_for_save
from mpa_gym.agents.learned.config import (
    DEFAULT_CONFIG,
    ConfigError,
    TrainConfig,
    load_config,
    with_scenario,
)
from mpa_gym.agents.learned.runs import (
    cut_eval_history,
    latest_state,
    legacy_objects,
    reconcile_best,
    save_final,
)
from mpa_gym.agents.learned.wrappers import (
    ForceStiffnessVectorAction,
    TrackingErrorVectorObservation,
)
from mpa_gym.agents.training.callbacks import (
    CompleteCheckpoints,
    HeldOutEval,
    NaNGuard,
    NonFiniteModel,
    StopRequest,
    TrackingMetrics,
    eval_worker_pays,
    model_is_finite,
    say,
)
from mpa_gym.envs.sb3 import SB3VecEnv
from mpa_gym.files import (
    DamagedFileError,
    atomic_write_text,
    check_out_dir,
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


class TrainingStopped(Exception):
    """Training stopped early; what was reached is saved (``run``, ``timesteps``).

    ``signum``: the signal that asked for the stop (SIGINT, SIGTERM), or None when the NaN guard
    stopped it (``reason`` says why)."""

    def __init__(self, run: Path, timesteps: int, reason: str, signum: int | None = None
                 ) -> None:
        super().__init__(reason)
        self.run, self.timesteps, self.reason, self.signum = run, timesteps, reason, signum


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
            say(f"{run} holds no complete checkpoint yet (killed before the first one): "
                 "training it from step 0")
        else:
            for note in state[3]:
                say(note)
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
        check_out_dir("--run-dir", str(run))  # created, or a one-line error naming the flag
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
        say(f"config.yaml: n_timesteps {cfg.n_timesteps} -> {done + steps} (--n-timesteps "
             f"{steps} more from step {done})")
    if state is not None or resume is not None:
        dropped = cut_eval_history(run / "eval", done)
        if dropped:
            say(f"dropped {dropped} evaluation(s) made after step {done} by the interrupted "
                 "run (their model was not saved)")
        note = reconcile_best(run, done, bool(cfg.normalize))
        if note:
            say(note)
    if "OMP_NUM_THREADS" not in os.environ:
        # a 64-wide MLP gains nothing from a second torch thread (it costs a core that the
        # evaluation worker can use); OMP_NUM_THREADS, when set, rules
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
            model = PPO.load(model_path, env=env, device="cpu", tensorboard_log=str(run / "tb"),
                             custom_objects=legacy_objects(model_path))
        except Exception as e:
            env.close()
            raise DamagedFileError(f"{model_path} is damaged ({type(e).__name__}: {e})") from None
        say(f"resuming {run} from {model_path.relative_to(run)} at {done} env steps")
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
                    save_final(model, run, prepare=rest_for_save)
        if stop.requested is None and not held_out.stopped_training:
            # the budget is reached and model.zip saved: the held-out evaluation at the last
            # step (a signal now interrupts it and loses nothing already written)
            held_out.final()
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
