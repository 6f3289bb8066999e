"""Layer 4: Gymnasium environments over the shared task layer."""

from mpa_gym.envs.leg_env import MPALegEnv, MPALegResidualEnv

__all__ = ["MPALegEnv", "MPALegResidualEnv"]
