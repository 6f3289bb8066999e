"""The run folder: what ``mpa-gym train`` writes and every loader reads.

A run folder holds ``config.yaml`` (the resolved config), ``model.zip`` + ``vecnormalize.pkl``
(the final state), ``README.txt`` (what ``model.zip`` takes and how to load the run),
``checkpoints/`` (``ppo_<N>_steps.zip`` + ``ppo_vecnormalize_<N>_steps.pkl``
and, written last, ``ppo_<N>_steps.json``: the step count and the files' sizes, so only a
checkpoint with its marker is complete), ``eval/evaluations.{npz,json}`` (the held-out
evaluations during training), ``best/`` and ``tb/``. Every file is written atomically
(``mpa_gym.files``): a kill leaves the old complete file or the new one.

A folder written by rl-baselines3-zoo (``python -m rl_zoo3.train --algo ppo --env ENV
--gym-packages mpa_gym -conf configs/ppo_residual.yaml`` writes ``logs/ppo/ENV_1/``) loads too:
it holds ``ENV.zip`` (the final model), ``best_model.zip`` (its evaluations' best, if any) and
``ENV/`` with ``config.yml`` (the hyper-parameters it trained with), ``args.yml`` (its command
line) and ``vecnormalize.pkl``. :func:`run_files` says where a folder keeps each file and
:func:`read_run_config` rebuilds the training config of either (:func:`zoo_config`).
"""

from __future__ import annotations

import base64
import io
import json
import pickle
import zipfile
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mpa_gym.agents.learned.config import (
    ENV_IDS,
    ConfigError,
    TrainConfig,
    load_config,
    parse_config,
)
from mpa_gym.agents.learned.episodic import ObservationCheck
from mpa_gym.files import DamagedFileError, atomic_save, atomic_write_text, read_yaml

EVAL_JSON, EVAL_NPZ = "evaluations.json", "evaluations.npz"
# the app's modules before 0.2.0, when it was a top-level ``agents`` package, and where they are
# now: a model file written then names its policy class (agents.anchor.RestAnchoredPolicy) by
# the old module, which no longer exists (and may be another distribution's)
LEGACY_MODULES = {
    f"agents.{old}": f"mpa_gym.agents.{new}" for old, new in {
        "baselines": "controllers.baselines", "supervisor": "controllers.supervisor",
        "excite": "controllers.excite", "config": "learned.config",
        "wrappers": "learned.wrappers", "anchor": "learned.anchor",
        "policies": "learned.policies", "inference": "learned.inference",
        "evaluate": "evaluation.evaluate", "robustness": "evaluation.robustness",
        "seeds": "evaluation.seeds", "train": "training.train", "tune": "training.tune",
        "tune_baselines": "training.tune_baselines", "rollout": "rig.rollout",
        "identify": "rig.identify", "worker": "worker"}.items()}


class _CurrentModules(pickle.Unpickler):
    """Unpickles what names a module of ``LEGACY_MODULES`` from where it is now."""

    def find_class(self, module: str, name: str) -> Any:
        return super().find_class(LEGACY_MODULES.get(module, module), name)


def legacy_objects(path: Path) -> dict[str, Any]:
    """``custom_objects`` for SB3's loaders: the entries of the model file ``path`` that name a
    module of the layout before 0.2.0, unpickled from where it is now (none for a file written
    since)."""
    try:
        with zipfile.ZipFile(path) as z:
            data = json.loads(z.read("data"))
    except (zipfile.BadZipFile, KeyError, ValueError, OSError) as e:
        raise DamagedFileError(f"{path} is damaged (not a complete SB3 model file: {e})"
                               ) from None
    out: dict[str, Any] = {}
    for key, value in data.items():
        if not (isinstance(value, dict) and ":serialized:" in value):
            continue
        raw = base64.b64decode(value[":serialized:"])
        if any(m.encode() in raw for m in LEGACY_MODULES):
            out[key] = _CurrentModules(io.BytesIO(raw)).load()
    return out


