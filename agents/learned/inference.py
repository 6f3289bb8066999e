"""Deployment-grade inference of a trained run: the whole action path compiled, for the rig's loop.

``LearnedPolicy.predict`` goes through SB3 and torch: tensors, a thread pool, Python glue, a few
hundred microseconds and a garbage-producing allocation per step. ``DeployedPolicy`` computes the
same deterministic action from the exported weights in one compiled (numba) call on buffers
allocated once: the tracking-error features and their integrals (``TrackingErrorObservation``),
the observation normaliser (VecNormalize's running mean and variance, its clip), the policy MLP
(SB3's ``mlp_extractor.policy_net`` then ``action_net``: the mean action, ``deterministic=True``),
the clip to the action space, and the force–stiffness map (``ForceStiffnessAction``) with its
stiffness estimator. Single
threaded, no framework, no allocation per step: what a real-time loop can afford.

It is equal to ``LearnedPolicy.predict`` (SB3's deterministic action) to 1e-6
(``tests/test_inference.py``); SB3 computes in float32, this in float64.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from mpa_gym.agents.learned.wrappers import (
    ADAPT_STARTED,
    ADAPT_STATE,
    FeatureSpec,
    _adapt_commit,
    _adapt_row,
    _constants,
    adapt_time_constant,
)

from mpa_gym.model import fast
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params
from mpa_gym.task.contract import OBS_COS as OCOS
from mpa_gym.task.contract import OBS_KREF as OK
from mpa_gym.task.contract import OBS_KREF_SCALE
from mpa_gym.task.contract import OBS_PE as OPE
from mpa_gym.task.contract import OBS_PF as OPF
from mpa_gym.task.contract import OBS_SIN as OSIN
from mpa_gym.task.contract import OBS_V as OV
from mpa_gym.task.contract import OBS_VREF as OVR
from mpa_gym.task.contract import OBS_X as OX
from mpa_gym.task.contract import OBS_XREF as OXR

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}

# activation codes of the hidden layers (SB3's activation_fn)
ACTIVATIONS = {"Tanh": 0, "ReLU": 1, "ELU": 2, "LeakyReLU": 3}


@numba.njit(**JIT)
def _features(raw, integ, prev, fresh, on, errors_only, mask_p, prev_act, fine, remod,
              harmonics, limit, dt, basis, feat):
    """Update the integrals with ``raw`` (unless ``fresh``: an episode's first observation, whose
    integrals are zero) and write ``FeatureSpec.features`` (``on``; else the observation itself)
    into ``feat``; returns its length."""
    if not on:
        for i in range(raw.shape[0]):
            feat[i] = raw[i]
        return raw.shape[0]
    # harmonic basis [1, sin φ, cos φ, sin 2φ, cos 2φ, …] by the complex recurrence z ← z z1,
    # as harmonic_basis computes it
    s1, c1 = raw[OSIN], raw[OCOS]
    basis[0] = 1.0
    zr, zi = 1.0, 0.0
    for h in range(harmonics):
        zr, zi = zr * c1 - zi * s1, zr * s1 + zi * c1
        basis[1 + 2 * h] = zi
        basis[2 + 2 * h] = zr
    m = 1 + 2 * harmonics
    e = raw[OXR] - raw[OX]
    if fresh:
        for i in range(m):
            integ[i] = 0.0
        prev[0] = 0.0
        prev[1] = 0.0
    else:
        for i in range(m):
            integ[i] = min(max(integ[i] + e * basis[i] * dt, -limit), limit)
    n = 0
    if not errors_only:
        for i in range(raw.shape[0]):
            feat[n] = 0.0 if (mask_p and (i == OPE or i == OPF)) else raw[i]
            n += 1
    feat[n] = e
    feat[n + 1] = raw[OVR] - raw[OV]
    n += 2
    for i in range(m):
        feat[n] = integ[i]
        n += 1
    if prev_act:
        feat[n] = prev[0]
        feat[n + 1] = prev[1]
        n += 2
    if not math.isnan(fine):
        feat[n] = min(max(e, -fine), fine)
        n += 1
    if remod:
        for h in range(harmonics):  # R_h = I_s sin + I_c cos
            feat[n + h] = integ[1 + 2 * h] * basis[1 + 2 * h] + integ[2 + 2 * h] * basis[2 + 2 * h]
        for h in range(harmonics):  # Q_h = I_s cos − I_c sin
            feat[n + harmonics + h] = (integ[1 + 2 * h] * basis[2 + 2 * h]
                                       - integ[2 + 2 * h] * basis[1 + 2 * h])
        n += 2 * harmonics
    return n


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
def _forward(raw, integ, prev, adapt, fresh, spec_i, spec_f, mean, inv_std, clip_obs, weights,
             shapes, offsets, act, a_low, a_high, fs, consts, basis, feat, h_a, h_b, out):
    """One action (module docstring) into ``out``; the state (integrals, previous action,
    stiffness estimator) is updated in place."""
    n = _features(raw, integ, prev, fresh, spec_i[5] > 0, spec_i[0] > 0, spec_i[1] > 0,
                  spec_i[2] > 0, spec_f[0], spec_i[3] > 0, spec_i[4], spec_f[1], spec_f[2],
                  basis, feat)
    for i in range(n):  # VecNormalize: clip((obs − μ) / √(σ² + ε), ±clip)
        feat[i] = min(max((feat[i] - mean[i]) * inv_std[i], -clip_obs), clip_obs)
    _mlp(feat, n, weights, shapes, offsets, act, h_a, h_b, out)
    for k in range(out.shape[0]):  # SB3 clips a Box action to the space
        out[k] = min(max(out[k], a_low[k]), a_high[k])
    if fs[0] > 0.0:  # ForceStiffnessAction: (a_F, a_k) → residual (a_e, a_f) on the nominal model
        x = raw[OXR]
        k_ref = raw[OK] * OBS_KREF_SCALE
        if fs[4] > 0.0:  # its stiffness estimator replaces a_k
            if fresh:
                adapt[ADAPT_STARTED] = 0.0
            out[1] = _adapt_row(adapt, x, x - raw[OX], k_ref, spec_f[2], fs[4], fs[2])
            _adapt_commit(adapt, out[0], fs[1])
        F0, k0 = fast.force_and_stiffness(x, 0.0, 0.0, 0.0, consts)
        Fe, ke = fast.force_and_stiffness(x, 0.0, BAR, 0.0, consts)
        Ff, kf = fast.force_and_stiffness(x, 0.0, 0.0, BAR, consts)
        j11, j12, j21, j22 = (Fe - F0) / BAR, (Ff - F0) / BAR, (ke - k0) / BAR, (kf - k0) / BAR
        dF = min(max(out[0], -1.0), 1.0) * fs[1]
        dk = min(max(out[1], -1.0), 1.0) * fs[2] * k_ref
        det = j11 * j22 - j12 * j21
        out[0] = min(max((dF * j22 - j12 * dk) / det / fs[3], -1.0), 1.0)
        out[1] = min(max((j11 * dk - j21 * dF) / det / fs[3], -1.0), 1.0)
    prev[0] = min(max(out[0], -1.0), 1.0)  # what the env applies: the next features' a_prev
    prev[1] = min(max(out[1], -1.0), 1.0)


class DeployedPolicy:
    """A trained run's deterministic action through the compiled path (module docstring).

    Build it with :meth:`from_learned` (``mpa_gym.agents.learned.policies.load_run(..., deployed=True)`` does).
    ``act(obs, episode_start)`` returns the action in a buffer that the next call overwrites;
    ``predict`` is the baselines' interface for one observation (the state lives inside the
    policy, so one instance serves one episode at a time).
    """

    def __init__(self, layers: list[tuple[np.ndarray, np.ndarray]], activation: str,
                 obs_dim: int, features: FeatureSpec | None = None,
                 normalizer: tuple[np.ndarray, np.ndarray, float, float] | None = None,
                 dt: float = 0.01, force_stiffness: tuple[float, float, float] | None = None,
                 action_low: np.ndarray | None = None, action_high: np.ndarray | None = None,
                 params: Params = DEFAULT_PARAMS, stiffness_adapt_s: float | None = None
                 ) -> None:
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation={activation!r} must be one of {sorted(ACTIVATIONS)}")
        spec = features
        self.features, self.dt = spec, float(dt)
        n_feat = obs_dim if spec is None else spec.space(_box(obs_dim)).shape[0]
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
        if spec is None:  # the env's observation as it is
            # errors_only, mask_pressures, previous_action, remodulate, harmonics, features on
            self._spec_i = np.array([0, 0, 0, 0, 0, 0], dtype=np.int64)
            self._spec_f = np.array([math.nan, 1.0, self.dt])
        else:
            self._spec_i = np.array([spec.errors_only, spec.mask_pressures, spec.previous_action,
                                     spec.remodulate, spec.harmonics, 1], dtype=np.int64)
            self._spec_f = np.array([math.nan if spec.fine_error_m is None else spec.fine_error_m,
                                     spec.limit_m_s, self.dt])
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
        tau = adapt_time_constant(stiffness_adapt_s, force_stiffness is not None)
        self._fs = np.zeros(5) if force_stiffness is None else np.array(  # fs[4] 0: no estimator
            [1.0, force_stiffness[0], force_stiffness[1], force_stiffness[2] * BAR,
             0.0 if tau is None else tau])
        self._consts = _constants(params)
        # buffers, allocated once
        m = 1 if spec is None else spec.n_integrals
        self._raw = np.zeros(obs_dim)
        self._integ = np.zeros(m)
        self._prev = np.zeros(2)
        self._adapt = np.zeros(ADAPT_STATE)
        self._basis = np.zeros(m)
        self._feat = np.zeros(n_feat + obs_dim + 8)
        self._h_a, self._h_b = np.zeros(width), np.zeros(width)
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
                   policy.force_stiffness, space.low, space.high, params,
                   policy.stiffness_adapt_s)

    def reset(self) -> None:
        """The next observation starts an episode (integrals, previous action and stiffness
        estimator restart)."""
        self._fresh = True

    def act(self, observation: np.ndarray, episode_start: bool = False) -> np.ndarray:
        """The action for one observation (a buffer the next call overwrites)."""
        self._raw[:] = observation
        _forward(self._raw, self._integ, self._prev, self._adapt, self._fresh or episode_start,
                 self._spec_i, self._spec_f, self._mean, self._inv_std, self._clip,
                 self._weights, self._shapes, self._offsets, self._act, self._low, self._high,
                 self._fs, self._consts, self._basis, self._feat, self._h_a, self._h_b,
                 self._out)
        self._fresh = False
        return self._out

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        """The baselines' interface, one observation: (action, state). The state lives inside
        (the returned one is a token to pass back); ``episode_start`` or a ``None`` state
        restarts the integrals."""
        obs = np.asarray(observation)
        if obs.shape != (self.obs_dim,):
            raise ValueError(f"observation has shape {obs.shape}; a deployed policy takes one "
                             f"observation of shape ({self.obs_dim},)")
        start = state is None or (episode_start is not None and bool(np.any(episode_start)))
        return self.act(obs, start), self._integ


def _box(dim: int) -> Any:
    from gymnasium import spaces

    return spaces.Box(-np.inf, np.inf, shape=(dim,), dtype=np.float32)


def benchmark(run_dir: str, n_actions: int = 20_000, n_reference: int = 2_000,
              emulator: bool = True) -> dict[str, Any]:
    """Time per action of a run: the deployed path and SB3's ``predict`` (the reference), in the
    same process and run, on the observations of a simulated episode, with (``emulator``) a
    device emulator serving telemetry from another process meanwhile.

    Returns median and p99 [ms] of each and their ratios (SB3 / deployed)."""
    import time

    import gymnasium as gym
    from mpa_gym.agents.learned.policies import load_run

    from mpa_gym.hardware import protocol as proto
    from mpa_gym.hardware.emulator import EmulatorProcess
    from mpa_gym.hardware.transport import open_transport

    sb3, cfg = load_run(run_dir)
    deployed, _ = load_run(run_dir, deployed=True)
    task = {k: v for k, v in (cfg.env_kwargs.get("task") or {}).items() if k != "episode_s"}
    env = gym.make(cfg.env_id, scenario="load_1kg", task={**task, "episode_s": 3.0})
    obs, _ = env.reset(seed=0)
    observations = [obs]
    state, start = None, np.array([True])
    for _ in range(299):  # the observations a policy sees along an episode
        a, state = sb3.predict(obs, state, start)
        start = np.array([False])
        obs, *_ = env.step(a)
        observations.append(obs)
    emu = link = None
    try:
        if emulator:
            emu = EmulatorProcess()
            link = open_transport(emu.url)
            link.send(proto.encode(proto.Vent(1, 0)))  # the emulator now streams to us
        times = {}
        for name, n, call in (
                ("deployed", n_actions, lambda o: deployed.act(o)),
                ("sb3", n_reference, lambda o: sb3.predict(o, state, start))):
            for o in observations[:50]:  # warm caches
                call(o)
            t = np.empty(n)
            for i in range(n):
                o = observations[i % len(observations)]
                t0 = time.perf_counter_ns()
                call(o)
                t[i] = time.perf_counter_ns() - t0
            times[name] = t * 1e-6  # [ms]
    finally:
        if link is not None:
            link.close()
        if emu is not None:
            emu.close()
    out: dict[str, Any] = {"run_dir": str(run_dir), "emulator_process": emulator}
    for name, t in times.items():
        out[name] = {"actions": int(t.size), "median_ms": float(np.median(t)),
                     "p99_ms": float(np.percentile(t, 99)), "max_ms": float(t.max())}
    out["ratio_median_sb3_over_deployed"] = out["sb3"]["median_ms"] / out["deployed"]["median_ms"]
    out["ratio_p99_sb3_over_deployed"] = out["sb3"]["p99_ms"] / out["deployed"]["p99_ms"]
    return out


def show_benchmark(o: dict[str, Any]) -> str:
    lines = [f"inference of {o['run_dir']} (device emulator in another process: "
             f"{'yes' if o['emulator_process'] else 'no'}), time per action:"]
    for name, label in (("deployed", "deployed (compiled)"), ("sb3", "SB3 predict (reference)")):
        m = o[name]
        lines.append(f"  {label:<26} median {m['median_ms']:.4f} ms   p99 {m['p99_ms']:.4f} ms"
                     f"   max {m['max_ms']:.3f} ms   ({m['actions']} actions)")
    lines.append(f"  SB3 / deployed: median x{o['ratio_median_sb3_over_deployed']:.1f}, "
                 f"p99 x{o['ratio_p99_sb3_over_deployed']:.1f}")
    return "\n".join(lines)
