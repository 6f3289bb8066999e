"""Learned policies behind the same ``predict`` interface as the baselines, and loading any
controller by name (``ff``, ``pid``, ``mbfb``) or run folder.

A run folder whose config has a ``supervisor`` loads under it (the supervised system: what runs
on the rig). ``RUN_DIR:alone`` (:data:`ALONE`; ``load_policy(..., supervised=False)`` in code)
loads the same run without it: the learned policy alone, whose figures are the policy's own
wherever the supervisor would have handed the loop to its fallback. Reports label it
``<run> (alone)`` (:func:`spec_label`) and show it beside the supervised run
(:func:`with_alone`), so that no figure of the fallback passes for the policy's.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np

from mpa_gym.agents.controllers.baselines import BASELINES, Policy, make_baseline
from mpa_gym.agents.controllers.excite import ExcitePolicy
from mpa_gym.agents.controllers.supervisor import Supervised
from mpa_gym.agents.learned.config import TrainConfig, load_config
from mpa_gym.agents.learned.frontend import ActionSpec, FeatureSpec, Frontend, new_state
from mpa_gym.agents.learned.inference import DeployedPolicy
from mpa_gym.agents.learned.runs import legacy_objects
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.files import DamagedFileError
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.contract import obs_names
from mpa_gym.task.plan import make_plan

ALONE = ":alone"  # a run folder's spec suffix: its policy without its supervisor
ALONE_LABEL = " (alone)"  # what reports append to the run's name for it


def run_of(spec: str) -> tuple[Path | None, bool]:
    """(the run folder of ``spec`` or None for a baseline, whether it runs supervised): a run
    folder as given runs under its config's supervisor (if it has one); ``RUN_DIR:alone``
    without it. A folder whose own name ends in ``:alone`` is that folder."""
    if Path(spec).is_dir():
        return Path(spec), True
    if spec.endswith(ALONE) and Path(spec[:-len(ALONE)]).is_dir():
        return Path(spec[:-len(ALONE)]), False
    return None, True


def spec_label(spec: str) -> str:
    """A controller's name in reports: a baseline's name, a run folder's name, and for
    ``RUN_DIR:alone`` the folder's name + `` (alone)``."""
    run, supervised = run_of(spec)
    if run is None:
        return spec
    return run.name + ("" if supervised else ALONE_LABEL)


def has_supervisor(spec: str) -> bool:
    """Whether ``spec`` is a run folder (as given, not ``:alone``) whose config has a
    ``supervisor`` section."""
    run, supervised = run_of(spec)
    return (run is not None and supervised and (run / "config.yaml").is_file()
            and load_config(run / "config.yaml").supervisor is not None)


def with_alone(specs: list[str]) -> list[str]:
    """``specs`` with ``RUN_DIR:alone`` after every supervised run folder (one whose config has
    a ``supervisor``) that is not already followed by it: every report shows the policy alone
    beside the supervised system. Idempotent."""
    out: list[str] = []
    for spec in specs:
        if spec in out:
            continue
        out.append(spec)
        if has_supervisor(spec) and spec + ALONE not in specs:
            out.append(spec + ALONE)
    return out


