"""What a loaded policy does with a call: its episode state kept between calls, and the
observation checked against its env's.

A learned policy is a controller with memory: its front-end (``mpa_gym.agents.learned.frontend``:
the tracking-error integrals, the harmonic integrals, the stiffness estimate, the previous
action) and a supervisor's monitors live in the per-episode ``state`` of SB3's
``predict(observation, state, episode_start, deterministic) -> (action, state)``. A caller that
drops the returned state would restart all of it every step: the policy would run as a
memoryless one, without an error (30–1000× worse tracking on the held-out scenarios).

:class:`Episodic` therefore keeps the state itself, as a recurrent policy with an internal
state does. Refusing a call without ``state`` was the alternative; it is not taken because
``action, _ = policy.predict(obs)`` is how every SB3 example calls a model, and that call can
be made right rather than rejected:

- ``predict(obs)`` (no ``state``) continues the episode of the previous call: the state the
  policy returned last, row by row for a batch of ``n`` observations.
- An episode starts at the first call, after :meth:`Episodic.reset` (call it beside
  ``env.reset()``), and on the rows where ``episode_start`` is True; a call with
  ``episode_start`` True on every row starts all of them whatever ``state`` says.
- ``predict(obs, state, episode_start)`` with the state passed back is SB3's explicit form; it
  runs on the state given (the kept one only follows it), so the callers that pass it (the
  evaluation, the rig loop, the supervisor) get the numbers they always got.
- A call without ``state`` whose batch has another number of rows than the kept state, on rows
  that do not all start, is refused: which row continues which is not known.

The observation is the env's own (``MPALeg-v0``: 8 columns, ``MPALegResidual-v0``: 9; the
contract in ``mpa_gym.task.contract``), never the features a training wrapper computes from it
nor another env's. :class:`ObservationCheck` refuses any other shape, an observation whose
phase columns are not a unit vector (sin φ, cos φ of the reference phase, in every observation
of these envs: the features have no such pair) and one whose reference columns are outside the
contract's bounds, naming the env id and the shape it takes. A config's features can be as
wide as the residual env's observation (9: errors only, one harmonic remodulated, one previous
action), where the shape alone cannot tell them apart.
"""

from __future__ import annotations

import abc
import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from mpa_gym.task.contract import OBS_COS, OBS_SIN, PLAN, obs_columns, obs_names

# |sin² φ + cos² φ − 1| of an env observation: float32 rounding of two numbers of |.| ≤ 1 is
# ~2e-7; the features a wrapper computes (errors, integrals, actions) meet this only by accident
PHASE_TOL = 1e-5

RESIDUAL_ENV = "MPALegResidual-v0"


