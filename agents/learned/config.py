"""Training configs in rl-baselines3-zoo's hyper-parameter format, validated.

A config file holds one top-level key per env id with rl-zoo's hyper-parameters (so the file also
works with ``python -m rl_zoo3.train --algo ppo --env MPALegResidual-v0 --gym-packages mpa_gym
-conf FILE``) and an optional top-level ``mpa_gym`` section for this harness (rl-zoo ignores it):

.. code-block:: yaml

    MPALegResidual-v0:
      n_envs: 16
      n_timesteps: !!float 2e6
      policy: MlpPolicy
      normalize: "{'norm_obs': True, 'norm_reward': True}"
      policy_kwargs: "dict(net_arch=[64, 64], log_std_init=-2.0)"
      env_kwargs: {scenario: {...}, task: {...}}
      env_wrapper:
        - mpa_gym.agents.learned.wrappers.TrackingErrorObservation:
            {errors_only: true, harmonics: 1, remodulate: true}
        - mpa_gym.agents.learned.wrappers.ForceStiffnessAction:
            {force_N: 20.0, stiffness_rel: 0.3, rate_penalty: 0.5}
      learning_rate: !!float 3e-4
      ...
    mpa_gym:
      seed: 0
      eval_scenarios: [heldout_a, load_1kg]
      eval_freq: 100000
      checkpoint_freq: 500000
"""

from __future__ import annotations

import ast
import copy
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mpa_gym  # noqa: F401  (registers the env ids)
from mpa_gym.agents.controllers.supervisor import SupervisorSpec
from mpa_gym.agents.learned.wrappers import ActionSpec, FeatureSpec, adapt_time_constant
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.configs import DEFAULT_TRAIN_CONFIG
from mpa_gym.envs.leg_env import make_plans, task_config
from mpa_gym.files import read_yaml
from mpa_gym.model.params import DEFAULT_PARAMS, check_keys

ZOO_KEYS = {"n_envs", "n_timesteps", "policy", "normalize", "policy_kwargs", "env_kwargs",
            "env_wrapper"}
PPO_KEYS = {"learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda",
            "clip_range", "clip_range_vf", "normalize_advantage", "ent_coef", "vf_coef",
            "max_grad_norm", "use_sde", "sde_sample_freq", "target_kl"}
HARNESS_KEYS = {"seed", "eval_scenarios", "eval_freq", "checkpoint_freq", "eval_seed",
                "tune",  # tune: the search space of `mpa-gym tune` (agents/training/tune.py)
                # run-time assurance of the trained policy (agents/controllers/supervisor.py)
                "supervisor",
                "anchor_at_rest"}  # mean action zero at zero features (agents/learned/anchor.py)
ENV_IDS = ("MPALeg-v0", "MPALegResidual-v0")
OBS_WRAPPER = "mpa_gym.agents.learned.wrappers.TrackingErrorObservation"
ACTION_WRAPPER = "mpa_gym.agents.learned.wrappers.ForceStiffnessAction"
WRAPPERS = (OBS_WRAPPER, ACTION_WRAPPER)
# the names configs and run folders written before 0.2.0 give the wrappers (the app was then a
# top-level ``agents`` package); a config that uses them loads as if it gave today's names
LEGACY_WRAPPERS = {"agents.wrappers.TrackingErrorObservation": OBS_WRAPPER,
                   "agents.wrappers.ForceStiffnessAction": ACTION_WRAPPER}
# the default training config: `mpa-gym train`, `tune` and `tune-baselines` without --config
DEFAULT_CONFIG = DEFAULT_TRAIN_CONFIG
SEED_MAX = 2**31 - 1  # largest training seed (every seed a training env and torch accept)
MAX_TIMESTEPS = 10**10  # the most env steps a run may ask for (~6 days at 20,000 steps/s)
EVAL_SEED = 1_000_000  # first seed of evaluation episodes: no training env draws seeds this high
ACTIVATIONS = {"nn.Tanh": "Tanh", "nn.ReLU": "ReLU", "nn.ELU": "ELU", "nn.LeakyReLU": "LeakyReLU"}