class LearnedPolicy:
    """An SB3 model with its observation normaliser, feature state and action coordinates.

    ``predict`` takes the env's own observation (as the baselines do): it appends the tracking
    error features when the model was trained with ``TrackingErrorObservation`` (``features``;
    their integrals and the previous action are the returned state), normalises with the
    training statistics, and returns the deterministic action — mapped from force–stiffness
    coordinates to the env's residual action when the model was trained with
    ``ForceStiffnessAction`` (``force_stiffness`` = (force_N, stiffness_rel, residual scale)),
    with its stiffness estimator if it had one (``stiffness_adapt_s``; its state is part of the
    returned state).
    """

    def __init__(self, model: Any, normalizer: Any = None, features: FeatureSpec | None = None,
                 dt: float = 0.01, force_stiffness: tuple[float, float, float] | None = None,
                 stiffness_adapt_s: float | None = None) -> None:
        self.frontend = Frontend.of(features, dt, force_stiffness, stiffness_adapt_s)
        self.model, self.normalizer, self.features, self.dt = model, normalizer, features, dt
        self.force_stiffness = force_stiffness
        self.stiffness_adapt_s = (None if self.frontend.action is None
                                  else self.frontend.action.stiffness_adapt_s)

    def _mean_action(self, obs: np.ndarray) -> np.ndarray:
        """SB3's deterministic action, ``model.predict(obs, deterministic=True)``, by the same
        torch operations (features, actor MLP, action net: the Gaussian's mean; then the clip to
        the action space) without predict's per-call overhead (training-mode switch, the
        distribution object): a report calls it once per step for thousands of steps."""
        import torch
        from stable_baselines3.common.distributions import DiagGaussianDistribution

        pol = self.model.policy
        if not isinstance(pol.action_dist, DiagGaussianDistribution) or pol.squash_output:
            return self.model.predict(obs, deterministic=True)[0]
        if pol.training:
            pol.set_training_mode(False)
        with torch.no_grad():
            t = torch.as_tensor(obs, device=pol.device).float()
            latent = pol.mlp_extractor.forward_actor(
                pol.extract_features(t, pol.pi_features_extractor))
            # a RestAnchoredPolicy's mean is its own (agents/learned/anchor.py)
            mean = pol.action_mean(latent) if hasattr(pol, "action_mean") else \
                pol.action_net(latent)
        a = mean.cpu().numpy().reshape((-1, *pol.action_space.shape))
        return np.clip(a, pol.action_space.low, pol.action_space.high)

    @classmethod
    def from_config(cls, model: Any, normalizer: Any, cfg: TrainConfig) -> LearnedPolicy:
        """The policy for a model trained with ``cfg``'s wrappers and task."""
        task_cfg = TaskConfig.from_kwargs(cfg.env_kwargs.get("task") or {})
        ow, aw = cfg.observation_wrapper, cfg.action_wrapper
        fs, tau = None, None
        if aw is not None:
            spec = ActionSpec(**aw)
            fs = (spec.force_N, spec.stiffness_rel, task_cfg.residual_scale_bar)
            tau = spec.stiffness_adapt_s
        return cls(model, normalizer, FeatureSpec(**ow) if ow is not None else None,
                   task_cfg.dt_s, fs, tau)

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        """Actions for one observation or a batch; ``state`` (returned, passed back on the next
        call) is each row's front-end record (``frontend.STATE``: integrals, previous action,
        stiffness estimator), restarted where ``episode_start`` or when it is None."""
        raw = np.asarray(observation, dtype=np.float32)
        single = raw.ndim == 1
        raw = raw.reshape(1, -1) if single else raw
        n = raw.shape[0]
        fresh = np.full(n, state is None)
        if episode_start is not None:
            fresh |= np.asarray(episode_start, dtype=bool).reshape(-1)
        st = new_state(n) if state is None else np.array(state).reshape(n)  # a copy
        obs = self.frontend.observe(raw, st, fresh)
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        action = (self._mean_action(obs) if deterministic
                  else self.model.predict(obs, deterministic=False)[0])
        action = self.frontend.act(action, raw, st)
        return (action[0] if single else action), st


def load_run(run_dir: str | Path, which: str = "final", deployed: bool = False
             ) -> tuple[Any, Any]:
    """The policy of a training run folder (``final`` model or the ``best`` one) and its config.

    ``deployed``: the compiled single-observation path of ``mpa_gym.agents.learned.inference`` (for
    the rig's real-time loop) instead of the SB3 one (batches, evaluation). The SB3 path is loaded
    once per process for as long as the run's files are unchanged (a report loads a run for every
    batch it runs; ``LearnedPolicy`` keeps no state of its own, so they can share it)."""
    run = Path(run_dir)
    files = (("config.yaml", "model.zip", "vecnormalize.pkl") if which == "final" else
             ("config.yaml", "best/best_model.zip", "best/vecnormalize.pkl"))
    stamp = tuple(_stamp(run / name) for name in files)
    if not deployed and stamp[1] is not None:
        return _load_learned(str(run.resolve()), which, stamp)
    return _load_run(run, which, deployed)


def _stamp(path: Path) -> tuple[int, int] | None:
    """(mtime [ns], size) of a file, None if there is none."""
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=8)
def _load_learned(run: str, which: str, stamp: tuple[Any, ...]) -> tuple[Any, Any]:
    """``load_run`` of an SB3 policy, once per run files' ``stamp`` (mtimes and sizes)."""
    return _load_run(Path(run), which, False)


