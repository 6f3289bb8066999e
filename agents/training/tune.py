"""Hyper-parameter tuning on Optuna: `mpa-gym tune --config YAML --storage URL --study-name NAME`.

One worker is one process running this module's :func:`tune`; several workers, on one machine
or many, share a study by starting the same command with the same ``--storage`` and
``--study-name`` (Optuna keeps the trials in that storage: a SQLite file, any SQLAlchemy URL such
as PostgreSQL, or a journal file on a shared disk).

- **Search space**: the config's ``mpa_gym.tune`` section, next to the hyper-parameters it varies
  (:data:`DEFAULT_SPACE` when the section is absent and the env is ``MPALegResidual-v0``). Each
  entry maps a hyper-parameter to an Optuna distribution::

      mpa_gym:
        tune:
          learning_rate: {float: [1.0e-4, 1.0e-3], log: true}
          n_envs: {categorical: [16, 32, 64]}
          n_epochs: {int: [3, 10]}
          policy_kwargs.log_std_init: {float: [-3.0, -1.0]}
          ForceStiffnessAction.rate_penalty: {float: [0.1, 1.0]}

  A plain name is a key of the env id's section; ``policy_kwargs.KEY`` a key of the policy
  kwargs; ``TrackingErrorObservation.KEY`` / ``ForceStiffnessAction.KEY`` a wrapper's kwarg.
  A ``lin_`` learning rate keeps its linear schedule. A new study's first trial is the config
  as written (user attribute ``base_config``) when its values lie in the space.
- **Objectives** (both minimised): the held-out position RMSE [mm] and stiffness error [% of k̂],
  each the mean over :data:`mpa_gym.agents.evaluation.evaluate.HELDOUT_SCENARIOS` (30 s episodes,
  the report's episode seed) and over the trial's seeds (``--seeds-per-trial``), of the policy
  alone, without its config's supervisor (:func:`make_objective` says why); the user attribute
  ``hand_overs`` counts the held-out episodes in which a monitor of the supervised run handed its
  loop to the fallback (a fallback its supervisor chose on the model before the episode is not
  a hand-over: ``mpa_gym.agents.evaluation.select``).
  The Pareto front is the study's ``best_trials``. Wall-clock time [s] per trial is the user
  attribute ``wall_s``.
- **Pruning**: Optuna prunes single-objective studies only (``Trial.report`` is not defined for
  several objectives). ``--objective position`` makes the study single-objective on the held-out
  position RMSE (the stiffness error is kept as the user attribute ``stiffness_err_pct``) and
  prunes with Optuna's ``MedianPruner`` on the periodic held-out evaluations of training (the
  config's ``eval_scenarios``). Seeds train one after another; the value of seed s at training
  step t is reported at step ``s · (n_timesteps + 1) + t``, so the pruner compares trials on
  the same seed at the same point of training. The default ``--objective both`` keeps the
  Pareto front and does not prune.
- **A killed worker**: SQL storages run Optuna's heartbeat (``--heartbeat`` seconds); a trial
  whose worker stopped beating for ``2 ×`` that long is marked FAIL by the next worker that
  starts a trial, and its parameters are queued once more
  (``RetryHeartbeatStaleTrialCallback``). Optuna never marks a trial stale that has not beaten
  yet (a worker killed while its sampler was still choosing the parameters), so a worker also
  fails and requeues, when it starts, a RUNNING trial that never reached the objective (no
  ``worker`` attribute) and started longer than the grace period ago. The journal file
  storage has no heartbeat in Optuna: there a killed worker's trial stays RUNNING (it holds no
  result) and the study goes on without it.
- **The cap**: ``--max-total-trials M`` caps the study's trials that count (COMPLETE, PRUNED,
  RUNNING, WAITING; FAIL does not, so a killed trial is replaced) over all workers. Optuna's
  ``MaxTrialsCallback`` stops a worker after a trial once the cap is reached; two workers asking
  for a trial at the same instant could still both get one, so a trial that has ``M`` counting
  trials of lower number before it ends at once, untrained, as FAIL with the user attribute
  ``over_cap`` — the count of finished trials is exactly ``M``.
"""

from __future__ import annotations

import copy
import datetime
import json
import math
import os
import signal
import socket
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import optuna
import yaml
from optuna.exceptions import ExperimentalWarning
from optuna.trial import TrialState