class ConfigError(ValueError):
    """A malformed training config: the message names the key, the value and what is allowed."""


NORMALIZE_KEYS = ("norm_obs", "norm_reward", "gamma", "clip_obs", "clip_reward")
# policy_kwargs of SB3's MlpPolicy that a config may set (each checked in TrainConfig)
POLICY_KWARGS = ("net_arch", "activation_fn", "log_std_init", "ortho_init", "full_std",
                 "squash_output", "share_features_extractor")
ENV_KWARGS = ("scenario", "stiffness", "task")


@dataclass
class TrainConfig:
    """One training run's settings; validates itself (``ConfigError`` names key, value, range).

    PPO's hyper-parameters (``ppo_kwargs``, rl-zoo's keys) are checked by type and range here,
    before any env or model is built: a bad one would otherwise train into NaN weights or fail
    deep inside torch."""

    env_id: str  # one of ENV_IDS
    n_timesteps: int  # env steps to train
    n_envs: int = 1  # parallel envs of the native vector env
    policy: str = "MlpPolicy"
    normalize: dict[str, Any] = field(default_factory=dict)  # VecNormalize kwargs; {} = none
    policy_kwargs: dict[str, Any] = field(default_factory=dict)  # SB3 MlpPolicy kwargs
    env_kwargs: dict[str, Any] = field(default_factory=dict)  # scenario / stiffness / task
    ppo_kwargs: dict[str, Any] = field(default_factory=dict)  # PPO_KEYS given in the file
    # kwargs of TrackingErrorObservation / ForceStiffnessAction; None: not used
    observation_wrapper: dict[str, Any] | None = None
    action_wrapper: dict[str, Any] | None = None
    seed: int = 0
    eval_scenarios: list[Any] = field(default_factory=list)
    eval_freq: int = 100_000  # env steps between evaluations
    checkpoint_freq: int = 500_000  # env steps between checkpoints
    eval_seed: int = EVAL_SEED  # seeds of evaluation episodes (no training env uses them)
    # a fallback that takes over from the trained policy when it fails (SupervisorSpec's keys);
    # None: the policy runs alone
    supervisor: Any = None
    # the policy's mean action is exactly zero while every feature is zero
    # (agents/learned/anchor.py)
    anchor_at_rest: bool = False
    raw: dict[str, Any] = field(default_factory=dict)  # the file's content, for the run folder
    source: str = "config"  # where the settings came from (prefixes error messages)

    def __post_init__(self) -> None:
        where = f"{self.source}: {self.env_id}"
        if self.env_id not in ENV_IDS:
            raise ConfigError(f"{self.source}: env_id={self.env_id!r}: allowed {list(ENV_IDS)}")
        self.n_envs = _int(self.n_envs, f"{where}.n_envs", 1, 4096)
        self.n_timesteps = _int(self.n_timesteps, f"{where}.n_timesteps", 1, MAX_TIMESTEPS)
        if self.policy != "MlpPolicy":
            raise ConfigError(f"{where}.policy={self.policy!r}: allowed ['MlpPolicy']")
        _check_normalize(self.normalize, f"{where}.normalize")
        _check_policy_kwargs(self.policy_kwargs, f"{where}.policy_kwargs")
        ek = self.env_kwargs
        if not isinstance(ek, dict) or set(ek) - set(ENV_KWARGS):
            raise ConfigError(f"{where}.env_kwargs={ek!r}: allowed keys are {list(ENV_KWARGS)}")
        _check_env_kwargs(ek, f"{where}.env_kwargs")
        _check_ppo(self.ppo_kwargs, self.n_envs, where)
        for name, kwargs in ((OBS_WRAPPER, self.observation_wrapper),
                             (ACTION_WRAPPER, self.action_wrapper)):
            if kwargs is not None:
                _check_wrapper(name, kwargs, self.env_id, f"{where}.env_wrapper",
                               task_config(ek.get("task")).dt_s)
        h = f"{self.source}: mpa_gym"
        self.seed = _int(self.seed, f"{h}.seed", 0, SEED_MAX)
        self.eval_freq = _int(self.eval_freq, f"{h}.eval_freq", 1, 1e10)
        self.checkpoint_freq = _int(self.checkpoint_freq, f"{h}.checkpoint_freq", 1, 1e10)
        self.eval_seed = _int(self.eval_seed, f"{h}.eval_seed", 0, SEED_MAX)
        if not isinstance(self.eval_scenarios, list):
            raise ConfigError(f"{h}.eval_scenarios={self.eval_scenarios!r} must be a list of "
                              "scenario names, paths or mappings")
        if self.supervisor is not None:
            try:
                self.supervisor = SupervisorSpec.from_config(self.supervisor)
            except ValueError as e:
                raise ConfigError(f"{h}.{e}") from None
        if not isinstance(self.anchor_at_rest, bool):
            raise ConfigError(f"{h}.anchor_at_rest={self.anchor_at_rest!r} must be true or false")
        if self.anchor_at_rest and not (self.observation_wrapper or {}).get("errors_only"):
            raise ConfigError(f"{h}.anchor_at_rest=true needs {OBS_WRAPPER} with errors_only: "
                              "true (the features are then all zero while tracking is exact)")

        for i, sc in enumerate(self.eval_scenarios):
            try:
                load_scenario(sc)
            except ValueError as e:
                raise ConfigError(f"{h}.eval_scenarios[{i}]: {e}") from None


