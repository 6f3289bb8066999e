"""Model parameters: Tables A1 and A2 of the paper plus the assumptions where it is silent
(docs/design.md#assumptions).

All quantities are SI (m, s, N, Pa, kg). Pressures are gauge pressures (the paper's P').
Variants are made with :func:`dataclasses.replace`; no default is repeated anywhere else.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any

from mpa_gym.model.leg import flexor_path, knee_angle

BAR = 1.0e5  # [Pa] one bar; pressures are shown in bar at the edges only


def check_range(
    name: str,
    value: float,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    low_open: bool = False,
    high_open: bool = False,
    unit: str = "",
    note: str = "",
) -> float:
    """Return ``float(value)`` or raise ``ValueError`` naming the field, the value and the range.

    ``low_open`` / ``high_open`` make the corresponding bound strict; ``note`` says why the
    range is what it is (e.g. the equation that imposes it).
    """
    if isinstance(value, bool | str | bytes | complex) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name}={value!r} is not a number ({type(value).__name__} given)")
    x = float(value)
    left = "(" if low_open else "["
    right = ")" if high_open else "]"
    unit_s = f" {unit}" if unit else ""
    allowed = f"{left}{low:g}, {high:g}{right}{unit_s}" + (f" ({note})" if note else "")
    if not math.isfinite(x):
        raise ValueError(f"{name}={x!r} must be finite; allowed range {allowed}")
    too_low = x <= low if low_open else x < low
    too_high = x >= high if high_open else x > high
    if too_low or too_high:
        raise ValueError(f"{name}={x:g}{unit_s} is outside the allowed range {allowed}")
    return x


def check_keys(where: str, keys: Iterable[Any], allowed: Iterable[str],
               error: type[Exception] = ValueError, note: str = "") -> None:
    """Raise ``error`` naming the keys of ``keys`` (a mapping's) that are not ``allowed``, and
    the allowed ones (``note`` added in parentheses): the one check of a config section's
    keys."""
    allowed = sorted(allowed)
    unknown = sorted(set(keys) - set(allowed), key=str)
    if unknown:
        raise error(f"{where}: unknown key(s) {unknown}; allowed keys are {allowed}"
                    + (f" ({note})" if note else ""))


def _positive(obj: object, *names: str, units: dict[str, str]) -> None:
    for name in names:
        check_range(
            f"{type(obj).__name__}.{name}", getattr(obj, name), 0.0, low_open=True,
            unit=units.get(name, ""),
        )


@dataclass(frozen=True)
class MPAParams:
    """McKibben actuator model of Eq. (1)-(4) and the Appendix; one set shared by both MPAs."""

    C1: float = 192.0e3  # [Pa] C_1, Mooney-Rivlin constant, Tab. A1
    C2: float = 1.3e3  # [Pa] C_2, Mooney-Rivlin constant, Tab. A1
    D0: float = 15.0e-3  # [m] D_0, resting-state diameter, Tab. A1
    b: float = 148.0e-3  # [m] b, braid (fibre) length, Tab. A1
    n: float = 1.68  # [-] n, number of turns of a fibre, Tab. A1
    gamma: float = 30.0  # [N s/m] γ = γ_e = γ_f, viscosity coefficient, Eq. (4), Tab. A1
    L0: float = 125.0e-3  # [m] L_0 = L_e0 = L_f0, resting length, Tab. A1/A2
    thickness: float = 1.0e-3  # [m] t, bladder wall thickness (docs/design.md#assumptions)
    # Braid friction (not in the paper; 0 keeps its model exact): a dry friction on the tension
    # proportional to the pressure force −P' dV_b/dL, after Tondu & Lopez (2000); see mpa.force.
    friction: float = 0.0  # [-] μ_b, friction force / pressure force
    friction_v: float = 1.0e-3  # [m/s] v_b, contraction velocity of the tanh regularisation

    def __post_init__(self) -> None:
        units = {"C1": "Pa", "C2": "Pa", "D0": "m", "b": "m", "gamma": "N s/m", "L0": "m",
                 "thickness": "m", "friction_v": "m/s"}
        for f in fields(self):
            check_range(f"MPAParams.{f.name}", getattr(self, f.name))
        _positive(self, "C1", "D0", "b", "n", "gamma", "L0", "thickness", "friction_v",
                  units=units)
        check_range("MPAParams.C2", self.C2, 0.0, unit="Pa")
        check_range("MPAParams.friction", self.friction, 0.0, 1.0, high_open=True,
                    note="a share of the pressure force")
        # Pressure makes tension only while dV_b/dL < 0, i.e. L > b/√3 (braid angle < 54.7°).
        check_range("MPAParams.L0", self.L0, self.b / math.sqrt(3.0), self.b,
                    low_open=True, high_open=True, unit="m")
        check_range("MPAParams.thickness", self.thickness, 0.0, self.D0 / 2.0,
                    low_open=True, high_open=True, unit="m")

    @cached_property
    def Vr(self) -> float:
        """[m^3] V_r, rubber volume π L0 (r_o² − (r_o − t)²), r_o = D0/2
        (docs/design.md#assumptions)."""
        ro = 0.5 * self.D0
        return math.pi * self.L0 * (ro**2 - (ro - self.thickness) ** 2)

    @property
    def length_domain(self) -> tuple[float, float]:
        """[m] open interval (b/√3, b) of MPA lengths where the model is physical.

        At L = b the braid diameter vanishes; below b/√3 the braid angle passes 54.7° and
        pressure no longer produces tension (dV_b/dL changes sign).
        """
        return (self.b / math.sqrt(3.0), self.b)


@dataclass(frozen=True)
class LegParams:
    """Knee geometry and hip mass of Fig. 2, Tab. A2."""

    Lo: float = 450.0e-3  # [m] L_o, femur length (knee to hip), Tab. A2
    Lu: float = 425.0e-3  # [m] L_u, tibia length, Tab. A2
    L1: float = 200.0e-3  # [m] L_1, knee to flexor attachment on the upper link, Tab. A2
    L2: float = 100.0e-3  # [m] L_2, knee to flexor attachment on the lower link, Tab. A2
    r: float = 40.0e-3  # [m] r, knee pulley radius, Tab. A2
    m: float = 3.74  # [kg] m, representative mass of leg and hip, Tab. A2
    g: float = 9.86  # [m/s^2] g, gravitational acceleration, Tab. A2
    x_rest: float = 0.8  # [m] hip height where L_e = L_f = L0: β0 = β(x_rest) (assumption)
    # Friction of the hip slider (not in the paper; 0 keeps its Eq. 15 exact), see
    # dynamics.slider_friction: f_s = −F_c tanh(V / v_s) − c_s V.
    friction_coulomb: float = 0.0  # [N] F_c, Coulomb friction of the slider
    friction_viscous: float = 0.0  # [N s/m] c_s, viscous friction of the slider
    friction_v: float = 5.0e-3  # [m/s] v_s, hip velocity of the tanh regularisation

    def __post_init__(self) -> None:
        units = {k: "m" for k in ("Lo", "Lu", "L1", "L2", "r", "x_rest")}
        units.update(m="kg", g="m/s^2", friction_coulomb="N", friction_viscous="N s/m",
                     friction_v="m/s")
        for f in fields(self):
            check_range(f"LegParams.{f.name}", getattr(self, f.name))
        _positive(self, "Lo", "Lu", "L1", "L2", "r", "m", "g", "x_rest", "friction_v",
                  units=units)
        check_range("LegParams.friction_coulomb", self.friction_coulomb, 0.0, unit="N")
        check_range("LegParams.friction_viscous", self.friction_viscous, 0.0, unit="N s/m")
        lo, hi = self.x_domain
        check_range("LegParams.x_rest", self.x_rest, lo, hi, low_open=True, high_open=True,
                    unit="m")

    @cached_property
    def beta0(self) -> float:
        """[rad] β0 = β(x_rest), Eq. (9) (docs/design.md#assumptions)."""

        return float(knee_angle(self.x_rest, self))

    @cached_property
    def l_mf0(self) -> float:
        """[m] l_Mf0 = l_Mf(β0), Eq. (10) (docs/design.md#assumptions)."""

        return float(flexor_path(self.x_rest, self))

    @property
    def x_domain(self) -> tuple[float, float]:
        """[m] open interval (|L_o − L_u|, L_o + L_u) of hip heights the knee can reach."""
        return (abs(self.Lo - self.Lu), self.Lo + self.Lu)


@dataclass(frozen=True)
class RegulatorParams:
    """The pressure regulators between a command and the MPA (not in the paper, which applies
    P' at once; the defaults are that ideal regulator). Per MPA, with the command c delayed by
    the dead time, c_d(t) = c(t − T_d):

        dP'/dt = sat((c_d − P') / τ, r)     (sat clips to [−r, r]; r = 0: no limit)

    With τ = 0 the lag vanishes: P' = c_d, reached at the rate r when r > 0. See
    ``dynamics.regulator_pressure`` for the exact solution under a held command.
    """

    lag: float = 0.0  # [s] τ, first-order time constant (0: none)
    dead_time: float = 0.0  # [s] T_d, transport and valve delay (0: none)
    slew: float = 0.0  # [Pa/s] r, largest |dP'/dt| (0: unlimited)

    def __post_init__(self) -> None:
        check_range("RegulatorParams.lag", self.lag, 0.0, 1.0, unit="s")
        check_range("RegulatorParams.dead_time", self.dead_time, 0.0, 1.0, unit="s")
        check_range("RegulatorParams.slew", self.slew, 0.0, unit="Pa/s", note="0: unlimited")


@dataclass(frozen=True)
class Params:
    """Everything the physics needs: the MPA model (both actuators), the leg, the regulators."""

    mpa: MPAParams = field(default_factory=MPAParams)
    leg: LegParams = field(default_factory=LegParams)
    regulator: RegulatorParams = field(default_factory=RegulatorParams)

    def __post_init__(self) -> None:
        for name, cls in (("mpa", MPAParams), ("leg", LegParams), ("regulator", RegulatorParams)):
            if not isinstance(getattr(self, name), cls):
                raise TypeError(f"Params.{name} must be {cls.__name__}, got "
                                f"{type(getattr(self, name)).__name__}")


DEFAULT_PARAMS = Params()