from mpa_gym.agents.controllers.supervisor import handed_over
from mpa_gym.agents.evaluation.evaluate import HELDOUT_SCENARIOS, evaluate
from mpa_gym.agents.learned.config import (
    ACTION_WRAPPER,
    DEFAULT_CONFIG,
    MAX_TIMESTEPS,
    OBS_WRAPPER,
    ConfigError,
    _literal,
    parse_config,
)
from mpa_gym.agents.learned.policies import ALONE, spec_label
from mpa_gym.agents.training.train import TrainingStopped, train
from mpa_gym.agents.training.trials import quiet_signalled_trials
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.files import check_out_dir, check_out_file, read_yaml

DEFAULT_STORAGE = "sqlite:///runs/optuna.db"
DEFAULT_STUDY = "ppo_residual"
MAX_TRIALS = 10**6  # per worker and per study: a bound a study never reaches on purpose
# The default search space for MPALegResidual-v0 (used when a config has no mpa_gym.tune): the
# default config's own section, so the space is written once, next to the values it varies.
DEFAULT_SPACE: dict[str, dict[str, Any]] = read_yaml(DEFAULT_CONFIG, "default config",
                                                     ConfigError)["mpa_gym"]["tune"]
OBJECTIVES = {"both": ("position_rmse_mm", "stiffness_err_pct"), "position": ("position_rmse_mm",)}
COUNTED = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING, TrialState.WAITING)
# heartbeat, its retry callback and metric names are experimental in Optuna; used as documented
warnings.filterwarnings("ignore", category=ExperimentalWarning, module="optuna")
warnings.filterwarnings("ignore", category=ExperimentalWarning,
                        module="mpa_gym.agents.training.tune")
WRAPPER_PREFIX = {"TrackingErrorObservation": OBS_WRAPPER, "ForceStiffnessAction": ACTION_WRAPPER}


# ---------------------------------------------------------------- search space (config section)

def parse_space(space: Any, where: str = "mpa_gym.tune") -> dict[str, optuna.distributions.
                                                                   BaseDistribution]:
    """Validate a search-space mapping into Optuna distributions; errors name the entry."""
    from optuna.distributions import (
        CategoricalDistribution,
        FloatDistribution,
        IntDistribution,
    )

    if not isinstance(space, dict) or not space:
        raise ConfigError(f"{where}={space!r} must be a non-empty mapping of hyper-parameter: "
                          "{float: [low, high]} | {int: [low, high]} | {categorical: [...]}")
    out: dict[str, optuna.distributions.BaseDistribution] = {}
    for name, spec in space.items():
        w = f"{where}.{name}"
        head, _, key = str(name).partition(".")
        if key and head != "policy_kwargs" and head not in WRAPPER_PREFIX:
            raise ConfigError(f"{w}: a dotted name must start with policy_kwargs, "
                              f"{' or '.join(WRAPPER_PREFIX)}")
        if not isinstance(spec, dict):
            raise ConfigError(f"{w}={spec!r} must be a mapping like {{float: [low, high]}}")
        kinds = [k for k in ("float", "int", "categorical") if k in spec]
        extra = sorted(set(spec) - {"float", "int", "categorical", "log", "step"})
        if len(kinds) != 1 or extra:
            raise ConfigError(f"{w}={spec!r}: needs exactly one of float / int / categorical "
                              f"(and optionally log, step); got keys {sorted(spec)}")
        kind, arg = kinds[0], spec[kinds[0]]
        if kind == "categorical":
            if not isinstance(arg, list) or not arg or not all(
                    v is None or isinstance(v, bool | int | float | str) for v in arg):
                raise ConfigError(f"{w}.categorical={arg!r} must be a non-empty list of "
                                  "numbers, strings, booleans or null")
            out[name] = CategoricalDistribution(arg)
            continue
        ok = (isinstance(arg, list) and len(arg) == 2
              and all(isinstance(v, int | float) and not isinstance(v, bool) for v in arg)
              and all(math.isfinite(v) for v in arg) and arg[0] < arg[1])
        if not ok:
            raise ConfigError(f"{w}.{kind}={arg!r} must be [low, high] with finite low < high")
        log = bool(spec.get("log", False))
        if log and arg[0] <= 0:
            raise ConfigError(f"{w}: log=true needs low > 0, got low={arg[0]!r}")
        try:
            if kind == "int":
                if any(v != int(v) for v in arg):
                    raise ConfigError(f"{w}.int={arg!r} must be whole numbers")
                out[name] = IntDistribution(int(arg[0]), int(arg[1]), log=log,
                                            step=int(spec.get("step", 1)))
            else:
                out[name] = FloatDistribution(float(arg[0]), float(arg[1]), log=log,
                                              step=spec.get("step"))
        except ValueError as e:  # Optuna's own checks (e.g. log with step)
            raise ConfigError(f"{w}: {e}") from None
    return out