def _literal(text: str, key: str) -> Any:
    """rl-zoo writes ``policy_kwargs`` / ``normalize`` as Python expressions; accept the safe
    subset: literals, dict(...) calls and ``nn.<Activation>`` names."""
    def conv(node: ast.AST) -> Any:
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and \
                node.func.id == "dict" and not node.args:
            return {kw.arg: conv(kw.value) for kw in node.keywords}
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            name = f"{node.value.id}.{node.attr}"
            if name in ACTIVATIONS:
                return name
            raise ConfigError(f"{key}: {name} is not allowed; activations {sorted(ACTIVATIONS)}")
        if isinstance(node, ast.Dict):
            return {conv(k): conv(v) for k, v in zip(node.keys, node.values, strict=True)}
        if isinstance(node, ast.List | ast.Tuple):
            return [conv(e) for e in node.elts]
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return -conv(node.operand)
        raise ConfigError(f"{key}={text!r}: only literals, dict(...) and nn.<Activation> are "
                          "allowed")
    try:
        return conv(ast.parse(text, mode="eval").body)
    except (SyntaxError, TypeError) as e:  # TypeError: -"text", an unhashable dict key
        raise ConfigError(f"{key}={text!r} is not a valid expression: "
                          f"{getattr(e, 'msg', e)}") from None


def _int(v: Any, name: str, lo: int, hi: float) -> int:
    """A whole number in [lo, hi] (a YAML float such as ``!!float 2e6`` counts)."""
    ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and \
        v == int(v) and lo <= v <= hi
    if not ok:
        raise ConfigError(f"{name}={v!r} must be a whole number in [{lo}, {hi:g}]")
    return int(v)


def _real(v: Any, name: str, lo: float, hi: float, lo_open: bool = False,
          hi_open: bool = False) -> float:
    """A finite number in the interval (bounds open where said)."""
    ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and \
        (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi)
    if not ok:
        interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        raise ConfigError(f"{name}={v!r} must be a finite number in {interval}")
    return float(v)


def _bool(v: Any, name: str) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(f"{name}={v!r} must be true or false")
    return v


def _schedule_or_real(v: Any, name: str, lo: float, hi: float) -> None:
    """A number in (lo, hi] or rl-zoo's linear schedule ``'lin_<number>'`` of one."""
    if isinstance(v, str):
        if not (v.startswith("lin_") and _is_float(v[4:])):
            raise ConfigError(f"{name}={v!r} must be a number or 'lin_<number>'")
        v0 = float(v[4:])
        if not (math.isfinite(v0) and lo < v0 <= hi):
            raise ConfigError(f"{name}={v!r}: the schedule's start {v0!r} must be a finite "
                              f"number in ({lo:g}, {hi:g}]")
        return
    _real(v, name, lo, hi, lo_open=True)


