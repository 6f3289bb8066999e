"""The configs that ship with mpa-gym, installed as the package data of ``mpa_gym.configs``.

- ``ppo_residual.yaml``, ``ppo_scratch.yaml``: rl-baselines3-zoo hyper-parameter files for
  ``mpa-gym train`` (the first is its default);
- ``scenarios/*.yaml``: the named scenarios (``gymnasium.make(..., scenario=NAME)``);
- ``rigs/*.yaml``: named rigs for the device emulator and ``mpa-gym bench --loop --rig``.

The repository keeps them in its top-level ``configs/`` folder; setuptools maps that folder to
this package (``pyproject.toml``), so a wheel and an editable install find them in one place.
"""

from pathlib import Path

CONFIG_DIR = Path(__file__).resolve().parent
SCENARIO_DIR = CONFIG_DIR / "scenarios"
RIG_DIR = CONFIG_DIR / "rigs"
DEFAULT_TRAIN_CONFIG = CONFIG_DIR / "ppo_residual.yaml"