CONFIG = "config.yaml"  # mpa-gym train's resolved config
ZOO_CONFIG, ZOO_ARGS = "config.yml", "args.yml"  # rl-baselines3-zoo's, in the folder ENV/


@dataclass(frozen=True)
class RunFiles:
    """Where a run folder keeps what the loaders read (module docstring): ``mpa-gym train``'s
    layout, or rl-baselines3-zoo's (``zoo_args``: its ``args.yml``; None for ours)."""

    config: Path
    model: Path
    normalizer: Path
    zoo_args: Path | None = None


def run_files(run: str | Path, which: str = "final") -> RunFiles:
    """The files of run folder ``run``'s ``final`` model or its ``best`` one. Raises
    ConfigError (naming both layouts) for a folder that is neither."""
    run = Path(run)
    if which not in ("final", "best"):
        raise ValueError(f"which={which!r} must be one of ['best', 'final']")
    if (run / CONFIG).is_file() or not run.is_dir():
        if which == "final":
            return RunFiles(run / CONFIG, run / "model.zip", run / "vecnormalize.pkl")
        return RunFiles(run / CONFIG, run / "best" / "best_model.zip",
                        run / "best" / "vecnormalize.pkl")
    zoo = sorted(p.parent for p in run.glob(f"*/{ZOO_CONFIG}") if p.parent.name in ENV_IDS)
    if len(zoo) != 1:
        found = f"; it holds {[str(p.relative_to(run)) for p in zoo]}" if zoo else ""
        raise ConfigError(f"{run} is not a run folder: it holds neither {CONFIG} (mpa-gym "
                          f"train) nor one ENV/{ZOO_CONFIG} with ENV in {list(ENV_IDS)} "
                          f"(rl-baselines3-zoo){found}")
    params = zoo[0]
    model = run / (f"{params.name}.zip" if which == "final" else "best_model.zip")
    return RunFiles(params / ZOO_CONFIG, model, params / "vecnormalize.pkl", params / ZOO_ARGS)


class _ZooLoader(yaml.SafeLoader):
    """YAML's safe loader plus the one Python tag rl-baselines3-zoo writes: its config.yml and
    args.yml are ``yaml.dump`` of an ``OrderedDict``, read here as a plain dict of its pairs
    (no other object is built from the file)."""


def _ordered_dict(loader: yaml.SafeLoader, node: yaml.Node) -> dict[Any, Any]:
    (pairs,) = loader.construct_sequence(node, deep=True)
    return {k: v for k, v in pairs}


_ZooLoader.add_constructor("tag:yaml.org,2002:python/object/apply:collections.OrderedDict",
                           _ordered_dict)


def zoo_config(files: RunFiles) -> TrainConfig:
    """The training config of an rl-baselines3-zoo run, rebuilt as rl-zoo used it: the
    hyper-parameters of its ``config.yml`` (the env's section of the config file, with its
    wrappers), ``env_kwargs`` from the command line (``args.yml``) where the file gave none,
    the command line's ``-n`` (``n_timesteps``) where it was given, and its seed. rl-zoo
    ignores the file's ``mpa_gym`` section, so the run has no supervisor and its policy is
    SB3's plain ``MlpPolicy`` (not anchored at rest): it is evaluated as the policy alone."""
    assert files.zoo_args is not None
    where = f"{files.config} (an rl-baselines3-zoo run)"
    hp = read_yaml(files.config, "rl-zoo config", ConfigError, loader=_ZooLoader)
    args = read_yaml(files.zoo_args, "rl-zoo args", ConfigError, loader=_ZooLoader)
    if not isinstance(hp, dict) or not isinstance(args, dict):
        raise ConfigError(f"{where}: config.yml and args.yml must each hold a mapping")
    env_id = args.get("env", files.config.parent.name)
    if env_id != files.config.parent.name:
        raise ConfigError(f"{files.zoo_args}: env={env_id!r} but its folder is "
                          f"{files.config.parent.name!r}")
    hp = dict(hp)
    if hp.get("env_kwargs") is None and args.get("env_kwargs"):
        hp["env_kwargs"] = args["env_kwargs"]
    if isinstance(args.get("n_timesteps"), int) and args["n_timesteps"] > 0:
        hp["n_timesteps"] = args["n_timesteps"]
    harness: dict[str, Any] = {}
    seed = args.get("seed")
    if isinstance(seed, int) and 0 <= seed <= 2**31 - 1:  # rl-zoo draws up to 2**32 - 2
        harness["seed"] = seed
    return parse_config({env_id: hp, "mpa_gym": harness}, where)