def _ppo_default(key: str) -> Any:
    """SB3's own default of a PPO hyper-parameter (read, not restated)."""
    import inspect

    from stable_baselines3 import PPO

    return inspect.signature(PPO).parameters[key].default


def _check_ppo(p: dict[str, Any], n_envs: int, where: str) -> None:
    """Types and ranges of PPO's hyper-parameters (SB3's defaults where a key is absent)."""
    if not isinstance(p, dict) or set(p) - PPO_KEYS:
        raise ConfigError(f"{where}: unknown PPO key(s) "
                          f"{sorted(set(p) - PPO_KEYS) if isinstance(p, dict) else p!r}; "
                          f"allowed keys are {sorted(PPO_KEYS)}")
    w = lambda k: f"{where}.{k}"  # noqa: E731
    if "learning_rate" in p:
        _schedule_or_real(p["learning_rate"], w("learning_rate"), 0.0, 1.0)
    n_steps = _int(p.get("n_steps", _ppo_default("n_steps")), w("n_steps"), 1, 1e7)
    if n_steps * n_envs < 2:
        raise ConfigError(f"{where}: n_steps * n_envs = {n_steps * n_envs} must be > 1")
    batch = _int(p.get("batch_size", _ppo_default("batch_size")), w("batch_size"), 2, 1e8)
    if batch > n_steps * n_envs:
        raise ConfigError(f"{where}.batch_size={batch} must be <= n_steps * n_envs = "
                          f"{n_steps * n_envs}")
    for key, lo, hi in (("n_epochs", 1, 1000), ("sde_sample_freq", -1, 1e7)):
        if key in p:
            _int(p[key], w(key), lo, hi)
    for key in ("gamma", "gae_lambda"):
        if key in p:
            _real(p[key], w(key), 0.0, 1.0)
    for key, hi in (("ent_coef", 1.0), ("vf_coef", 10.0)):
        if key in p:
            _real(p[key], w(key), 0.0, hi)
    if "max_grad_norm" in p:
        _real(p["max_grad_norm"], w("max_grad_norm"), 0.0, 1e6, lo_open=True)
    if "clip_range" in p:
        _schedule_or_real(p["clip_range"], w("clip_range"), 0.0, 10.0)
    if p.get("clip_range_vf") is not None:
        _schedule_or_real(p["clip_range_vf"], w("clip_range_vf"), 0.0, 1e6)
    if p.get("target_kl") is not None:
        _real(p["target_kl"], w("target_kl"), 0.0, 10.0, lo_open=True)
    for key in ("normalize_advantage", "use_sde"):
        if key in p:
            _bool(p[key], w(key))


def _check_env_kwargs(ek: dict[str, Any], where: str) -> None:
    """The env's scenario, stiffness target and task settings, checked by building its plan (as
    the env will) before any env, model or run folder exists."""

    try:
        make_plans(ek.get("scenario", "nominal"), ek.get("stiffness"), task_config(ek.get("task")),
                   DEFAULT_PARAMS)
    except ValueError as e:
        raise ConfigError(f"{where}: {e}") from None


def _check_normalize(norm: Any, where: str) -> None:
    if not isinstance(norm, dict) or set(norm) - set(NORMALIZE_KEYS):
        raise ConfigError(f"{where}={norm!r}: allowed keys are {list(NORMALIZE_KEYS)}")
    for key in ("norm_obs", "norm_reward"):
        if key in norm:
            _bool(norm[key], f"{where}.{key}")
    if "gamma" in norm:
        _real(norm["gamma"], f"{where}.gamma", 0.0, 1.0)
    for key in ("clip_obs", "clip_reward"):
        if key in norm:
            _real(norm[key], f"{where}.{key}", 0.0, 1e6, lo_open=True)


