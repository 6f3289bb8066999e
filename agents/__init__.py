"""Layer 5: controllers for the MPA leg envs — classical baselines, PPO residual training and an
evaluation harness that treats them all alike (SB3's ``predict`` interface).

``load_policy`` (``mpa_gym.agents.learned.policies.load_policy``) loads a trained run folder,
supervised or not, or a built-in controller; it is imported when first used, so that importing
the package (the CLI, the envs' users) does not pay for the loader's imports.
"""

from __future__ import annotations

from typing import Any

__all__ = ["load_policy"]


def __getattr__(name: str) -> Any:
    if name == "load_policy":
        from mpa_gym.agents.learned.policies import load_policy

        return load_policy
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