def read_run_config(run: str | Path) -> TrainConfig:
    """The training config of run folder ``run``, of either layout (:func:`run_files`)."""
    files = run_files(run)
    return load_config(files.config) if files.zoo_args is None else zoo_config(files)


# how a model is prepared while it is written: training passes
# ``mpa_gym.agents.learned.anchor.rest_for_save`` (the policy anchored at its normaliser's zero as
# saved); it is a parameter so that reading a run folder never imports torch
Prepare = Callable[[Any], AbstractContextManager[Any]]


def save_state(model: Any, model_path: Path, norm_path: Path | None, *, prepare: Prepare
               ) -> None:
    """The model (inside ``prepare(model)``) and its normaliser, each written atomically."""
    with prepare(model):
        atomic_save(model_path, model.save)
    norm = model.get_vec_normalize_env()
    if norm is not None and norm_path is not None:
        atomic_save(norm_path, lambda f: pickle.dump(norm, f))


def checkpoint_paths(run: Path, steps: int) -> dict[str, Path]:
    d = run / "checkpoints"
    return {"model": d / f"ppo_{steps}_steps.zip",
            "normalizer": d / f"ppo_vecnormalize_{steps}_steps.pkl",
            "marker": d / f"ppo_{steps}_steps.json"}


def write_checkpoint(model: Any, run: Path, *, prepare: Prepare) -> Path:
    """A complete checkpoint at the model's step count: model, normaliser, then the marker
    (written last, so a checkpoint without it was torn by a kill and is ignored)."""
    steps = int(model.num_timesteps)
    p = checkpoint_paths(run, steps)
    has_norm = model.get_vec_normalize_env() is not None
    save_state(model, p["model"], p["normalizer"], prepare=prepare)
    files = {p["model"].name: p["model"].stat().st_size}
    if has_norm:
        files[p["normalizer"].name] = p["normalizer"].stat().st_size
    atomic_write_text(p["marker"], json.dumps({"timesteps": steps, "files": files}))
    return p["model"]


def save_final(model: Any, run: Path, *, prepare: Prepare) -> None:
    """A checkpoint at the current step count, then ``model.zip`` + ``vecnormalize.pkl``, and
    the folder's ``README.txt`` (:func:`write_readme`)."""
    write_checkpoint(model, run, prepare=prepare)
    save_state(model, run / "model.zip", run / "vecnormalize.pkl", prepare=prepare)
    write_readme(run, tuple(model.observation_space.shape))


README = """\
A trained run of mpa-gym ({env_id}), written by `mpa-gym train`.

model.zip is the PPO network alone. It takes the run's features, shape {features}: the
observation of {env_id} (shape {obs}) after the run's wrappers (config.yaml,
env_wrapper), normalised with vecnormalize.pkl. It does not take the env's own observation.
`PPO.load("model.zip").predict(obs)` accepts an observation of {env_id} whenever the two
shapes are equal (SB3 checks the shape only) and returns a wrong, often saturated action;
`PPO.load("model.zip", env=gym.make("{env_id}"))` refuses it ("Observation spaces do not
match"). Load the run with its wrappers, normaliser and supervisor instead:

    import gymnasium as gym
    from mpa_gym.agents import load_policy

    policy, env_id, cfg = load_policy("{run}")   # supervised=False: the policy alone
    env = gym.make(env_id, scenario="nominal", task=cfg.env_kwargs.get("task"))
    obs, info = env.reset(seed=0); policy.reset()
    for _ in range(1000):
        action, _ = policy.predict(obs)   # keeps its episode state; refuses a wrapped obs
        obs, reward, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            obs, info = env.reset(); policy.reset()

`mpa-gym evaluate {run}` reports it; `mpa-gym rollout --policy {run} --device URL` runs it
on a rig.
Folder: config.yaml (the resolved config), model.zip + vecnormalize.pkl (final), best/ (best
held-out evaluation), checkpoints/, eval/ (evaluations during training), tb/ (TensorBoard).
"""


