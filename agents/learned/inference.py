"""Deployment-grade inference of a trained run: the whole action path compiled, for the rig's loop.

``LearnedPolicy.predict`` goes through SB3 and torch: tensors, a thread pool, Python glue, a few
hundred microseconds and a garbage-producing allocation per step. ``DeployedPolicy`` computes the
same deterministic action from the exported weights in one compiled (numba) call on buffers
allocated once: the controller front-end's features
(``mpa_gym.agents.learned.frontend.observe_row``, the kernel the training wrappers and
``LearnedPolicy`` call), the observation normaliser (VecNormalize's running mean and variance, its
clip), the policy MLP (SB3's ``mlp_extractor.policy_net`` then ``action_net``: the mean action,
``deterministic=True``), the clip to the action space, and the front-end's action map with its
harmonic force correction and stiffness estimator
(``mpa_gym.agents.learned.frontend.act_row``). Single threaded, no framework, no allocation per
step: what a real-time loop can afford.

Only the normaliser and the network are its own; they equal ``LearnedPolicy.predict``'s (SB3's
deterministic action) to 1e-6 (``tests/test_inference.py``): SB3 computes them in float32,
this in float64.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from mpa_gym.agents.learned.episodic import Episodic, ObservationCheck
from mpa_gym.agents.learned.frontend import (
    ActionSpec,
    FeatureSpec,
    Frontend,
    act_row,
    new_state,
    observe_row,
)
from mpa_gym.model.jit import JIT
from mpa_gym.model.params import DEFAULT_PARAMS, Params

# activation codes of the hidden layers (SB3's activation_fn)
ACTIVATIONS = {"Tanh": 0, "ReLU": 1, "ELU": 2, "LeakyReLU": 3}


@numba.njit(**JIT)
def _activate(x, code):
    if code == 0:
        return math.tanh(x)
    if code == 1:
        return x if x > 0.0 else 0.0
    if code == 2:
        return x if x > 0.0 else math.expm1(x)
    return x if x > 0.0 else 0.01 * x


@numba.njit(**JIT)
def _mlp(x, n_in, weights, shapes, offsets, act, h_a, h_b, out):
    """Dense layers y = W x + b (W row-major at ``offsets``, shape (out, in)); every layer but the
    last followed by the activation ``act``; the last writes ``out``."""
    n_layers = shapes.shape[0]
    src, dst = x, h_a
    for layer in range(n_layers):
        n_out, n_in_l = shapes[layer, 0], shapes[layer, 1]
        o = offsets[layer]
        b = o + n_out * n_in_l
        last = layer == n_layers - 1
        tgt = out if last else dst
        for r in range(n_out):
            acc = weights[b + r]
            row = o + r * n_in_l
            for c in range(n_in_l):
                acc += weights[row + c] * src[c]
            tgt[r] = acc if last else _activate(acc, act)
        if not last:
            src, dst = dst, (h_b if dst is h_a else h_a)


@numba.njit(**JIT)
def _forward(raw, state, fresh, cfg, consts, mean, inv_std, clip_obs, weights, shapes, offsets,
             act, a_low, a_high, feat, x, h_a, h_b, net, out):
    """One action (module docstring) into ``out``; the front-end record ``state[0]`` is
    updated in place."""
    st, c = state[0], cfg[0]
    n = observe_row(raw, st, fresh, c, feat)
    for i in range(n):  # VecNormalize: clip((obs − μ) / √(σ² + ε), ±clip)
        x[i] = min(max((feat[i] - mean[i]) * inv_std[i], -clip_obs), clip_obs)
    _mlp(x, n, weights, shapes, offsets, act, h_a, h_b, net)
    for k in range(net.shape[0]):  # SB3 clips a Box action to the space
        net[k] = min(max(net[k], a_low[k]), a_high[k])
    act_row(net, raw, st, c, consts, out)


class DeployedPolicy(Episodic):
    """A trained run's deterministic action through the compiled path (module docstring).

    Build it with :meth:`from_learned`
    (``mpa_gym.agents.learned.policies.load_policy(..., deployed=True)`` does).
    ``act(obs, episode_start)`` returns the action in a buffer that the next call overwrites;
    ``predict`` is the baselines' interface for one observation, called as
    ``LearnedPolicy.predict`` is (``Episodic``: the state kept when it is not passed back,
    ``reset()`` or ``episode_start`` to start an episode, the observation checked against the
    run's env when ``check`` is set). The state lives inside the policy, so one instance
    serves one episode at a time and takes no batch.
    """

    def __init__(self, layers: list[tuple[np.ndarray, np.ndarray]], activation: str,
                 obs_dim: int, features: FeatureSpec | None = None,
                 normalizer: tuple[np.ndarray, np.ndarray, float, float] | None = None,
                 dt: float = 0.01, action: ActionSpec | None = None,
                 residual_scale_bar: float | None = None,
                 action_low: np.ndarray | None = None, action_high: np.ndarray | None = None,
                 params: Params = DEFAULT_PARAMS, check: ObservationCheck | None = None
                 ) -> None:
        self.check = check
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation={activation!r} must be one of {sorted(ACTIVATIONS)}")
        self.frontend = Frontend(features, action, dt, residual_scale_bar, params)
        self.features, self.dt = features, float(dt)
        n_feat = self.frontend.width(obs_dim)
        if layers[0][0].shape[1] != n_feat:
            raise ValueError(f"the network takes {layers[0][0].shape[1]} inputs but the "
                             f"observation and features give {n_feat}")
        self.obs_dim = obs_dim
        self._shapes = np.array([w.shape for w, _ in layers], dtype=np.int64)
        sizes = [w.size + b.size for w, b in layers]
        self._offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self._weights = np.concatenate([np.concatenate([np.asarray(w, float).ravel(),
                                                        np.asarray(b, float).ravel()])
                                        for w, b in layers])
        self._act = ACTIVATIONS[activation]
        n_act = layers[-1][0].shape[0]
        width = max(int(w.shape[0]) for w, _ in layers)
        if normalizer is None:
            self._mean, self._inv_std, self._clip = np.zeros(n_feat), np.ones(n_feat), math.inf
        else:
            mean, var, eps, clip = normalizer
            self._mean = np.asarray(mean, float).copy()
            self._inv_std = 1.0 / np.sqrt(np.asarray(var, float) + eps)
            self._clip = float(clip)
        self._low = np.full(n_act, -np.inf) if action_low is None else np.asarray(action_low,
                                                                                  float)
        self._high = np.full(n_act, np.inf) if action_high is None else np.asarray(action_high,
                                                                                   float)
        # buffers, allocated once; the observation in the env's float32, as the other paths
        self._raw = np.zeros(obs_dim, dtype=np.float32)
        self._state = new_state(1)
        self._feat = np.zeros(n_feat, dtype=np.float32)
        self._x = np.zeros(n_feat)
        self._h_a, self._h_b = np.zeros(width), np.zeros(width)
        self._net = np.zeros(n_act)
        self._out = np.zeros(n_act)
        self._fresh = True
        self.act(np.zeros(obs_dim), True)  # compile (or load) now, not inside the loop
        self._fresh = True

    @classmethod
    def from_learned(cls, policy: Any, obs_dim: int, params: Params = DEFAULT_PARAMS
                     ) -> DeployedPolicy:
        """Export a ``LearnedPolicy`` (SB3 PPO model, VecNormalize, wrapper settings) of an env
        whose observation has ``obs_dim`` columns (8: ``MPALeg-v0``, 9: the residual env)."""
        import torch
        import torch.nn as nn
        from stable_baselines3.common.torch_layers import FlattenExtractor

        pol = policy.model.policy
        if not isinstance(pol.features_extractor, FlattenExtractor):
            raise ValueError(f"features extractor {type(pol.features_extractor).__name__}: only "
                             "SB3's FlattenExtractor (MlpPolicy) can be deployed")
        if getattr(pol, "squash_output", False):
            raise ValueError("squash_output=True (gSDE squashing) cannot be deployed; train "
                             "without it")
        layers, acts = [], set()
        for mod in pol.mlp_extractor.policy_net:
            if isinstance(mod, nn.Linear):
                layers.append((mod.weight.detach().double().numpy(),
                               mod.bias.detach().double().numpy()))
            else:
                acts.add(type(mod).__name__)
        an = pol.action_net
        bias = an.bias.detach().double().numpy()
        if hasattr(pol, "rest_offset"):  # RestAnchoredPolicy: μ = f(o) − f(o_rest), a constant
            with torch.no_grad():
                bias = bias - pol.rest_offset().double().numpy().reshape(-1)
        layers.append((an.weight.detach().double().numpy(), bias))
        if len(acts) > 1:
            raise ValueError(f"mixed activations {sorted(acts)} cannot be deployed")
        activation = acts.pop() if acts else "Tanh"
        norm = None
        if policy.normalizer is not None and policy.normalizer.norm_obs:
            nz = policy.normalizer
            norm = (nz.obs_rms.mean, nz.obs_rms.var, float(nz.epsilon), float(nz.clip_obs))
        space = policy.model.action_space
        return cls(layers, activation, obs_dim, policy.features, norm, policy.dt,
                   policy.action, policy.residual_scale_bar, space.low, space.high,
                   params, policy.check)

    def reset(self) -> None:
        """The next observation starts an episode (integrals, previous action, harmonic force
        correction and stiffness estimator restart), for ``act`` and ``predict`` alike."""
        super().reset()
        self._fresh = True

    def act(self, observation: np.ndarray, episode_start: bool = False) -> np.ndarray:
        """The action for one observation (a buffer the next call overwrites)."""
        self._raw[:] = observation
        if self._fresh or episode_start:  # the rig's delays (delay_observation), as told
            self._state["delay_s"] = self.frontend.known_delay_s
        _forward(self._raw, self._state, self._fresh or episode_start,
                 self.frontend.settings, self.frontend.consts, self._mean, self._inv_std,
                 self._clip, self._weights, self._shapes, self._offsets, self._act, self._low,
                 self._high, self._feat, self._x, self._h_a, self._h_b, self._net, self._out)
        self._fresh = False
        return self._out

    def _predict(self, observation: np.ndarray, state: Any, episode_start: np.ndarray | None,
                 deterministic: bool) -> tuple[np.ndarray, Any]:
        """One observation: (action, state). The state lives inside (the returned one is a
        token to pass back); ``episode_start`` or a ``None`` state restarts the integrals."""
        obs = np.asarray(observation)
        if obs.shape != (self.obs_dim,):
            raise ValueError(f"observation has shape {obs.shape}; a deployed policy takes one "
                             f"observation of shape ({self.obs_dim},)")
        start = state is None or (episode_start is not None and bool(np.any(episode_start)))
        return self.act(obs, start), self._state
