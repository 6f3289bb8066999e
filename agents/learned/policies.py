"""Learned policies behind the same ``predict`` interface as the baselines, and loading any
controller by name (``ff``, ``pid``, ``mbfb``, ``afc``, ``rc``), run folder or, for your own
controller, ``module:Class`` (:func:`user_controller`; the interface is in docs/design.md,
"Your own controller").

A run folder whose config has a ``supervisor`` loads under it (the supervised system: what runs
on the rig). ``RUN_DIR:alone`` (:data:`ALONE`; ``load_policy(..., supervised=False)`` in code)
loads the same run without it: the learned policy alone, whose figures are the policy's own
wherever the supervisor would have handed the loop to its fallback. Reports label it
``<run> (alone)`` (:func:`spec_label`) and show it beside the supervised run
(:func:`with_alone`), so that no figure of the fallback passes for the policy's.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import importlib
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from mpa_gym.agents.controllers.baselines import BASELINES, Policy, make_baseline
from mpa_gym.agents.controllers.excite import ExcitePolicy
from mpa_gym.agents.controllers.gains import Gains
from mpa_gym.agents.controllers.supervisor import Supervised
from mpa_gym.agents.learned.config import TrainConfig
from mpa_gym.agents.learned.episodic import Episodic, ObservationCheck
from mpa_gym.agents.learned.frontend import ActionSpec, FeatureSpec, Frontend
from mpa_gym.agents.learned.inference import DeployedPolicy
from mpa_gym.agents.learned.runs import legacy_objects, read_run_config, run_files
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.files import DamagedFileError
from mpa_gym.model.params import DEFAULT_PARAMS
from mpa_gym.task.config import TaskConfig
from mpa_gym.task.contract import obs_names
from mpa_gym.task.plan import make_plan

ALONE = ":alone"  # a run folder's spec suffix: its policy without its supervisor
ALONE_LABEL = " (alone)"  # what reports append to the run's name for it
USER_SPEC = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*")  # module:Class, your own controller


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
    return (run is not None and supervised and run_files(run).config.is_file()
            and read_run_config(run).supervisor is not None)


def selects(spec: str) -> bool:
    """Whether ``spec`` is a supervised run folder whose supervisor chooses the stage it starts
    at on the model (``supervisor.select``; ``mpa_gym.agents.evaluation.select``): it is loaded
    for each plant it runs on."""
    return has_supervisor(spec) and read_run_config(run_of(spec)[0]).supervisor.select is not None


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


def is_user_spec(spec: str) -> bool:
    """Whether ``spec`` names your own controller class, ``module:Class`` (not a baseline, not
    a run folder nor ``RUN_DIR:alone``)."""
    return (spec not in BASELINES and run_of(spec)[0] is None
            and USER_SPEC.fullmatch(spec) is not None)


def builds_per_scenario(spec: str) -> bool:
    """Whether ``spec``'s controller is built for each scenario's plan (a baseline, your own
    class) rather than loaded once (a run folder)."""
    return spec in BASELINES or is_user_spec(spec)


def loads_per_scenario(spec: str) -> bool:
    """Whether a report loads ``spec``'s controller for each scenario it runs on: one built for
    each scenario's plan (:func:`builds_per_scenario`), a supervised run, whose supervisor
    judges its loop over the scenario's reference period and hands it to fallbacks built for
    the scenario's plan (:func:`supervise`), and a policy told the rig's delays
    (:func:`tells_delays`: the scenario's plant's), and a supervisor that chooses its start
    on the plant (:func:`selects`). The run's model is read once either way
    (:func:`load_run`); any other run's policy is loaded once and serves every scenario."""
    return builds_per_scenario(spec) or has_supervisor(spec) or tells_delays(spec)


def tells_delays(spec: str) -> bool:
    """Whether ``spec`` is a run folder (alone or supervised) whose policy observes the rig's
    regulator dead time and lag (``FeatureSpec.delay_observation``)."""
    run, _ = run_of(spec)
    if run is None or not run_files(run).config.is_file():
        return False
    return bool((read_run_config(run).observation_wrapper or {}).get("delay_observation"))


def load_for_plant(spec: str, scenario: Any, plant: dict[str, Any] | None,
                   gains: Gains | None = None) -> tuple[Policy, str, Any]:
    """:func:`load_policy` for ``scenario`` run with ``plant``'s fields (a sweep cell, a random
    rig): a policy that observes the rig's delays (:func:`tells_delays`) is told this plant's
    dead time and lag (as ``mpa-gym identify`` would measure them on that rig), not the
    scenario's; every other controller is loaded for the scenario."""
    if plant and tells_delays(spec):
        base = load_scenario(scenario)
        told = {k: plant[k] for k in ("pressure_dead_time_s", "pressure_lag_s") if k in plant}
        scenario = dataclasses.replace(base, plant=dataclasses.replace(base.plant, **told))
    return load_policy(spec, {"scenario": scenario}, gains=gains)