def _load_run(run_dir: str | Path, which: str, deployed: bool) -> tuple[Any, Any]:
    import torch
    from stable_baselines3.common.vec_env import VecNormalize

    # one small MLP per step: a thread pool only adds latency (and competes with the rig's loop)
    torch.set_num_threads(1)

    run = Path(run_dir)
    cfg = load_config(run / "config.yaml")
    model_path = run / ("model.zip" if which == "final" else "best" / Path("best_model.zip"))
    if not model_path.is_file():
        raise FileNotFoundError(f"{model_path} not found: is {run} a finished run folder?")
    try:
        model = SavedModel.load(model_path)
    except Exception as e:  # a truncated zip, a foreign file: zipfile, pickle, torch errors
        raise DamagedFileError(f"{model_path} is damaged ({type(e).__name__}: {e})") from None
    norm = None
    norm_path = run / ("vecnormalize.pkl" if which == "final" else "best/vecnormalize.pkl")
    if cfg.normalize:
        if not norm_path.is_file():
            raise FileNotFoundError(f"{norm_path} not found (the run normalises observations)")
        try:
            norm = VecNormalize.load(str(norm_path), _DummyVec(model))
        except Exception as e:  # a truncated pickle: EOFError, UnpicklingError, …
            raise DamagedFileError(f"{norm_path} is damaged ({type(e).__name__}: {e})"
                                   ) from None
        norm.training = False
        norm.norm_reward = False
    policy = LearnedPolicy.from_config(model, norm, cfg)
    env_width = len(obs_names(cfg.env_id == "MPALegResidual-v0"))
    width, trained = policy.frontend.width(env_width), model.observation_space.shape
    if trained != (width,):  # the config is not the one the model was trained with
        raise ValueError(f"{run}: config.yaml's env and env_wrapper give {width}-wide "
                         f"observations, model.zip was trained on {trained}: the run's config "
                         "does not match its model (was config.yaml edited or copied in?)")
    if deployed:
        return DeployedPolicy.from_learned(policy, env_width), cfg
    return policy, cfg


class SavedModel:
    """The policy of a saved SB3 model (``model.zip``) for inference, without the algorithm.

    ``PPO.load`` rebuilds the whole algorithm: a rollout buffer, and an Adam optimiser whose
    construction imports ``torch._dynamo`` (about a second per process). Evaluation and
    rollouts need only the network, so this builds the saved policy class with the saved
    spaces and keyword arguments, no optimiser, and loads its weights, through SB3's own
    ``load_from_zip_file``. ``predict`` is SB3's ``policy.predict``, which ``PPO.predict``
    calls; ``num_timesteps`` is the training steps the model was saved at."""

    def __init__(self, policy: Any, num_timesteps: int) -> None:
        self.policy, self.num_timesteps = policy, num_timesteps
        self.observation_space = policy.observation_space
        self.action_space = policy.action_space

    @classmethod
    def load(cls, path: str | Path) -> SavedModel:
        from stable_baselines3.common.save_util import load_from_zip_file

        data, params, _ = load_from_zip_file(path, device="cpu",
                                             custom_objects=legacy_objects(Path(path)))
        if data is None or "policy" not in params:
            raise ValueError("not a saved SB3 model (no data or no policy weights)")
        kwargs = {**data.get("policy_kwargs", {}), "optimizer_class": _NoOptimizer}
        policy = data["policy_class"](data["observation_space"], data["action_space"],
                                      lambda _: 0.0, **kwargs)
        policy.load_state_dict(params["policy"])
        policy.set_training_mode(False)
        return cls(policy, int(data.get("num_timesteps", 0)))

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = False
                ) -> tuple[np.ndarray, Any]:
        return self.policy.predict(observation, state, episode_start, deterministic)

    def get_vec_normalize_env(self) -> None:
        """No env: the normaliser is the ``LearnedPolicy``'s
        (``mpa_gym.agents.learned.anchor.set_rest``)."""
        return None


class _NoOptimizer:
    """The optimiser of a policy loaded for inference: none (it is never stepped)."""

    def __init__(self, params: Any, lr: float = 0.0, **kwargs: Any) -> None:
        pass


class _DummyVec:
    """Just enough of a VecEnv for VecNormalize.load (spaces and num_envs)."""

    def __init__(self, model: Any) -> None:
        self.observation_space = model.observation_space
        self.action_space = model.action_space
        self.num_envs = 1
        self.render_mode = None


