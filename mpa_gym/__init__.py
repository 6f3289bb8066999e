"""mpa-gym: the McKibben-actuated leg of Sugimoto, Naniwa & Osuka as a physics model, the paper's
analytic design and stability tools, and Gymnasium environments.

Importing the package registers ``MPALeg-v0`` and ``MPALegResidual-v0`` (single and native vector
entry points) and ``MPALegHardware-v0`` (the rig; ``gymnasium.make("MPALegHardware-v0",
device="udp://HOST:PORT")``).
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
if "MPALegHardware-v0" not in registry:
    register(id="MPALegHardware-v0", entry_point="mpa_gym.hardware.env:HardwareLegEnv",
             disable_env_checker=True)  # the checker would drive the real rig