def apply_params(data: dict[str, Any], env_id: str, params: dict[str, Any]) -> dict[str, Any]:
    """The config document with ``params`` (search-space names → values) put in place."""
    data = copy.deepcopy(data)
    hp = data[env_id]
    for name, value in params.items():
        head, _, key = name.partition(".")
        if not key:
            old = hp.get(name)
            hp[name] = (f"lin_{value!r}" if name == "learning_rate" and isinstance(old, str)
                        and old.startswith("lin_") else value)
        elif head == "policy_kwargs":
            pk = hp.get("policy_kwargs") or {}
            pk = _literal(pk, "policy_kwargs") if isinstance(pk, str) else dict(pk)
            pk[key] = value
            hp["policy_kwargs"] = repr(pk)  # rl-zoo's form: a Python expression
        else:
            full = WRAPPER_PREFIX[head]
            items = hp.get("env_wrapper") or []
            items = items if isinstance(items, list) else [items]
            for i, item in enumerate(items):
                wname = next(iter(item)) if isinstance(item, dict) else item
                if wname == full:
                    kwargs = dict(item[wname] or {}) if isinstance(item, dict) else {}
                    kwargs[key] = value
                    items[i] = {full: kwargs}
                    break
            else:
                raise ConfigError(f"mpa_gym.tune.{name}: the config has no {full} in env_wrapper")
            hp["env_wrapper"] = items
    return data


def current_params(data: dict[str, Any], env_id: str,
                   space: dict[str, optuna.distributions.BaseDistribution]
                   ) -> dict[str, Any] | None:
    """The config's own values of the search space's entries, or None if one is missing or
    outside its distribution (then the config cannot be a trial of the study)."""
    hp = data[env_id]
    out: dict[str, Any] = {}
    for name, dist in space.items():
        head, _, key = name.partition(".")
        if not key:
            v = hp.get(name)
            if isinstance(v, str) and v.startswith("lin_"):
                v = float(v[4:])
        elif head == "policy_kwargs":
            pk = hp.get("policy_kwargs") or {}
            v = (_literal(pk, "policy_kwargs") if isinstance(pk, str) else pk).get(key)
        else:
            items = hp.get("env_wrapper") or []
            kw = [i[WRAPPER_PREFIX[head]] for i in (items if isinstance(items, list) else [items])
                  if isinstance(i, dict) and WRAPPER_PREFIX[head] in i]
            v = (kw[0] or {}).get(key) if kw else None
        if v is None:
            return None
        try:
            if not dist._contains(dist.to_internal_repr(v)):
                return None
        except (ValueError, TypeError):
            return None
        out[name] = v
    return out


def study_space(data: dict[str, Any]) -> dict[str, Any]:
    """The search-space mapping of a config document (its own, or the default)."""
    h = data.get("mpa_gym") or {}
    space = h.get("tune") if isinstance(h, dict) else None
    if space is None:
        if "MPALegResidual-v0" not in data:
            raise ConfigError("the config has no mpa_gym.tune search space and the default one "
                              "is for MPALegResidual-v0 only")
        space = DEFAULT_SPACE
    return space


# ---------------------------------------------------------------- storage and study

