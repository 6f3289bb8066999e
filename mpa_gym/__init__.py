"""mpa-gym: the McKibben-actuated leg of Sugimoto, Naniwa & Osuka as a physics model, the paper's
analytic design and stability tools, and Gymnasium environments.

Importing the package registers ``MPALeg-v0`` and ``MPALegResidual-v0`` (single and native vector
entry points) and ``MPALegHardware-v0`` (the rig; ``gymnasium.make("MPALegHardware-v0",
device="udp://HOST:PORT")``).

The sub-packages load on first use (``mpa_gym.envs.MPALegEnv`` works after ``import mpa_gym``):
``model`` (physics), ``design`` and ``analysis`` (the paper's tools), ``task`` (what sim and rig
share), ``envs``, ``hardware``. The app side — controllers, PPO training, evaluation, rig tools
and the ``mpa-gym`` command — is ``mpa_gym.agents`` (the ``train`` extra); nothing outside it
imports it. The design document is ``docs/design.md`` in the repository.
"""

import importlib
from typing import Any

from gymnasium.envs.registration import register, registry

__version__ = "0.2.0"
_SUBPACKAGES = ("model", "design", "analysis", "task", "envs", "hardware", "configs", "agents")


def __getattr__(name: str) -> Any:
    """``mpa_gym.<sub-package>`` imported on first access (PEP 562)."""
    if name in _SUBPACKAGES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_SUBPACKAGES])


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