def user_controller(spec: str, flag: str = "--policy") -> type:
    """The class of ``module:Class``, imported; a ValueError naming ``flag`` and the value if
    the module cannot be imported, has no such class, or the class has no ``predict``."""
    module, _, name = spec.partition(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name is not None and module.startswith(e.name):
            raise ValueError(f"{flag} {spec!r}: no module named {e.name!r} (a controller given "
                             "as module:Class must be importable: installed, or its folder on "
                             "PYTHONPATH)") from None
        raise ValueError(f"{flag} {spec!r}: importing {module!r} failed: {e}") from None
    except Exception as e:  # the module's own code failed: the user's to fix
        raise ValueError(f"{flag} {spec!r}: importing {module!r} failed: "
                         f"{type(e).__name__}: {e}") from None
    cls = getattr(mod, name, None)
    if cls is None:
        raise ValueError(f"{flag} {spec!r}: module {module!r} has no {name!r}")
    if not isinstance(cls, type) or not callable(getattr(cls, "predict", None)):
        raise ValueError(f"{flag} {spec!r}: {name} is not a controller class (it needs "
                         "predict(observation, state, episode_start, deterministic); "
                         "docs/design.md, \"Your own controller\")")
    return cls


def make_user_controller(spec: str, scenario: Any = "nominal", stiffness: Any = None,
                         task: dict[str, Any] | None = None, flag: str = "--policy") -> Policy:
    """Your controller ``module:Class`` built as ``Class(plan, params)`` for an env made with
    (scenario, stiffness, task): ``plan`` its ``mpa_gym.task.plan.TaskPlan`` (the reference,
    the nominal feedforward, ``plan.cfg`` the task settings), ``params`` the nominal model."""
    cls = user_controller(spec, flag)
    plan = make_plan(scenario, stiffness, TaskConfig.from_kwargs(task))
    try:
        return cls(plan, DEFAULT_PARAMS)
    except Exception as e:  # its constructor failed: say so as the user's error
        raise ValueError(f"{flag} {spec!r}: {cls.__name__}(plan, params) failed: "
                         f"{type(e).__name__}: {e}") from None


class LearnedPolicy(Episodic):
    """An SB3 model with its observation normaliser, feature state and action coordinates.

    ``predict`` takes the env's own observation (as the baselines do): it appends the tracking
    error features when the model was trained with ``TrackingErrorObservation`` (``features``;
    their integrals and the previous action are the returned state), normalises with the
    training statistics, and returns the deterministic action — mapped from force–stiffness
    coordinates to the env's residual action when the model was trained with
    ``ForceStiffnessAction`` (``action``, its settings, and the residual env's
    ``residual_scale_bar``), with its stiffness estimator and harmonic force correction if
    it had them (their state is part of the returned state). The state not passed back is
    kept (``Episodic``: per row of a batch, restarted by ``reset()`` or ``episode_start``);
    ``check`` (set by :meth:`from_config`: the run's env id) refuses an observation that is
    not that env's own.
    """

    def __init__(self, model: Any, normalizer: Any = None, features: FeatureSpec | None = None,
                 dt: float = 0.01, action: ActionSpec | None = None,
                 residual_scale_bar: float | None = None,
                 check: ObservationCheck | None = None) -> None:
        self.check = check
        self.frontend = Frontend(features, action, dt, residual_scale_bar)
        self.model, self.normalizer, self.features, self.dt = model, normalizer, features, dt
        self.residual_scale_bar = residual_scale_bar

    @property
    def action(self) -> ActionSpec | None:
        """The action map (``ForceStiffnessAction``'s settings), None: the network's action
        as it is."""
        return self.frontend.action

    @classmethod
    def stack_rows(cls, policies: list[LearnedPolicy]) -> LearnedPolicy:
        """One policy for a batch whose row i is ``policies[i]``'s (``baselines.stack``): the
        same model, normaliser, features and action map, each row told its own policy's
        delays. One network call per step for all rows, where each of them would make its own:
        the actions are each policy's to float32 rounding (torch's product over a batch of
        rows need not round the last bit as over one row; ~1e-7)."""
        first = policies[0]
        for p in policies:
            if (p.model is not first.model or p.normalizer is not first.normalizer
                    or p.features != first.features or p.dt != first.dt
                    or p.action != first.action
                    or p.residual_scale_bar != first.residual_scale_bar):
                raise ValueError("stack: learned policies of one model, normaliser, features "
                                 "and action map only")
            if np.ndim(p.frontend.known_delay_s) != 1:
                raise ValueError("stack: a stack of learned policies does not stack again")
        out = cls(first.model, first.normalizer, first.features, first.dt, first.action,
                  first.residual_scale_bar, first.check)
        out.frontend.known_delay_s = np.array([p.frontend.known_delay_s for p in policies],
                                              dtype=np.float64).reshape(len(policies), 2)
        return out

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
    def from_config(cls, model: Any, normalizer: Any, cfg: TrainConfig, run: str = ""
                    ) -> LearnedPolicy:
        """The policy for a model trained with ``cfg``'s wrappers and task (in the run folder
        ``run``, which its errors name)."""
        task_cfg = TaskConfig.from_kwargs(cfg.env_kwargs.get("task") or {})
        ow, aw = cfg.observation_wrapper, cfg.action_wrapper
        return cls(model, normalizer, FeatureSpec(**ow) if ow is not None else None,
                   task_cfg.dt_s, ActionSpec(**aw) if aw is not None else None,
                   task_cfg.residual_scale_bar if aw is not None else None,
                   ObservationCheck(cfg.env_id, run))

    def _predict(self, observation: np.ndarray, state: Any, episode_start: np.ndarray | None,
                 deterministic: bool) -> tuple[np.ndarray, Any]:
        """Actions for one observation or a batch; ``state`` is each row's front-end record
        (``frontend.STATE``: integrals, previous action, harmonic force correction, stiffness
        estimator), restarted where ``episode_start`` or when it is None."""
        raw = np.asarray(observation, dtype=np.float32)
        single = raw.ndim == 1
        raw = raw.reshape(1, -1) if single else raw
        n = raw.shape[0]
        fresh = np.full(n, state is None)
        if episode_start is not None:
            fresh |= np.asarray(episode_start, dtype=bool).reshape(-1)
        st = self.frontend.new_state(n) if state is None else np.array(state).reshape(n)  # a copy
        obs = self.frontend.observe(raw, st, fresh)
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        action = (self._mean_action(obs) if deterministic
                  else self.model.predict(obs, deterministic=False)[0])
        action = self.frontend.act(action, raw, st)
        return (action[0] if single else action), st


def tell_delays(policy: Any, scenario: Any) -> Any:
    """``policy`` (loaded, alone) told the regulator dead time and lag of ``scenario``'s plant
    if it observes them (``FeatureSpec.delay_observation``); returned."""
    if getattr(policy, "features", None) is not None and policy.features.delay_observation:
        plant = load_scenario(scenario).plant
        policy.frontend.known_delay_s = (plant.pressure_dead_time_s, plant.pressure_lag_s)
    return policy


def known_delays(policy: Any) -> tuple[float, float] | None:
    """[s] (dead time, lag) a loaded policy (or the policy under a supervisor) was told of its
    rig, None if it does not observe them."""
    inner = getattr(policy, "policy", None) if isinstance(policy, Supervised) else policy
    features = getattr(inner, "features", None)
    if features is None or not features.delay_observation:
        return None
    return tuple(float(v) for v in inner.frontend.known_delay_s)


def load_run(run_dir: str | Path, which: str = "final", deployed: bool = False
             ) -> tuple[Any, Any]:
    """(policy, config) of a run folder: the learned policy alone, never its supervisor; a
    folder of ``mpa-gym train`` or of rl-baselines3-zoo (``mpa_gym.agents.learned.runs``:
    ``run_files``, ``read_run_config``).

    :func:`load_policy` is the loader (supervised as the config says, or not); this is its
    step that reads the model. ``which``: the ``final`` model or the ``best`` one;
    ``deployed``: the compiled single-observation path of ``mpa_gym.agents.learned.inference``
    (for the rig's real-time loop) instead of the SB3 one (batches, evaluation). The SB3 model
    is read once per process for as long as the run's files are unchanged (a report loads a
    run for every batch it runs); each call returns a policy of its own around it, so the
    episode state one caller leaves in it (``Episodic``) is no other caller's."""
    run = Path(run_dir)
    files = run_files(run, which)
    stamp = tuple(_stamp(path) for path in (files.config, files.model, files.normalizer,
                                            files.zoo_args) if path is not None)
    if not deployed and stamp[1] is not None:
        shared, cfg = _load_learned(str(run.resolve()), which, stamp)
        policy = copy.copy(shared)
        policy.frontend = copy.copy(shared.frontend)  # its rig's delays are this policy's
        policy.reset()
        return policy, cfg
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
    files = run_files(run, which)
    cfg = read_run_config(run)
    model_path = files.model
    if not model_path.is_file():
        raise FileNotFoundError(f"{model_path} not found: is {run} a finished run folder?")
    try:
        model = SavedModel.load(model_path)
    except Exception as e:  # a truncated zip, a foreign file: zipfile, pickle, torch errors
        raise DamagedFileError(f"{model_path} is damaged ({type(e).__name__}: {e})") from None
    norm = None
    norm_path = files.normalizer
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
    policy = LearnedPolicy.from_config(model, norm, cfg, str(run))
    env_width = len(obs_names(cfg.env_id == "MPALegResidual-v0"))
    width, trained = policy.frontend.width(env_width), model.observation_space.shape
    if trained != (width,):  # the config is not the one the model was trained with
        raise ValueError(f"{run}: config.yaml's env and env_wrapper give {width}-wide "
                         f"observations, model.zip was trained on {trained}: the run's config "
                         "does not match its model (was config.yaml edited or copied in?)")
    if deployed:
        return DeployedPolicy.from_learned(policy, env_width), cfg
    return policy, cfg


SCHEDULES = ("learning_rate", "lr_schedule", "clip_range", "clip_range_vf")


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

        # the optimiser's schedules are not read for inference; rl-baselines3-zoo pickles them
        # as classes of rl_zoo3, which need not be installed where its run is evaluated
        skip = dict.fromkeys(SCHEDULES, 0.0)
        data, params, _ = load_from_zip_file(path, device="cpu", custom_objects={
            **legacy_objects(Path(path)), **skip})
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
    training env, with the section's ``gains`` if it has them."""

    own, given = cfg.env_kwargs, env_kwargs or {}
    task = {**(own.get("task") or {}), **(given.get("task") or {})}
    scenario = given.get("scenario", own.get("scenario", "nominal"))
    # a run trained on several designs (a list) has none of its own to give the fallback
    stiffness = given.get("stiffness", None if isinstance(own.get("stiffness"), list)
                          else own.get("stiffness"))
    def build(name: str | None) -> Policy | None:
        if name is None:
            return None
        try:
            return make_baseline(name, scenario, stiffness, task,
                                 gains=cfg.supervisor.gains.get(name))
        except ValueError as e:  # e.g. rc's delay line for a reference it cannot hold
            sc = load_scenario(scenario).name
            raise ValueError(f"the supervisor's fallback {name!r} cannot be built for scenario "
                             f"{sc!r}: {e}. Evaluate the policy alone (RUN_DIR{ALONE}) there, "
                             "or give the run's supervisor other stages") from None

    fallback, last = build(cfg.supervisor.fallback), build(cfg.supervisor.last_resort)
    return SupervisedPolicy(policy, fallback, TaskConfig.from_kwargs(task).dt_s,
                            load_scenario(scenario).reference.period, cfg.supervisor, last)


class SupervisedPolicy(Episodic, Supervised):
    """A run's policy under its supervisor (:func:`supervise`), called as a loaded policy is
    (``Episodic``: the state kept when it is not passed back, the observation checked as the
    policy's own ``check``)."""

    def __init__(self, policy: Policy, *args: Any, **kwargs: Any) -> None:
        super().__init__(policy, *args, **kwargs)
        self.check = getattr(policy, "check", None)

    def _predict(self, observation: np.ndarray, state: Any, episode_start: np.ndarray | None,
                 deterministic: bool) -> tuple[np.ndarray, Any]:
        return Supervised.predict(self, observation, state, episode_start, deterministic)


def load_policy(spec: str | Path, env_kwargs: dict[str, Any] | None = None,
                deployed: bool = False, supervised: bool = True, which: str = "final",
                gains: Gains | None = None, flag: str = "--policy"
                ) -> tuple[Policy, str, Any]:
    """Load a controller: a trained run folder (with or without its supervisor) or a built-in
    one, ready to act on the observations of the env it names.

    Parameters
    ----------
    spec : str or path
        A run folder (what ``mpa-gym train`` writes), the same folder + ``:alone``
        (:data:`ALONE`, as ``supervised=False``), a baseline (``BASELINES``: ``ff``, ``pid``,
        ``mbfb``, ``afc``, ``rc``), ``excite`` (the identification excitation) or your own
        controller ``module:Class`` (:func:`make_user_controller`).
    env_kwargs : dict, optional
        The keyword arguments of the env the controller will run in (``scenario``,
        ``stiffness``, ``task``). Baselines, excitation and a supervisor's fallback are built
        for it (a run's supervisor: over the run's own task settings). A ``task.dt_s`` other
        than the run's training period is refused before the model is read (a learned
        policy acts at its training rate only; rollout's ``--control-hz``).
    deployed : bool
        A run through the compiled single-observation path
        (``mpa_gym.agents.learned.inference.DeployedPolicy``: the rig's real-time loop) instead
        of SB3's torch one (batches). Both give the same actions to 1e-6.
    supervised : bool
        A run under its config's ``supervisor`` section (the supervised system, what
        ``evaluate`` and ``rollout`` run), if it has one; False: the learned policy alone.
        A supervisor whose section has ``select`` starts at the policy until its start is
        chosen on the model: ``mpa_gym.agents.evaluation.select.choose_starts([loaded],
        [scenario], [plant])``, as ``evaluate`` and ``rollout`` do before the first episode.
    which : {"final", "best"}
        A run's ``model.zip`` or ``best/best_model.zip`` (the best held-out evaluation).
    gains : Gains, optional
        A baseline's gains (``load_gains``: a gains file of ``mpa-gym tune-baselines --out``).
    flag : str
        The command-line flag that gave ``spec``, named in errors.

    Returns
    -------
    policy
        SB3's ``predict(observation, state=None, episode_start=None, deterministic=True)
        -> (action, state)`` on the env's own observation, one (d,) or a batch (n, d) (the
        deployed path: one). A run's policy (``Episodic``) keeps its episode state when the
        state is not passed back: call ``policy.reset()`` where the env resets (or pass
        ``episode_start``); it refuses an observation that is not its env's own (a wrapper's
        features, another env's) with a ValueError naming the env id and the shape.
    env_id : str
        The env id it acts on (``MPALegResidual-v0`` or ``MPALeg-v0``).
    config : TrainConfig or None
        The run's config (``config.yaml``; ``env_kwargs["task"]`` holds its training task
        settings), None for a built-in controller.

    Raises
    ------
    ValueError
        ``spec`` names nothing loadable, ``which`` is unknown, or the control period differs
        from the run's.
    FileNotFoundError, mpa_gym.files.DamagedFileError
        A run folder without its model or normaliser, or with a damaged one.

    Examples
    --------
    >>> policy, env_id, cfg = load_policy("runs/ppo_residual")
    >>> env = gym.make(env_id, scenario="load_1kg", task=cfg.env_kwargs.get("task"))
    >>> obs, info = env.reset(seed=0); policy.reset()
    >>> action, _ = policy.predict(obs)                               # state kept inside
    """
    spec = str(spec)
    if spec == "excite":  # system-identification excitation (mpa_gym.agents.controllers.excite)
        kw = env_kwargs or {}
        return (ExcitePolicy(make_plan(kw.get("scenario", "nominal"), kw.get("stiffness"),
                                       TaskConfig.from_kwargs(kw.get("task")))),
                "MPALegResidual-v0", None)
    if spec in BASELINES:
        kw = env_kwargs or {}
        return (make_baseline(spec, kw.get("scenario", "nominal"), kw.get("stiffness"),
                              kw.get("task"), gains=(gains or {}).get(spec)),
                "MPALegResidual-v0", None)
    if is_user_spec(spec):
        kw = env_kwargs or {}
        return (make_user_controller(spec, kw.get("scenario", "nominal"), kw.get("stiffness"),
                                     kw.get("task"), flag), "MPALegResidual-v0", None)
    run, as_given = run_of(spec)
    if run is not None:
        dt = ((env_kwargs or {}).get("task") or {}).get("dt_s")
        if dt is not None and run_files(run).config.is_file():
            check_control_period(read_run_config(run), dt, run)
        policy, cfg = load_run(run, which, deployed)
        tell_delays(policy, (env_kwargs or {}).get("scenario", "nominal"))
        if cfg.supervisor is not None and supervised and as_given:
            policy = supervise(policy, cfg, env_kwargs)
        return policy, cfg.env_id, cfg
    raise ValueError(f"{flag} {spec!r} is neither a baseline {sorted(BASELINES)}, a run "
                     f"folder (or a run folder + {ALONE!r}: its policy without its supervisor) "
                     "nor your own controller module:Class")