def open_storage(url: str, heartbeat_s: int = 60) -> optuna.storages.BaseStorage:
    """An Optuna storage from a URL: ``sqlite:///FILE``, any SQLAlchemy URL
    (``postgresql://USER@HOST:PORT/DB``), or ``journal:FILE`` / a ``.log`` / ``.jsonl`` path
    (a journal file, for a disk several machines share). Raises ValueError naming the URL
    when it cannot be opened."""
    from optuna.storages import RDBStorage, RetryHeartbeatStaleTrialCallback
    from optuna.storages.journal import JournalFileBackend, JournalStorage

    journal = url[len("journal:"):] if url.startswith("journal:") else (
        url if "://" not in url and url.endswith((".log", ".jsonl")) else None)
    if journal is not None:
        check_out_file("--storage", journal)
        try:
            return JournalStorage(JournalFileBackend(journal))
        except OSError as e:
            raise ValueError(f"--storage={url!r}: cannot open the journal file: {e}") from None
    if "://" not in url:
        raise ValueError(f"--storage={url!r} is neither a SQLAlchemy URL (sqlite:///FILE, "
                         "postgresql://USER@HOST:PORT/DB) nor a journal file (journal:FILE)")
    given = url
    if url.startswith("postgresql://"):  # SQLAlchemy 2.1 defaults to psycopg 3; we ship psycopg2
        url = "postgresql+psycopg2://" + url[len("postgresql://"):]
    if url.startswith("postgresql+psycopg2://"):
        try:
            import psycopg2  # noqa: F401
        except ImportError:
            raise ValueError(f"--storage={given!r}: PostgreSQL needs the psycopg2 driver (the "
                             "postgres extra): pip install -c constraints.txt -e "
                             "\".[postgres]\"") from None
    if url.startswith("sqlite:///"):
        check_out_file("--storage", url[len("sqlite:///"):])
    from sqlalchemy.exc import IntegrityError, ProgrammingError

    for attempt in range(5):
        try:
            return RDBStorage(url, heartbeat_interval=heartbeat_s, grace_period=2 * heartbeat_s,
                              heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(
                                  max_retry=1),
                              engine_kwargs={"pool_pre_ping": True})
        except (IntegrityError, ProgrammingError):
            # workers starting together on a new database race to create Optuna's tables;
            # the loser finds them made on its next try
            if attempt == 4:
                raise
            time.sleep(0.5 * (attempt + 1))
        except Exception as e:  # sqlalchemy's OperationalError, ArgumentError, a missing driver
            lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
            msg = " ".join(lines[:2]) if lines else type(e).__name__
            raise ValueError(f"--storage={given!r}: cannot open the study storage: {msg}"
                             ) from None
    raise AssertionError("unreachable")


def open_study(storage: optuna.storages.BaseStorage, name: str, data: dict[str, Any],
               objective: str) -> optuna.Study:
    """Create the study or load it; a study of that name must have the same search space and
    objectives (its trials would not be comparable otherwise)."""
    space = study_space(data)
    parse_space(space)
    env_id = next(k for k in data if k != "mpa_gym")
    directions = ["minimize"] * len(OBJECTIVES[objective])
    try:  # not load_if_exists: only the worker that creates the study sets it up
        study = optuna.create_study(storage=storage, study_name=name, directions=directions,
                                    sampler=optuna.samplers.TPESampler(),
                                    pruner=_pruner(objective))
        created = True
    except optuna.exceptions.DuplicatedStudyError:
        created = False
    if not created:
        study = optuna.load_study(study_name=name, storage=storage,
                                  pruner=_pruner(objective))
        old_space = study.user_attrs.get("search_space")
        old_obj = study.user_attrs.get("objectives")
        if old_space is not None and json.loads(old_space) != _jsonable(space):
            diff = sorted(k for k in set(json.loads(old_space)) | set(space)
                          if json.loads(old_space).get(k) != _jsonable(space).get(k))
            raise ValueError(f"--study-name={name!r} exists with a different search space "
                             f"(entries {diff} differ); use another --study-name or the "
                             "study's own config")
        if old_obj is not None and old_obj != list(OBJECTIVES[objective]):
            raise ValueError(f"--study-name={name!r} exists with objectives {old_obj}, not "
                             f"{list(OBJECTIVES[objective])} (--objective)")
        if study.user_attrs.get("env_id") not in (None, env_id):
            raise ValueError(f"--study-name={name!r} tunes {study.user_attrs['env_id']}, "
                             f"the config {env_id}")
        return study
    study.set_metric_names(list(OBJECTIVES[objective]))
    study.set_user_attr("search_space", json.dumps(_jsonable(space)))
    study.set_user_attr("objectives", list(OBJECTIVES[objective]))
    study.set_user_attr("env_id", env_id)
    study.set_user_attr("config", json.dumps(_jsonable(data)))
    base = current_params(data, env_id, parse_space(space))
    if base is not None:  # trial 0: the config as written, the reference every trial beats or not
        study.enqueue_trial(base, user_attrs={"base_config": True})
    return study