@dataclass(frozen=True)
class ObservationCheck:
    """The observation a policy takes: ``env_id``'s own, one row or a batch of rows."""

    env_id: str  # MPALeg-v0 or MPALegResidual-v0
    run: str = ""  # the run folder, for the message

    @functools.cached_property
    def width(self) -> int:
        return len(obs_names(self.env_id == RESIDUAL_ENV))

    @functools.cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The contract's bounds of the columns the plan fills (reference, phase, k̂: computed,
        so always within them); ±inf on the measured ones, which a sensor's spike on the rig
        may push past theirs, and where a bound depends on the task settings."""
        cols = obs_columns(self.env_id == RESIDUAL_ENV)
        return tuple(np.array([b if c.signal in PLAN and isinstance(b, float | int)
                               else sign * np.inf for c in cols for b in (getattr(c, side),)])
                     for side, sign in (("low", -1), ("high", 1)))

    def __call__(self, observation: Any) -> np.ndarray:
        """``observation`` as an array, or ValueError naming the env id and the shape it takes
        (:meth:`refusal`)."""
        obs = np.asarray(observation)
        if obs.ndim not in (1, 2) or obs.shape[-1] != self.width:
            raise self.refusal(obs)
        rows = obs.reshape(-1, self.width)
        ring = (rows[:, OBS_SIN].astype(np.float64) ** 2
                + rows[:, OBS_COS].astype(np.float64) ** 2)
        low, high = self.bounds
        if not ((np.abs(ring - 1.0) <= PHASE_TOL).all()  # also refuses a NaN phase
                and not ((rows < low) | (rows > high)).any()):
            raise self.refusal(obs)
        return obs

    def refusal(self, obs: np.ndarray) -> ValueError:
        """The error for an observation the check refuses: what is wrong with it (its shape, and
        which other env has that width; its phase; a reference column out of bounds) and
        what the policy takes."""
        w, who = self.width, f"policy {self.run}" if self.run else "this policy"
        take = (f"{who} takes the observation of {self.env_id} itself, shape ({w},) or (n, {w}) "
                "(the env's, before any wrapper: the policy computes its features itself)")
        if obs.ndim not in (1, 2) or obs.shape[-1] != w:
            other = [e for e in ("MPALeg-v0", RESIDUAL_ENV)
                     if e != self.env_id and obs.ndim in (1, 2)
                     and obs.shape[-1] == len(obs_names(e == RESIDUAL_ENV))]
            like = f" ({other[0]}'s width)" if other else ""
            return ValueError(f"observation has shape {obs.shape}{like}; {take}")
        rows = obs.reshape(-1, w)
        ring = np.abs(rows[:, OBS_SIN].astype(np.float64) ** 2
                      + rows[:, OBS_COS].astype(np.float64) ** 2 - 1.0)
        if not np.all(ring <= PHASE_TOL):
            bad = int(np.argmax(~(ring <= PHASE_TOL)))
            return ValueError(
                f"observation row {bad} is not an observation of {self.env_id}: its phase "
                f"columns (sin_phase, cos_phase) = ({rows[bad, OBS_SIN]:g}, "
                f"{rows[bad, OBS_COS]:g}) are not a unit vector (wrapped features or another "
                f"env's observation?); {take}")
        low, high = self.bounds
        r, c = np.argwhere((rows < low) | (rows > high))[0]
        name = obs_names(self.env_id == RESIDUAL_ENV)[c]
        return ValueError(f"observation row {r} is not an observation of {self.env_id}: "
                          f"{name}={rows[r, c]:g} is outside its bounds [{low[c]:g}, "
                          f"{high[c]:g}]; {take}")


class Episodic(abc.ABC):
    """A policy that keeps its episode state between calls (the module docstring says how).

    A subclass computes the action in ``_predict`` (SB3's ``predict`` on an explicit state:
    ``None`` starts every row); ``check`` (an :class:`ObservationCheck` or None) checks each
    observation first."""

    check: ObservationCheck | None = None
    _kept: Any = None  # the state the last call returned
    _kept_rows: int = 0

    @abc.abstractmethod
    def _predict(self, observation: Any, state: Any, episode_start: Any,
                 deterministic: bool) -> tuple[np.ndarray, Any]:
        """SB3's ``predict`` on an explicit state (the subclass's policy)."""

    def reset(self) -> None:
        """The next call starts an episode on every row (call it where ``env.reset()`` is)."""
        self._kept, self._kept_rows = None, 0

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        """Actions for one observation (d,) or a batch (n, d) of the env's own observations,
        and the state to pass back (or not: then this policy keeps it).

        Parameters
        ----------
        observation : array, (d,) or (n, d)
            The env's observation (``check``'s env id), not a wrapper's features.
        state : optional
            What the previous call returned. None: the state this policy kept from its
            previous call, or a new episode on every row at the first call and after
            :meth:`reset`.
        episode_start : bool array (n,), optional
            True on the rows whose episode starts with this observation.
        deterministic : bool
            The mean action (True: what evaluation and the rig run).
        """
        obs = observation if self.check is None else self.check(observation)
        n = 1 if np.ndim(obs) == 1 else len(obs)
        starts = (np.zeros(n, dtype=bool) if episode_start is None
                  else np.asarray(episode_start, dtype=bool).reshape(-1))
        if state is None and self._kept is not None and not starts.all():
            if n != self._kept_rows:
                raise ValueError(
                    f"a batch of {n} observations without state, but the episode state this "
                    f"policy kept has {self._kept_rows} rows: call policy.reset() when the "
                    "envs reset, pass episode_start=[True]*n, or pass back the state predict "
                    "returns")
            state = self._kept
        if state is None:  # every row starts: said explicitly to a nested policy
            episode_start = np.ones(n, dtype=bool)
        action, new = self._predict(obs, state, episode_start, deterministic)
        self._kept, self._kept_rows = new, n
        return action, new