def _check_policy_kwargs(pk: Any, where: str) -> None:
    if not isinstance(pk, dict):
        raise ConfigError(f"{where}={pk!r} must be a dict")
    check_keys(where, pk, POLICY_KWARGS, ConfigError)
    if "net_arch" in pk:
        arch = pk["net_arch"]
        layers = ({k: arch.get(k) for k in arch} if isinstance(arch, dict) else {"": arch})
        if isinstance(arch, dict) and set(arch) != {"pi", "vf"}:
            raise ConfigError(f"{where}.net_arch={arch!r}: a dict needs exactly the keys "
                              "['pi', 'vf']")
        for k, sizes in layers.items():
            name = f"{where}.net_arch" + (f".{k}" if k else "")
            if not isinstance(sizes, list) or len(sizes) > 16:
                raise ConfigError(f"{name}={sizes!r} must be a list of up to 16 layer sizes "
                                  "(or dict(pi=[...], vf=[...]))")
            for i, n in enumerate(sizes):
                _int(n, f"{name}[{i}]", 1, 4096)
    if "log_std_init" in pk:
        _real(pk["log_std_init"], f"{where}.log_std_init", -20.0, 2.0)
    if "activation_fn" in pk and pk["activation_fn"] not in ACTIVATIONS:
        raise ConfigError(f"{where}.activation_fn={pk['activation_fn']!r}: allowed "
                          f"{sorted(ACTIVATIONS)}")
    for key in ("ortho_init", "full_std", "squash_output", "share_features_extractor"):
        if key in pk:
            _bool(pk[key], f"{where}.{key}")


def _check_wrapper(name: str, kwargs: Any, env_id: str, where: str, dt_s: float) -> None:
    """A wrapper's kwargs, checked by the wrapper's own validation, on an env whose control
    period is ``dt_s``."""
    import dataclasses


    if not isinstance(kwargs, dict):
        raise ConfigError(f"{where}: {name}: kwargs {kwargs!r} must be a mapping")
    check = FeatureSpec if name == OBS_WRAPPER else ActionSpec
    allowed = [f.name for f in dataclasses.fields(check)]
    check_keys(f"{where}: {name}", kwargs, allowed, ConfigError)
    try:
        spec = check(**kwargs)
        if name == ACTION_WRAPPER:  # the estimator's time constant against the env's period
            adapt_time_constant(spec.stiffness_adapt_s, dt_s=dt_s)
    except ValueError as e:
        raise ConfigError(f"{where}: {name}: {e}") from None
    if name == ACTION_WRAPPER and env_id != "MPALegResidual-v0":
        raise ConfigError(f"{where}: {name} needs MPALegResidual-v0, not {env_id}")