def _pruner(objective: str) -> optuna.pruners.BasePruner:
    # Median of the same seed at the same step (module docstring); the first evaluation of a
    # trial is its untrained policy, so never prune on it
    if objective == "position":
        return optuna.pruners.MedianPruner(n_startup_trials=4, n_warmup_steps=1)
    return optuna.pruners.NopPruner()


def _jsonable(o: Any) -> Any:
    return json.loads(json.dumps(o))


# ---------------------------------------------------------------- one trial

def _counting_before(study: optuna.Study, number: int) -> int:
    return sum(1 for t in study.get_trials(deepcopy=False, states=COUNTED) if t.number < number)


def make_objective(study: optuna.Study, data: dict[str, Any], objective: str, seeds: list[int],
                   n_timesteps: int | None, max_total: int | None, out_dir: Path,
                   worker: str, heldout: list[Any] | None = None
                   ) -> Callable[[optuna.Trial], Any]:
    """The Optuna objective: train each seed, evaluate on the held-out plants, aggregate.

    A trial is scored on its policy alone (the run evaluated without its config's supervisor,
    ``RUN_DIR:alone``): the study tunes the policy's hyper-parameters, and with the supervisor
    in the loop a trial whose policy fails scores its fallback's figures (two budgets whose
    policies both fail would score the same pid number), so the sampler would learn nothing
    about the policy and could prefer a policy that fails early. The periodic held-out
    evaluations of training, which the pruner sees, are the policy alone too. The supervised
    run is evaluated beside it, and each trial records ``hand_overs``: in how many held-out
    episodes (scenarios × seeds) the supervisor's fallback took over (per seed in
    ``per_seed``; None for a config without a supervisor)."""

    space = parse_space(study_space(data))
    env_id = next(k for k in data if k != "mpa_gym")
    names = OBJECTIVES[objective]
    heldout = list(heldout or HELDOUT_SCENARIOS)

    def run(trial: optuna.Trial) -> Any:
        trial.set_user_attr("worker", worker)
        if max_total is not None and _counting_before(study, trial.number) >= max_total:
            trial.set_user_attr("over_cap", True)
            raise _OverCap(f"trial {trial.number} is beyond --max-total-trials={max_total}")
        params = {n: _suggest(trial, n, d) for n, d in space.items()}
        doc = apply_params(data, env_id, params)
        try:
            cfg = parse_config(copy.deepcopy(doc), f"trial {trial.number}")
        except ConfigError as e:  # a combination the space allows but PPO does not
            trial.set_user_attr("invalid", str(e))
            raise optuna.TrialPruned(str(e)) from None
        steps = n_timesteps if n_timesteps is not None else cfg.n_timesteps
        trial.set_user_attr("config", json.dumps(_jsonable(doc)))
        trial.set_user_attr("n_timesteps", steps)
        t0 = time.perf_counter()
        per_seed: list[dict[str, float]] = []
        run_dirs = []
        for s_idx, seed in enumerate(seeds):
            run_dir = out_dir / f"trial{trial.number:04d}-s{seed}"
            cfg_path = out_dir / f"trial{trial.number:04d}.yaml"
            cfg_path.write_text(yaml.safe_dump(doc, sort_keys=False))
            offset = s_idx * (steps + 1)

            def report(entry: dict[str, Any], offset: int = offset) -> bool:
                if objective != "position":
                    return True
                v = _mean([m["position_rmse_mm"] for m in entry["scenarios"].values()])
                trial.report(v, offset + entry["timesteps"])
                return not trial.should_prune()

            # in this process: the workers are the parallelism, and the pruner stops training
            # at the step it evaluated
            train(cfg_path, run_dir, seed, n_timesteps=steps, progress=False,
                  on_evaluation=report, eval_worker=False)
            run_dirs.append(str(run_dir))
            if objective == "position" and trial.should_prune():
                trial.set_user_attr("wall_s", time.perf_counter() - t0)
                raise optuna.TrialPruned(f"seed {seed}: below the median of earlier trials")
            # the policy alone is scored; the supervised run is evaluated beside it (evaluate:
            # with_alone) for its hand-overs
            res = evaluate([str(run_dir)], heldout, cfg.eval_seed)["results"]
            alone = spec_label(str(run_dir) + ALONE)
            scored = alone if alone in next(iter(res.values())) else run_dir.name
            per_seed.append({
                "position_rmse_mm": _mean([r[scored]["position_rmse_mm"]
                                           for r in res.values()]),
                "stiffness_err_pct": _mean([r[scored]["stiffness_rmse_pct"]
                                            for r in res.values()]),
                "hand_overs": (None if cfg.supervisor is None else
                               sum(handed_over(r[run_dir.name]) for r in res.values()))})
        agg = {k: _mean([p[k] for p in per_seed]) for k in OBJECTIVES["both"]}
        trial.set_user_attr("wall_s", time.perf_counter() - t0)
        trial.set_user_attr("per_seed", per_seed)
        trial.set_user_attr("hand_overs", None if cfg.supervisor is None else
                            sum(p["hand_overs"] for p in per_seed))
        trial.set_user_attr("run_dirs", run_dirs)
        trial.set_user_attr("stiffness_err_pct", agg["stiffness_err_pct"])
        values = [agg[n] for n in names]
        return values if len(values) > 1 else values[0]

    return run