def write_readme(run: Path, features: tuple[int, ...]) -> None:
    """``run/README.txt``: what ``model.zip`` takes (the features of shape ``features``, not
    the env's observation) and how to load the run (``load_policy``)."""
    env_id = load_config(run / "config.yaml").env_id
    atomic_write_text(run / "README.txt", README.format(
        env_id=env_id, features=features, obs=(ObservationCheck(env_id).width,), run=run))


def zip_timesteps(path: Path) -> int:
    """The step count stored in an SB3 model file (without building the model)."""
    try:
        with zipfile.ZipFile(path) as z:
            return int(json.loads(z.read("data"))["num_timesteps"])
    except (zipfile.BadZipFile, KeyError, ValueError, OSError) as e:
        raise DamagedFileError(f"{path} is damaged (not a complete SB3 model file: {e})"
                               ) from None


def checked_checkpoint(marker: Path) -> int:
    """The step count of the checkpoint whose marker is ``marker``, after checking its files'
    sizes; raises (ValueError, KeyError, TypeError, OSError) if it is incomplete or damaged."""
    meta = json.loads(marker.read_text())
    steps = int(meta["timesteps"])
    for name, size in meta["files"].items():
        if (marker.parent / name).stat().st_size != size:
            raise ValueError(f"{name} has the wrong size")
    return steps


def latest_state(run: Path, normalized: bool) -> tuple[int, Path, Path | None, list[str]] | None:
    """The newest complete state of a run: (steps, model file, normaliser file, notes) or None.

    Candidates are the complete checkpoints and ``model.zip`` (+ ``vecnormalize.pkl``); a damaged
    or incomplete one is skipped and named in the notes."""
    notes: list[str] = []
    cands: list[tuple[int, Path, Path | None]] = []
    for marker in (run / "checkpoints").glob("ppo_*_steps.json"):
        try:
            steps = checked_checkpoint(marker)
        except (ValueError, KeyError, TypeError, OSError) as e:
            notes.append(f"skipped damaged checkpoint {marker.name} ({e})")
            continue
        p = checkpoint_paths(run, steps)
        cands.append((steps, p["model"], p["normalizer"] if normalized else None))
    root = run / "model.zip"
    if root.is_file():
        try:
            norm = run / "vecnormalize.pkl" if normalized else None
            if norm is not None and not norm.is_file():
                raise DamagedFileError(f"{norm} is missing")
            cands.append((zip_timesteps(root), root, norm))
        except DamagedFileError as e:
            notes.append(f"skipped model.zip ({e})")
    if not cands:
        return None
    # newest first; at equal step counts a checkpoint and model.zip hold the same state
    steps, model, norm = max(cands, key=lambda c: (c[0], c[1] != root))
    if root.is_file() and model != root:
        try:
            root_steps = zip_timesteps(root)
        except DamagedFileError:
            root_steps = -1
        if root_steps > steps:
            notes.append(f"model.zip ({root_steps} steps) is newer but unusable; rewinding to "
                         f"{steps} steps")
    return steps, model, norm, notes


