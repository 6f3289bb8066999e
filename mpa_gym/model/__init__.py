"""Layer 1: the physics of the MPA leg (pure numpy, no gymnasium)."""

from mpa_gym.model.dynamics import (
    ForceTerms,
    force_terms,
    ground_force,
    integrate_reference,
    integrate_rk4,
    leg_dynamics,
    rk4_step,
)
from mpa_gym.model.leg import Kinematics, contractile_velocities, kinematics, knee_angle
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, LegParams, MPAParams, Params, check_range

__all__ = [
    "BAR",
    "DEFAULT_PARAMS",
    "ForceTerms",
    "Kinematics",
    "LegParams",
    "MPAParams",
    "Params",
    "check_range",
    "contractile_velocities",
    "force_terms",
    "ground_force",
    "integrate_reference",
    "integrate_rk4",
    "kinematics",
    "knee_angle",
    "leg_dynamics",
    "rk4_step",
]
