"""A residual policy anchored at rest: its mean action is exactly zero where tracking is exact.

With ``errors_only`` features (``TrackingErrorObservation``) every feature is zero while the leg
follows X̂ exactly and no correction has been commanded: e, ė, the integrals, their resonant
outputs and the previous action. That is the state the feedforward alone keeps on the plant it
was computed for. An MLP's output there is whatever training left it at, not zero: a
constant pressure offset at rest, which on the nominal plant is a tracking error the
feedforward alone does not make and on the kmin design (flexor feedforward near 0 bar)
clips the flexor (CHANGELOG.md, 0.1.0, 56b6135). With the previous action among the
features, a nonzero rest output also feeds itself back as a fixed point.

``RestAnchoredPolicy`` is SB3's ``MlpPolicy`` with the Gaussian's mean

    μ(o) = f(o) − f(o_rest),    o_rest = the normaliser's image of the zero feature vector,

f the actor MLP and action net. The exploration noise, the critic and PPO's loss are SB3's. So
μ = 0 at rest on every plant, whatever the weights: where the feedforward is exact the residual
adds nothing, and the policy has to see an error before it corrects. ``o_rest`` is a buffer of
the policy (saved in its state dict), set from the VecNormalize statistics before each rollout
(``RestObservation``) and for every save (``rest_for_save``), so a loaded model is anchored at
its own normaliser's zero.

Opted into by ``mpa_gym.anchor_at_rest: true``; it needs ``errors_only`` features (with the
env's observation among them the rest state would depend on X̂ and the phase).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import DiagGaussianDistribution, Distribution
from stable_baselines3.common.policies import ActorCriticPolicy

# parameters, buffers and submodules assigned to any module, counted: a cached list of a
# module's tensors is stale once this changes (torch's global registration hooks)
_REGISTERED = [0]


def _registered(*_: Any) -> None:
    _REGISTERED[0] += 1


th.nn.modules.module.register_module_parameter_registration_hook(_registered)
th.nn.modules.module.register_module_buffer_registration_hook(_registered)
th.nn.modules.module.register_module_module_registration_hook(_registered)


class RestAnchoredPolicy(ActorCriticPolicy):
    """``MlpPolicy`` whose Gaussian mean is f(o) − f(o_rest) (module docstring)."""

    # the rest offset's cache (``rest_offset``) and the tensors its key reads (``_versions``);
    # here too for an object unpickled without __init__
    _cached: tuple[tuple[int, ...], th.Tensor] | None = None
    _watched: tuple[int, tuple[th.Tensor, ...]] | None = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if not isinstance(self.action_dist, DiagGaussianDistribution) or self.squash_output:
            raise ValueError("RestAnchoredPolicy needs a Gaussian policy without squashing "
                             "(use_sde=False, squash_output=False)")
        n = int(np.prod(self.observation_space.shape))
        self.register_buffer("rest_obs", th.zeros(n, dtype=th.float32))

    def _apply(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        """``to``, ``cpu``, ``float``, …: torch puts new tensors in place of the old without
        registering them, so the cache and the tensors its key reads are dropped."""
        self._cached = self._watched = None
        return super()._apply(fn, *args, **kwargs)

    def _versions(self) -> tuple[int, ...]:
        """Torch's in-place version counters of the rest point and the actor's weights: any
        optimiser step, ``load_state_dict`` or ``set_rest`` changes one of them; a parameter,
        buffer or submodule assigned anew changes ``_REGISTERED``, and ``_apply`` (a move or
        cast) drops the list, after which the tensors are gathered again. Writing a tensor's
        ``.data`` (``torch.nn.utils.vector_to_parameters``) changes no counter: follow it by
        ``load_state_dict`` or an in-place copy. One call costs a few microseconds: a report
        calls it once per step."""
        if self._watched is None or self._watched[0] != _REGISTERED[0]:
            mods = (self.mlp_extractor.policy_net, self.action_net, self.pi_features_extractor)
            self._watched = (_REGISTERED[0], (self.rest_obs, *(q for m in mods
                                                              for q in m.parameters())))
        return (self._watched[0], *(t._version for t in self._watched[1]))

    def rest_offset(self) -> th.Tensor:
        """f(o_rest): what the mean subtracts, (1, n_actions). Without gradients (rollouts,
        evaluation) it is computed once per set of weights and rest point: a rollout step
        would otherwise pay a second forward pass."""
        if th.is_grad_enabled():
            return self._rest_forward()
        key = self._versions()
        if self._cached is None or self._cached[0] != key:
            self._cached = (key, self._rest_forward())
        return self._cached[1]

    def _rest_forward(self) -> th.Tensor:
        rest = self.rest_obs.reshape(1, -1)
        return self.action_net(self.mlp_extractor.forward_actor(
            self.extract_features(rest, self.pi_features_extractor)))

    def action_mean(self, latent_pi: th.Tensor) -> th.Tensor:
        """μ = f(o) − f(o_rest) from the actor's latent code of o."""
        return self.action_net(latent_pi) - self.rest_offset()

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> Distribution:
        return self.action_dist.proba_distribution(self.action_mean(latent_pi), self.log_std)


def set_rest(model: Any) -> None:
    """Point a ``RestAnchoredPolicy``'s rest observation at the zero features as its model's
    VecNormalize sees them now (a no-op for other policies)."""
    pol = model.policy
    if not isinstance(pol, RestAnchoredPolicy):
        return
    zero = np.zeros((1, pol.rest_obs.numel()), dtype=np.float32)
    norm = model.get_vec_normalize_env()
    rest = norm.normalize_obs(zero) if norm is not None and norm.norm_obs else zero
    with th.no_grad():
        pol.rest_obs.copy_(th.as_tensor(np.asarray(rest, dtype=np.float32).reshape(-1)))


@contextmanager
def rest_for_save(model: Any) -> Iterator[None]:
    """Inside: the policy anchored at the normaliser as it is saved now; after: the rest point
    of the rollout under way again (PPO's update must see the one its actions were drawn with)."""
    pol = model.policy
    if not isinstance(pol, RestAnchoredPolicy):
        yield
        return
    before = pol.rest_obs.clone()
    set_rest(model)
    try:
        yield
    finally:
        with th.no_grad():
            pol.rest_obs.copy_(before)


class RestObservation(BaseCallback):
    """``set_rest`` before each rollout: the rollout's actions and PPO's update on them use one
    rest point, the normaliser's zero as the last rollout left it."""

    def _on_rollout_start(self) -> None:
        set_rest(self.model)

    def _on_step(self) -> bool:
        return True
