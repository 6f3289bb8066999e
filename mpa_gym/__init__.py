"""mpa-gym: the McKibben-actuated leg of Sugimoto, Naniwa & Osuka as a physics model, the paper's
analytic design and stability tools, and Gymnasium environments.

Importing the package registers ``MPALeg-v0`` and ``MPALegResidual-v0`` (single and native vector
entry points).
"""

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

_ENVS = {
    "MPALeg-v0": ("MPALegEnv", "MPALegVectorEnv"),
    "MPALegResidual-v0": ("MPALegResidualEnv", "MPALegResidualVectorEnv"),
}
for _id, (_single, _vector) in _ENVS.items():
    if _id not in registry:
        register(
            id=_id,
            entry_point=f"mpa_gym.envs.leg_env:{_single}",
            vector_entry_point=f"mpa_gym.envs.vector:{_vector}",
            disable_env_checker=False,
        )
