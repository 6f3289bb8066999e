"""Parameter dataclasses validate themselves: field, value and allowed range in every error."""

from __future__ import annotations

import dataclasses
import math

import pytest

from mpa_gym.model.params import DEFAULT_PARAMS, LegParams, MPAParams, Params, check_range


def test_defaults_are_the_papers_tables():
    m, leg = DEFAULT_PARAMS.mpa, DEFAULT_PARAMS.leg
    assert (m.C1, m.C2, m.D0, m.b, m.n, m.gamma, m.L0) == (192e3, 1.3e3, 15e-3, 148e-3, 1.68,
                                                           30.0, 125e-3)
    assert (leg.Lo, leg.Lu, leg.L1, leg.L2, leg.r, leg.m, leg.g) == (0.45, 0.425, 0.2, 0.1, 0.04,
                                                                     3.74, 9.86)
    assert (m.thickness, leg.x_rest) == (1e-3, 0.8)  # documented assumptions


@pytest.mark.parametrize(
    ("cls", "field", "value", "match"),
    [
        (MPAParams, "C1", float("nan"), r"MPAParams.C1=nan must be finite"),
        (MPAParams, "gamma", -30.0, r"MPAParams.gamma=-30 N s/m is outside the allowed range "
                                    r"\(0, inf\]"),
        (MPAParams, "n", 0.0, r"MPAParams.n=0 is outside the allowed range \(0, inf\]"),
        (MPAParams, "L0", 0.2, r"MPAParams.L0=0.2 m is outside the allowed range "
                               r"\(0.0854478, 0.148\) m"),
        (MPAParams, "thickness", 0.01, r"MPAParams.thickness=0.01 m is outside the allowed range "
                                       r"\(0, 0.0075\) m"),
        (MPAParams, "C2", -1.0, r"MPAParams.C2=-1 Pa is outside the allowed range \[0, inf\]"),
        (LegParams, "m", -3.74, r"LegParams.m=-3.74 kg is outside the allowed range"),
        (LegParams, "g", math.inf, r"LegParams.g=inf must be finite"),
        (LegParams, "x_rest", 0.9, r"LegParams.x_rest=0.9 m is outside the allowed range "
                                   r"\(0.025, 0.875\) m"),
    ],
)
def test_bad_parameter_names_field_value_and_range(cls, field, value, match):
    with pytest.raises(ValueError, match=match):
        cls(**{field: value})


def test_variants_are_made_with_replace_and_validated():
    heavy = dataclasses.replace(DEFAULT_PARAMS.leg, m=4.74)
    assert heavy.m == 4.74 and DEFAULT_PARAMS.leg.m == 3.74
    with pytest.raises(ValueError, match=r"LegParams\.m"):
        dataclasses.replace(DEFAULT_PARAMS.leg, m=0.0)
    with pytest.raises(TypeError, match=r"Params\.mpa must be MPAParams"):
        Params(mpa=DEFAULT_PARAMS.leg)  # type: ignore[arg-type]


def test_check_range_messages():
    with pytest.raises(ValueError, match=r"x='a' is not a number"):
        check_range("x", "a")
    assert check_range("x", 1, 0.0, 2.0) == 1.0
    with pytest.raises(ValueError, match=r"x=2 is outside the allowed range \[0, 2\) \(why\)"):
        check_range("x", 2.0, 0.0, 2.0, high_open=True, note="why")
