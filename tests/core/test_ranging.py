"""core.ranging: the forward sensor's true range, range rate and field of view."""

from __future__ import annotations

import math

import pytest

from openconvoy.core.ranging import FIELD_OF_VIEW_RAD, in_view, range_and_rate


def test_range_and_rate_on_the_line_of_sight() -> None:
    # Ego at the origin east at 2 m/s; the car 3-4-5 ahead, north-east, standing still.
    rng, rate = range_and_rate(0.0, 0.0, 2.0, 0.0, 3.0, 4.0, 0.0, 0.0)
    assert rng == pytest.approx(5.0)
    assert rate == pytest.approx(-2.0 * 3.0 / 5.0)  # closing at the projection of 2 m/s
    # Same speed, same heading: the range does not change.
    assert range_and_rate(0.0, 0.0, 1.5, 0.3, 10 * math.cos(0.3), 10 * math.sin(0.3), 1.5, 0.3)[
        1
    ] == pytest.approx(0.0)
    assert range_and_rate(1.0, 1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0) == (0.0, 0.0)


def test_field_of_view_is_a_cone_about_the_heading() -> None:
    half = 0.5 * FIELD_OF_VIEW_RAD
    h = math.radians(170.0)  # facing west-ish: the bearing wraps around ±180°
    for off, seen in (
        (0.0, True),
        (half - 1e-3, True),
        (-half + 1e-3, True),
        (half + 1e-3, False),
        (math.pi, False),
    ):
        assert in_view(0.0, 0.0, h, 10 * math.cos(h + off), 10 * math.sin(h + off)) is seen, off