def parse_config(data: Any, source: str = "config") -> TrainConfig:
    """A loaded YAML document → TrainConfig: the file's structure (env id key, known keys, rl-zoo's
    Python-expression strings, the wrapper list); TrainConfig checks the values."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping with one env id key, got {data!r}")
    unknown_top = sorted(set(data) - set(ENV_IDS) - {"mpa_gym"}, key=str)
    if unknown_top:
        raise ConfigError(f"{source}: unknown top-level key(s) {unknown_top}; allowed: one of "
                          f"{list(ENV_IDS)} and 'mpa_gym'")
    ids = [k for k in data if k in ENV_IDS]
    if len(ids) != 1:
        raise ConfigError(f"{source}: needs exactly one env id key of {list(ENV_IDS)}, got {ids}")
    env_id = ids[0]
    if isinstance(data[env_id], dict) and data[env_id].get("env_wrapper") is not None:
        data = {**data, env_id: {**data[env_id], "env_wrapper": _current_names(
            data[env_id]["env_wrapper"])}}
    hp = data[env_id]
    if not isinstance(hp, dict):
        raise ConfigError(f"{source}: {env_id} must be a mapping of hyper-parameters")
    check_keys(f"{source}: {env_id}", hp, ZOO_KEYS | PPO_KEYS, ConfigError)
    for req in ("n_timesteps", "policy"):
        if req not in hp:
            raise ConfigError(f"{source}: {env_id}: missing required key {req!r}")
    where = f"{source}: {env_id}"
    norm = hp.get("normalize", False)
    if isinstance(norm, str):
        norm = _literal(norm, f"{where}.normalize")
    if norm is True:
        norm = {"norm_obs": True, "norm_reward": True}
    elif norm is False or norm is None:
        norm = {}
    elif isinstance(norm, dict):
        norm = {"norm_obs": True, "norm_reward": True, **norm}
    else:
        raise ConfigError(f"{where}.normalize={norm!r} must be a bool or a dict")
    pk = hp.get("policy_kwargs", {})
    if isinstance(pk, str):
        pk = _literal(pk, f"{where}.policy_kwargs")
    wrappers = _wrappers(hp.get("env_wrapper"), f"{where}.env_wrapper")
    h = data.get("mpa_gym") or {}
    if not isinstance(h, dict):
        raise ConfigError(f"{source}: mpa_gym={h!r} must be a mapping with the keys "
                          f"{sorted(HARNESS_KEYS)}")
    check_keys(f"{source}: mpa_gym", h, HARNESS_KEYS, ConfigError)
    # tune (the search space) is read from ``raw`` by mpa_gym.agents.training.tune, which
    # validates it
    harness = {k: v for k, v in h.items() if k not in ("eval_scenarios", "tune")}
    if h.get("eval_scenarios") is not None:
        harness["eval_scenarios"] = h["eval_scenarios"]
    return TrainConfig(
        env_id=env_id, n_timesteps=hp["n_timesteps"], n_envs=hp.get("n_envs", 1),
        policy=hp["policy"], normalize=norm, policy_kwargs=pk,
        env_kwargs=hp.get("env_kwargs") or {},
        ppo_kwargs={k: hp[k] for k in PPO_KEYS if k in hp},
        observation_wrapper=wrappers.get(OBS_WRAPPER), action_wrapper=wrappers.get(ACTION_WRAPPER),
        raw=copy.deepcopy(data), source=source, **harness)


def _current_names(spec: Any) -> Any:
    """rl-zoo's ``env_wrapper`` with the names of ``LEGACY_WRAPPERS`` replaced by today's."""
    def rename(item: Any) -> Any:
        if isinstance(item, str):
            return LEGACY_WRAPPERS.get(item, item)
        if isinstance(item, dict) and len(item) == 1:
            ((name, kwargs),) = item.items()
            return {LEGACY_WRAPPERS.get(name, name) if isinstance(name, str) else name: kwargs}
        return item

    return [rename(i) for i in spec] if isinstance(spec, list) else rename(spec)


def _wrappers(spec: Any, where: str) -> dict[str, Any]:
    """rl-zoo's ``env_wrapper``: a name, ``{name: kwargs}``, or a list of those → {name: kwargs}
    (TrainConfig checks the kwargs, so a typo fails before training starts)."""
    if spec is None:
        return {}
    out: dict[str, Any] = {}
    for item in spec if isinstance(spec, list) else [spec]:
        if isinstance(item, dict) and len(item) == 1:
            name, kwargs = next(iter(item.items()))
            kwargs = {} if kwargs is None else kwargs
        else:
            name, kwargs = item, {}
        if not isinstance(name, str) or name not in WRAPPERS:
            raise ConfigError(f"{where}={item!r}: allowed wrappers {list(WRAPPERS)}, each a name "
                              "or {name: kwargs}")
        if name in out:
            raise ConfigError(f"{where}: {name} is given twice")
        out[name] = dict(kwargs) if isinstance(kwargs, dict) else kwargs
    return out


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def load_config(path: str | Path) -> TrainConfig:
    """The training config in the YAML file ``path``."""
    return parse_config(read_yaml(path, "config file", ConfigError), str(path))


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
