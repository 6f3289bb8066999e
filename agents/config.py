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
        - agents.wrappers.TrackingErrorObservation:
            {errors_only: true, harmonics: 1, remodulate: true}
        - agents.wrappers.ForceStiffnessAction:
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

import mpa_gym  # noqa: F401  (registers the env ids)

ZOO_KEYS = {"n_envs", "n_timesteps", "policy", "normalize", "policy_kwargs", "env_kwargs",
            "env_wrapper"}
PPO_KEYS = {"learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda",
            "clip_range", "clip_range_vf", "normalize_advantage", "ent_coef", "vf_coef",
            "max_grad_norm", "use_sde", "sde_sample_freq", "target_kl"}
HARNESS_KEYS = {"seed", "eval_scenarios", "eval_freq", "checkpoint_freq", "eval_seed"}
ENV_IDS = ("MPALeg-v0", "MPALegResidual-v0")
OBS_WRAPPER = "agents.wrappers.TrackingErrorObservation"
ACTION_WRAPPER = "agents.wrappers.ForceStiffnessAction"
WRAPPERS = (OBS_WRAPPER, ACTION_WRAPPER)
ACTIVATIONS = {"nn.Tanh": "Tanh", "nn.ReLU": "ReLU", "nn.ELU": "ELU", "nn.LeakyReLU": "LeakyReLU"}


class ConfigError(ValueError):
    """A malformed training config: the message names the key, the value and what is allowed."""


@dataclass
class TrainConfig:
    env_id: str
    n_envs: int
    n_timesteps: int
    policy: str
    normalize: dict[str, Any]  # VecNormalize kwargs; {} = no normalisation
    policy_kwargs: dict[str, Any]
    env_kwargs: dict[str, Any]
    ppo_kwargs: dict[str, Any]
    # kwargs of TrackingErrorObservation / ForceStiffnessAction; None: not used
    observation_wrapper: dict[str, Any] | None = None
    action_wrapper: dict[str, Any] | None = None
    seed: int = 0
    eval_scenarios: list[Any] = field(default_factory=list)
    eval_freq: int = 100_000  # env steps between evaluations
    checkpoint_freq: int = 500_000  # env steps between checkpoints
    eval_seed: int = 1_000_000  # seeds of evaluation episodes (no training env uses them)
    raw: dict[str, Any] = field(default_factory=dict)  # the file's content, for the run folder


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
    except SyntaxError as e:
        raise ConfigError(f"{key}={text!r} is not a valid expression: {e.msg}") from None


def _int(d: dict[str, Any], key: str, lo: int, hi: float, where: str) -> int:
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or v != int(v) or not lo <= v <= hi:
        raise ConfigError(f"{where}.{key}={v!r} must be a whole number in [{lo}, {hi:g}]")
    return int(v)