SPACE_DRAWS = 256  # random points of a search space tried before refusing it as unsatisfiable


def check_space_feasible(data: dict[str, Any],
                         space: dict[str, optuna.distributions.BaseDistribution]) -> None:
    """Refuse a search space none of whose points makes a valid config (every trial would be
    pruned as invalid), before any trial: ``SPACE_DRAWS`` random points of the space are
    tried (one valid point ends the check); the error names the first point's problem."""
    import numpy as np
    from optuna.distributions import CategoricalDistribution, IntDistribution

    env_id = next(k for k in data if k != "mpa_gym")
    rng = np.random.default_rng(0)

    def draw(d: optuna.distributions.BaseDistribution) -> Any:
        if isinstance(d, CategoricalDistribution):
            return d.choices[int(rng.integers(len(d.choices)))]
        if isinstance(d, IntDistribution):
            return int(d.low + d.step * rng.integers((d.high - d.low) // d.step + 1))
        if d.log:
            return float(np.exp(rng.uniform(np.log(d.low), np.log(d.high))))
        return float(rng.uniform(d.low, d.high))

    first = None
    for _ in range(SPACE_DRAWS):
        params = {n: draw(d) for n, d in space.items()}
        try:
            parse_config(apply_params(data, env_id, params), "mpa_gym.tune")
            return
        except ConfigError as e:
            first = first or (params, e)
    raise ConfigError(f"mpa_gym.tune: no point of the search space makes a valid config "
                      f"({SPACE_DRAWS} random points tried; every trial would be pruned), e.g. "
                      f"{first[0]}: {first[1]}")


def _suggest(trial: optuna.Trial, name: str, d: optuna.distributions.BaseDistribution) -> Any:
    from optuna.distributions import CategoricalDistribution, IntDistribution

    if isinstance(d, CategoricalDistribution):
        return trial.suggest_categorical(name, d.choices)
    if isinstance(d, IntDistribution):
        return trial.suggest_int(name, d.low, d.high, step=d.step, log=d.log)
    return trial.suggest_float(name, d.low, d.high, step=d.step, log=d.log)


class _OverCap(Exception):
    """A trial created beyond the cap by a race between workers: closed at once as FAIL."""


def _mean(v: list[float]) -> float:
    return float(sum(v) / len(v))


# ---------------------------------------------------------------- the command

def tune(config: str | Path | None = None, storage: str = DEFAULT_STORAGE,
         study_name: str = DEFAULT_STUDY, n_trials: int | None = 10,
         max_total_trials: int | None = None, seeds_per_trial: int = 1,
         n_timesteps: int | None = None, objective: str = "both", heartbeat_s: int = 60,
         out_dir: str | Path | None = None, heldout: list[Any] | None = None
         ) -> dict[str, Any]:
    """Run one worker: at most ``n_trials`` trials of the study (fewer once the study holds
    ``max_total_trials``). ``heldout``: the scenarios of the objectives (default
    :data:`mpa_gym.agents.evaluation.evaluate.HELDOUT_SCENARIOS`). Returns a summary of the whole
    study."""
    _check_counts(n_trials, max_total_trials, seeds_per_trial, n_timesteps, heartbeat_s)
    if objective not in OBJECTIVES:
        raise ValueError(f"--objective={objective!r}: allowed {sorted(OBJECTIVES)}")
    path = Path(config or DEFAULT_CONFIG)
    data = read_yaml(path, "config file", ConfigError)
    cfg = parse_config(copy.deepcopy(data), str(path))  # the base config must be valid itself
    check_space_feasible(data, parse_space(study_space(data)))
    for i, sc in enumerate(heldout or []):  # the objectives' scenarios, before a trial trains
        try:
            load_scenario(sc)
        except ValueError as e:
            raise ValueError(f"--heldout[{i}]: {e}") from None
    out = check_out_dir("--out-dir", str(out_dir) if out_dir else
                        str(Path("runs") / "tune" / study_name))
    st = open_storage(storage, heartbeat_s)
    study = open_study(st, study_name, data, objective)
    worker = f"{socket.gethostname()}:{os.getpid()}"
    seeds = [cfg.seed + i for i in range(seeds_per_trial)]
    callbacks = []
    if max_total_trials is not None:
        callbacks.append(optuna.study.MaxTrialsCallback(max_total_trials, states=COUNTED))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    import torch

    torch.set_num_threads(1)  # workers are the parallelism: one core each
    fail_orphans(study, st, grace_s=2 * heartbeat_s)
    # a queued trial (a failed one's rerun) counts toward the cap, and is run even at the cap
    waiting = study.get_trials(deepcopy=False, states=(TrialState.WAITING,))
    if max_total_trials is None or _count(study) < max_total_trials or waiting:
        started = datetime.datetime.now()  # Optuna's own clock for a trial's start
        try:
            with quiet_signalled_trials():  # Optuna logs a failed trial with its traceback
                study.optimize(make_objective(study, data, objective, seeds, n_timesteps,
                                              max_total_trials, out, worker, heldout),
                               n_trials=n_trials, callbacks=callbacks, catch=(_OverCap,),
                               gc_after_trial=True)
        except (TrainingStopped, KeyboardInterrupt) as e:
            signum = getattr(e, "signum", signal.SIGINT)
            if signum is None:  # the NaN guard: a genuine failure, with its traceback
                raise
            raise TuneStopped(_requeue_interrupted(study, st, worker, started), e,
                              signum) from None
    return summary(study, worker)


class TuneStopped(Exception):
    """A signal (Ctrl-C, SIGTERM) stopped this worker inside a trial; the trial is FAILED and
    queued again (``requeued``: its number, or None when nothing ran), so the next worker runs
    it; the trial's run folder keeps what training reached."""

    def __init__(self, requeued: int | None, cause: BaseException, signum: int) -> None:
        self.requeued, self.signum = requeued, signum
        name = signal.Signals(signum).name
        if requeued is None:
            msg = f"interrupted by {name} before a trial started"
        else:
            where = (f" at {cause.timesteps} env steps of training ({cause.run})"
                     if isinstance(cause, TrainingStopped) else "")
            msg = (f"interrupted by {name} in trial {requeued}{where}; the trial is FAILED and "
                   "queued again for the next worker")
        super().__init__(msg)


def _requeue_interrupted(study: optuna.Study, storage: optuna.storages.BaseStorage,
                         worker: str, started: datetime.datetime) -> int | None:
    """Queue the trial the signal stopped again, as a stale trial is (once), and return its
    number: this worker's newest FAILED trial begun since ``started`` (this optimize call)
    that is not an over-cap one (FAILED on purpose); None when the signal came between
    trials."""
    mine = [t for t in study.get_trials(deepcopy=False, states=(TrialState.FAIL,))
            if t.user_attrs.get("worker") == worker and not t.user_attrs.get("over_cap")
            and t.datetime_start is not None and t.datetime_start >= started]
    if not mine:
        return None
    t = max(mine, key=lambda t: t.number)
    callback = getattr(storage, "get_heartbeat_stale_trial_callback", lambda: None)()
    if callback is not None:
        callback(study, t)
    else:  # a journal file has no heartbeat: queue the same parameters
        study.enqueue_trial(t.params, user_attrs={"retried_from": t.number})
    return t.number


def fail_orphans(study: optuna.Study, storage: optuna.storages.BaseStorage,
                 grace_s: float) -> list[int]:
    """Fail (and requeue once, like a stale trial) each RUNNING trial of ``study`` that never
    reached the objective and started more than ``grace_s`` ago; returns their numbers. Only
    for storages with a heartbeat: elsewhere a RUNNING trial may be a live worker's."""
    from datetime import datetime, timedelta

    callback = getattr(storage, "get_heartbeat_stale_trial_callback", lambda: None)()
    if getattr(storage, "heartbeat_interval", None) is None:
        return []
    failed = []
    old = datetime.now() - timedelta(seconds=grace_s)
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        # FrozenTrial has no public id; Optuna's own storages and callbacks use _trial_id
        if "worker" in t.user_attrs or t.datetime_start is None or t.datetime_start > old:
            continue
        try:
            if storage.set_trial_state_values(t._trial_id, state=TrialState.FAIL):
                failed.append(t)
        except optuna.exceptions.UpdateFinishedTrialError:
            continue  # another worker got there first
    for t in failed:
        if callback is not None:
            callback(study, storage.get_trial(t._trial_id))
    return [t.number for t in failed]


def _count(study: optuna.Study) -> int:
    return len(study.get_trials(deepcopy=False, states=COUNTED))


def _check_counts(n_trials: int | None, max_total: int | None, seeds: int,
                  n_timesteps: int | None, heartbeat_s: int) -> None:
    for flag, v, hi in (("--n-trials", n_trials, MAX_TRIALS),
                        ("--max-total-trials", max_total, MAX_TRIALS),
                        ("--seeds-per-trial", seeds, 100),
                        ("--n-timesteps", n_timesteps, MAX_TIMESTEPS),
                        ("--heartbeat", heartbeat_s, 86400)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= hi):
            raise ValueError(f"{flag}={v!r} must be a whole number in [1, {hi}]")


def summary(study: optuna.Study, worker: str | None = None) -> dict[str, Any]:
    """Trials by state, this worker's share, and the Pareto front (or the best trial)."""
    trials = study.get_trials(deepcopy=False)
    names = study.user_attrs.get("objectives") or ["value"]
    states: dict[str, int] = {}
    for t in trials:
        states[t.state.name] = states.get(t.state.name, 0) + 1
    front = [t for t in study.best_trials] if trials and any(
        t.state == TrialState.COMPLETE for t in trials) else []
    return {
        "study_name": study.study_name,
        "objectives": names,
        "n_trials": len(trials),
        "states": states,
        "by_this_worker": sum(1 for t in trials if worker and t.user_attrs.get("worker") == worker
                              and t.state in (TrialState.COMPLETE, TrialState.PRUNED)),
        "pareto_front": [{"number": t.number, "values": dict(zip(names, t.values, strict=True)),
                          "params": t.params, "wall_s": t.user_attrs.get("wall_s"),
                          "stiffness_err_pct": t.user_attrs.get("stiffness_err_pct"),
                          "hand_overs": t.user_attrs.get("hand_overs")}
                         for t in sorted(front, key=lambda t: t.values[0])],
    }


def write_best(storage: str, study_name: str, out: str | Path, trial: int | None = None
               ) -> dict[str, Any]:
    """Write the config of a study's trial (default: the Pareto-front trial with the lowest
    held-out position RMSE) to ``out``; the search space stays in it for a next study."""
    check_out_file("--out", str(out))
    st = open_storage(storage)
    try:
        study = optuna.load_study(study_name=study_name, storage=st)
    except KeyError:
        names = [s.study_name for s in optuna.get_all_study_summaries(st)]
        raise ValueError(f"--best {study_name!r}: no such study in {storage!r}; it holds "
                         f"{names}") from None
    done = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
    if not done:
        raise ValueError(f"--best {study_name!r}: the study has no complete trial yet")
    if trial is None:
        chosen = min(study.best_trials, key=lambda t: t.values[0])
    else:
        match = [t for t in done if t.number == trial]
        if not match:
            raise ValueError(f"--trial={trial}: not a complete trial of {study_name!r}; "
                             f"complete: {sorted(t.number for t in done)}")
        chosen = match[0]
    doc = json.loads(chosen.user_attrs["config"])
    header = (f"# Trial {chosen.number} of study {study_name!r} ({storage}): held-out "
              + ", ".join(f"{n} {v:.4g}" for n, v in
                          zip(study.user_attrs.get("objectives", ["value"]), chosen.values,
                              strict=True))
              + f"; {chosen.user_attrs.get('n_timesteps')} env steps per seed.\n")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=out.parent, delete=False, suffix=".yaml") as f:
        f.write(header + yaml.safe_dump(doc, sort_keys=False))
    os.replace(f.name, out)
    return {"study_name": study_name, "trial": chosen.number, "values": list(chosen.values),
            "params": chosen.params, "out": str(out)}