def read_eval_history(folder: Path) -> tuple[list[dict[str, Any]], list[int], list[list[float]],
                                             list[list[int]]]:
    """(history, timesteps, returns, lengths) of ``eval/``; a damaged file is named."""
    jpath, npath = folder / EVAL_JSON, folder / EVAL_NPZ
    try:
        history = json.loads(jpath.read_text())
        if not isinstance(history, list):
            raise ValueError("not a list of evaluations")
    except (ValueError, UnicodeDecodeError) as e:
        raise DamagedFileError(f"{jpath} is damaged (not a JSON list of evaluations: {e}); "
                               "delete it (and evaluations.npz) to start the history afresh"
                               ) from None
    if not npath.is_file():
        return history, [], [], []
    try:
        with np.load(npath) as npz:
            ts = [int(t) for t in npz["timesteps"]]
            res = [list(map(float, r)) for r in npz["results"]]
            lens = [list(map(int, r)) for r in npz["ep_lengths"]]
    except Exception as e:  # zipfile, pickle and numpy's own errors: all mean "damaged"
        raise DamagedFileError(f"{npath} is damaged ({type(e).__name__}: {e}); delete it (and "
                               "evaluations.json) to start the history afresh") from None
    return history, ts, res, lens


def write_eval_history(folder: Path, history: list[dict[str, Any]], ts: list[int],
                       res: list[list[float]], lens: list[list[int]]) -> None:
    atomic_save(folder / EVAL_NPZ, lambda f: np.savez(f, timesteps=np.array(ts, dtype=np.int64),
                                                      results=np.array(res),
                                                      ep_lengths=np.array(lens)))
    atomic_write_text(folder / EVAL_JSON, json.dumps(history, indent=1))


def cut_eval_history(folder: Path, steps: int) -> int:
    """Drop the evaluations after ``steps`` (made by a run later killed); returns how many."""
    if not (folder / EVAL_JSON).is_file():
        return 0
    history, ts, res, lens = read_eval_history(folder)
    keep = [i for i, t in enumerate(ts) if t <= steps]
    kept_hist = [h for h in history if int(h.get("timesteps", 0)) <= steps]
    dropped = len(history) - len(kept_hist)
    if dropped or len(keep) != len(ts):
        write_eval_history(folder, kept_hist, [ts[i] for i in keep], [res[i] for i in keep],
                           [lens[i] for i in keep])
    return dropped


def reconcile_best(run: Path, steps: int, normalized: bool) -> str | None:
    """After a resume cut the evaluation history back to ``steps``: a ``best/`` saved by a
    dropped evaluation belongs to the discarded timeline. It is re-derived from the checkpoint
    at the best kept evaluation where there is one (EvalCallback keeps the first best), else
    removed (the next evaluation writes a new one). Returns what was done, or None."""
    best = run / "best" / "best_model.zip"
    if not best.is_file():
        return None
    try:
        best_steps = zip_timesteps(best)
    except DamagedFileError:
        best_steps = -1
    if 0 <= best_steps <= steps:
        return None
    was = (f"best/ was saved at step {best_steps} by an evaluation after step {steps}, dropped "
           "with the interrupted run" if best_steps >= 0 else "best/best_model.zip is damaged")
    _, ts, res, _ = (read_eval_history(run / "eval") if (run / "eval" / EVAL_JSON).is_file()
                     else ([], [], [], []))
    norm = run / "best" / "vecnormalize.pkl"
    best.unlink()  # the model goes first and comes back last: a kill leaves no mixed pair
    norm.unlink(missing_ok=True)
    if res:
        i = int(np.argmax([np.mean(r) for r in res]))
        ck = checkpoint_paths(run, ts[i])
        try:
            complete = checked_checkpoint(ck["marker"]) == ts[i]
        except (ValueError, KeyError, TypeError, OSError):
            complete = False
        if complete:
            if normalized:
                atomic_save(norm, lambda f: f.write(ck["normalizer"].read_bytes()))
            atomic_save(best, lambda f: f.write(ck["model"].read_bytes()))
            return (f"{was}: re-derived it from {ck['model'].relative_to(run)}, the best kept "
                    f"evaluation (step {ts[i]}, mean return {np.mean(res[i]):.4g})")
    return (f"{was}: removed it (no checkpoint at the best kept evaluation); the next "
            "evaluation writes a new one")


# ----------------------------------------------------------------------------- callbacks