def parse_config(data: Any, source: str = "config") -> TrainConfig:
    """Validate a loaded YAML document into a TrainConfig."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping with one env id key, got {data!r}")
    unknown_top = sorted(set(data) - set(ENV_IDS) - {"mpa_gym"})
    if unknown_top:
        raise ConfigError(f"{source}: unknown top-level key(s) {unknown_top}; allowed: one of "
                          f"{list(ENV_IDS)} and 'mpa_gym'")
    ids = [k for k in data if k in ENV_IDS]
    if len(ids) != 1:
        raise ConfigError(f"{source}: needs exactly one env id key of {list(ENV_IDS)}, got {ids}")
    env_id = ids[0]
    hp = data[env_id]
    if not isinstance(hp, dict):
        raise ConfigError(f"{source}: {env_id} must be a mapping of hyper-parameters")
    unknown = sorted(set(hp) - ZOO_KEYS - PPO_KEYS)
    if unknown:
        raise ConfigError(f"{source}: {env_id}: unknown key(s) {unknown}; allowed keys are "
                          f"{sorted(ZOO_KEYS | PPO_KEYS)}")
    for req in ("n_timesteps", "policy"):
        if req not in hp:
            raise ConfigError(f"{source}: {env_id}: missing required key {req!r}")
    where = f"{source}: {env_id}"
    hp.setdefault("n_envs", 1)
    n_envs = _int(hp, "n_envs", 1, 4096, where)
    n_timesteps = _int(hp, "n_timesteps", 1, 1e10, where)
    if hp["policy"] != "MlpPolicy":
        raise ConfigError(f"{where}.policy={hp['policy']!r}: allowed ['MlpPolicy']")
    norm = hp.get("normalize", False)
    if isinstance(norm, str):
        norm = _literal(norm, f"{where}.normalize")
    if norm is True:
        norm = {}
        normalize: dict[str, Any] = {"norm_obs": True, "norm_reward": True}
    elif norm is False or norm is None:
        normalize = {}
    elif isinstance(norm, dict):
        bad = sorted(set(norm) - {"norm_obs", "norm_reward", "gamma", "clip_obs", "clip_reward"})
        if bad:
            raise ConfigError(f"{where}.normalize: unknown key(s) {bad}")
        normalize = {"norm_obs": True, "norm_reward": True, **norm}
    else:
        raise ConfigError(f"{where}.normalize={norm!r} must be a bool or a dict")
    pk = hp.get("policy_kwargs", {})
    if isinstance(pk, str):
        pk = _literal(pk, f"{where}.policy_kwargs")
    if not isinstance(pk, dict):
        raise ConfigError(f"{where}.policy_kwargs={pk!r} must be a dict")
    env_kwargs = hp.get("env_kwargs") or {}
    if not isinstance(env_kwargs, dict) or set(env_kwargs) - {"scenario", "stiffness", "task"}:
        raise ConfigError(f"{where}.env_kwargs={env_kwargs!r}: allowed keys are ['scenario', "
                          "'stiffness', 'task']")
    wrappers = _wrappers(hp.get("env_wrapper"), env_id, f"{where}.env_wrapper")
    ppo = {k: hp[k] for k in PPO_KEYS if k in hp}
    lr = ppo.get("learning_rate")
    if isinstance(lr, str) and not (lr.startswith("lin_") and _is_float(lr[4:])):
        raise ConfigError(f"{where}.learning_rate={lr!r} must be a number or 'lin_<number>'")
    h = data.get("mpa_gym") or {}
    if not isinstance(h, dict) or set(h) - HARNESS_KEYS:
        raise ConfigError(f"{source}: mpa_gym: unknown key(s) "
                          f"{sorted(set(h) - HARNESS_KEYS) if isinstance(h, dict) else h!r}; "
                          f"allowed keys are {sorted(HARNESS_KEYS)}")
    h = {"seed": 0, "eval_freq": 100_000, "checkpoint_freq": 500_000, "eval_seed": 1_000_000,
         **h}
    cfg = TrainConfig(
        env_id=env_id, n_envs=n_envs, n_timesteps=n_timesteps, policy="MlpPolicy",
        normalize=normalize, policy_kwargs=pk, env_kwargs=env_kwargs,
        ppo_kwargs=ppo, observation_wrapper=wrappers.get(OBS_WRAPPER),
        action_wrapper=wrappers.get(ACTION_WRAPPER),
        seed=_int(h, "seed", 0, 2**31 - 1, f"{source}: mpa_gym"),
        eval_scenarios=list(h.get("eval_scenarios") or []),
        eval_freq=_int(h, "eval_freq", 1, 1e10, f"{source}: mpa_gym"),
        checkpoint_freq=_int(h, "checkpoint_freq", 1, 1e10, f"{source}: mpa_gym"),
        eval_seed=_int(h, "eval_seed", 0, 2**31 - 1, f"{source}: mpa_gym"),
        raw=copy.deepcopy(data))
    _check_ppo(cfg, where)
    return cfg


def _wrappers(spec: Any, env_id: str, where: str) -> dict[str, dict[str, Any]]:
    """rl-zoo's ``env_wrapper``: a name, ``{name: kwargs}``, or a list of those → {name: kwargs}.

    The kwargs are checked here, so a typo fails before training starts."""
    import dataclasses

    from agents.wrappers import ACTION_KWARGS, FeatureSpec, check_action_kwargs

    if spec is None:
        return {}
    out: dict[str, dict[str, Any]] = {}
    for item in spec if isinstance(spec, list) else [spec]:
        if isinstance(item, dict) and len(item) == 1:
            name, kwargs = next(iter(item.items()))
            kwargs = {} if kwargs is None else kwargs
        else:
            name, kwargs = item, {}
        if name not in WRAPPERS:
            raise ConfigError(f"{where}={item!r}: allowed wrappers {list(WRAPPERS)}, each a name "
                              "or {name: kwargs}")
        if name in out:
            raise ConfigError(f"{where}: {name} is given twice")
        if not isinstance(kwargs, dict):
            raise ConfigError(f"{where}: {name}: kwargs {kwargs!r} must be a mapping")
        check, allowed = ((FeatureSpec, [f.name for f in dataclasses.fields(FeatureSpec)])
                          if name == OBS_WRAPPER else
                          (check_action_kwargs, list(ACTION_KWARGS)))
        unknown = sorted(set(kwargs) - set(allowed))
        if unknown:
            raise ConfigError(f"{where}: {name}: unknown key(s) {unknown}; allowed keys are "
                              f"{list(allowed)}")
        try:
            check(**kwargs)
        except ValueError as e:
            raise ConfigError(f"{where}: {name}: {e}") from None
        if name == ACTION_WRAPPER and env_id != "MPALegResidual-v0":
            raise ConfigError(f"{where}: {name} needs MPALegResidual-v0, not {env_id}")
        out[name] = dict(kwargs)
    return out


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _check_ppo(cfg: TrainConfig, where: str) -> None:
    p = cfg.ppo_kwargs
    n_steps = p.get("n_steps", 2048)
    batch = p.get("batch_size", 64)
    if n_steps * cfg.n_envs < 2:
        raise ConfigError(f"{where}: n_steps * n_envs = {n_steps * cfg.n_envs} must be > 1")
    if batch > n_steps * cfg.n_envs:
        raise ConfigError(f"{where}.batch_size={batch} must be <= n_steps * n_envs = "
                          f"{n_steps * cfg.n_envs}")


def load_config(path: str | Path) -> TrainConfig:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {e}") from None
    return parse_config(data, str(path))
