"""Reference periodic motion (Eq. 21) and flexor input patterns (Eq. 22, Table 1)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from mpa_gym.model.params import BAR, LegParams, check_range


@dataclass(frozen=True)
class Reference:
    """X̂(t) = X̂0 + Â sin ωt, V̂ = Â ω cos ωt, ω = 2π/T (Eq. 21)."""

    x0: float = 0.8  # [m] X̂0, centre of oscillation, Sec. 3.2
    amp: float = 0.02  # [m] Â, amplitude, Sec. 3.2
    period: float = 3.0  # [s] T, period, Sec. 3.2

    def __post_init__(self) -> None:
        check_range("reference.x0_m", self.x0, 0.0, low_open=True, unit="m")
        check_range("reference.amp_m", self.amp, 0.0, unit="m")
        check_range("reference.period_s", self.period, 0.0, low_open=True, unit="s")

    @property
    def omega(self) -> float:
        """[rad/s] ω = 2π / T."""
        return 2.0 * math.pi / self.period

    def position(self, t: ArrayLike) -> np.ndarray:
        """[m] X̂(t)."""
        return self.x0 + self.amp * np.sin(self.omega * np.asarray(t, dtype=float))

    def velocity(self, t: ArrayLike) -> np.ndarray:
        """[m/s] V̂(t)."""
        return self.amp * self.omega * np.cos(self.omega * np.asarray(t, dtype=float))

    def acceleration(self, t: ArrayLike) -> np.ndarray:
        """[m/s^2] dV̂/dt."""
        return -self.amp * self.omega**2 * np.sin(self.omega * np.asarray(t, dtype=float))

    def check_reachable(self, leg: LegParams) -> None:
        """Raise ValueError if X̂ leaves the heights the knee can reach."""
        lo, hi = leg.x_domain
        check_range("reference.x0_m - amp_m", self.x0 - self.amp, lo, hi, low_open=True,
                    high_open=True, unit="m")
        check_range("reference.x0_m + amp_m", self.x0 + self.amp, lo, hi, low_open=True,
                    high_open=True, unit="m")


@dataclass(frozen=True)
class FlexorPattern:
    """P'_f(t) = P'_f0 + A_f sin ωt with −P'_f0 ≤ A_f ≤ P'_f0 (Eq. 22). Pressures in Pa."""

    mean: float = 0.5 * BAR  # [Pa] P'_f0 (Fig. 3 uses a constant 0.5 bar)
    amp: float = 0.0  # [Pa] A_f
    period: float = 3.0  # [s] T, the reference's period

    def __post_init__(self) -> None:
        check_range("inputs.pf_mean_bar", self.mean / BAR, 0.0, unit="bar")
        check_range("inputs.pf_amp_bar", self.amp / BAR, -self.mean / BAR, self.mean / BAR,
                    unit="bar", note="Eq. 22: |A_f| <= P'_f0")
        check_range("inputs.period_s", self.period, 0.0, low_open=True, unit="s")

    def __call__(self, t: ArrayLike) -> np.ndarray:
        """[Pa] P'_f(t)."""
        w = 2.0 * math.pi / self.period
        return self.mean + self.amp * np.sin(w * np.asarray(t, dtype=float))


# Table 1: (P'_f0, A_f) in bar.
MODES: dict[int, tuple[float, float]] = {1: (1.0, 1.0), 2: (1.0, -0.5), 3: (1.0, -1.0)}


def mode_pattern(mode: int, period: float = 3.0) -> FlexorPattern:
    """Flexor pattern of Table 1's mode 1, 2 or 3."""
    if mode not in MODES:
        raise ValueError(f"mode={mode!r} is not one of Table 1's modes {sorted(MODES)}")
    mean_bar, amp_bar = MODES[mode]
    return FlexorPattern(mean=mean_bar * BAR, amp=amp_bar * BAR, period=period)