def check_control_period(cfg: TrainConfig, dt_s: float, run: str | Path) -> None:
    """Refuse to run a trained policy at a control period other than its training ``dt_s``:
    its tracking-error integrals are summed with the training period and its actions were
    learned for that period (slew per step, plant response per step), so at another rate it
    acts silently wrong."""
    run_dt = TaskConfig.from_kwargs(cfg.env_kwargs.get("task") or {}).dt_s
    if not math.isclose(dt_s, run_dt, rel_tol=1e-9):
        raise ValueError(f"--control-hz {1.0 / dt_s:g} (period {dt_s:g} s) vs the run's dt_s "
                         f"{run_dt:g} s = {1.0 / run_dt:g} Hz: policy {run} was trained at "
                         f"{1.0 / run_dt:g} Hz and acts at that rate only; roll it out with "
                         f"--control-hz {1.0 / run_dt:g}")


def supervise(policy: Policy, cfg: TrainConfig, env_kwargs: dict[str, Any] | None = None
              ) -> Policy:
    """``policy`` under the run-time assurance of its config's ``supervisor``
    (``mpa_gym.agents.controllers.supervisor``): the fallback baseline is built for the env of
    ``env_kwargs`` (scenario, stiffness; task settings over the run's own), else for the run's
    training env."""


    own, given = cfg.env_kwargs, env_kwargs or {}
    task = {**(own.get("task") or {}), **(given.get("task") or {})}
    scenario = given.get("scenario", own.get("scenario", "nominal"))
    # a run trained on several designs (a list) has none of its own to give the fallback
    stiffness = given.get("stiffness", None if isinstance(own.get("stiffness"), list)
                          else own.get("stiffness"))
    fallback, last = (None if name is None else make_baseline(name, scenario, stiffness, task)
                      for name in (cfg.supervisor.fallback, cfg.supervisor.last_resort))
    return Supervised(policy, fallback, TaskConfig.from_kwargs(task).dt_s,
                      load_scenario(scenario).reference.period, cfg.supervisor, last)


def load_policy(spec: str, env_kwargs: dict[str, Any] | None = None, deployed: bool = False,
                supervised: bool = True) -> tuple[Policy, str, Any]:
    """(policy, env id, run config or None) for ``ff`` / ``pid`` / ``mbfb``, ``excite`` (the
    identification excitation), a run folder or ``RUN_DIR:alone`` (:data:`ALONE`).

    Baselines are built for the env made with ``env_kwargs`` (scenario, stiffness, task); a run
    is loaded ``deployed`` (``load_run``) when asked, wrapped in its config's ``supervisor``
    if it has one (:func:`supervise`) unless ``supervised`` is False or the spec ends in
    ``:alone`` (the policy alone; its config still holds the section), and refused
    (``check_control_period``, before its model is loaded) when ``env_kwargs`` sets a
    ``task.dt_s`` (the control period it will run at: rollout's ``--control-hz``) other than
    its training one.
    """
    if spec == "excite":  # system-identification excitation (mpa_gym.agents.controllers.excite)
        kw = env_kwargs or {}
        return (ExcitePolicy(make_plan(kw.get("scenario", "nominal"), kw.get("stiffness"),
                                       TaskConfig.from_kwargs(kw.get("task")))),
                "MPALegResidual-v0", None)
    if spec in BASELINES:
        kw = env_kwargs or {}
        return (make_baseline(spec, kw.get("scenario", "nominal"), kw.get("stiffness"),
                              kw.get("task")), "MPALegResidual-v0", None)
    run, as_given = run_of(spec)
    if run is not None:
        dt = ((env_kwargs or {}).get("task") or {}).get("dt_s")
        if dt is not None and (run / "config.yaml").is_file():
            check_control_period(load_config(run / "config.yaml"), dt, run)
        policy, cfg = load_run(run, deployed=deployed)
        if cfg.supervisor is not None and supervised and as_given:
            policy = supervise(policy, cfg, env_kwargs)
        return policy, cfg.env_id, cfg
    raise ValueError(f"policy={spec!r} is neither a baseline {sorted(BASELINES)} nor a run "
                     f"folder (or a run folder + {ALONE!r}: its policy without its supervisor)")
