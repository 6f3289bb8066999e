"""The ``mpa-gym`` command lives in the app, ``mpa_gym.agents.cli``."""

from mpa_gym.agents.cli import main

__all__ = ["main"]
