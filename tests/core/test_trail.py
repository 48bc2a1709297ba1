import math

import pytest

from openconvoy.core.trail import Trail


def straight(n: int, spacing: float = 0.5, capacity: int = 1024) -> Trail:
    trail = Trail(spacing_m=0.2, capacity=capacity)
    for k in range(n):
        trail.add(k * spacing, 0.0)
    return trail


def test_projection_gap_offset_and_heading_on_a_straight():
    trail = straight(41)  # 0 .. 20 m
    head = (21.0, 0.0)  # dead-reckoned 1 m past the last breadcrumb
    p = trail.project(head, 0.0, 6.0, -0.5, expected_arc=15.0)
    assert p.arc_to_head == pytest.approx(15.0)
    assert p.cross_track == pytest.approx(-0.5)  # the point is right of the path
    assert p.heading == pytest.approx(0.0)


def test_short_trail_extends_backwards_along_its_heading():
    trail = Trail()
    trail.add(0.0, 0.0)  # a vehicle that has not moved, heading north
    p = trail.project((0.0, 0.0), math.pi / 2, 0.0, -15.0, expected_arc=15.0)
    assert p.arc_to_head == pytest.approx(15.0) and p.cross_track == pytest.approx(0.0, abs=1e-9)
    assert trail.point_at((0.0, 0.0), math.pi / 2, p.s + 5.0) == pytest.approx((0.0, -10.0))


def test_points_beyond_the_head_continue_straight():
    trail = straight(3)
    assert trail.point_at((1.5, 0.0), 0.0, 3.0) == pytest.approx((3.0, 0.0))


def test_breadcrumbs_closer_than_the_spacing_are_skipped():
    trail = Trail(spacing_m=0.2)
    for x in (0.0, 0.1, 0.25, 0.3, 0.5):
        trail.add(x, 0.0)
    assert len(trail) == 3


def test_arc_coordinates_survive_dropping_old_breadcrumbs():
    trail = straight(40, capacity=16)
    assert len(trail) <= 16
    p = trail.project((19.5, 0.0), 0.0, 15.0, 0.0, expected_arc=4.5)
    assert p.s == pytest.approx(15.0)  # measured from the first breadcrumb ever
    # A hint from an earlier tick still starts the walk in the right place.
    q = trail.project((19.5, 0.0), 0.0, 15.2, 0.0, expected_arc=100.0, hint_s=p.s)
    assert q.arc_to_head == pytest.approx(4.3)


def test_walk_from_a_wrong_start_still_finds_the_nearest_segment():
    trail = straight(200)  # 0 .. 99.5 m
    p = trail.project((99.5, 0.0), 0.0, 10.0, 0.2, expected_arc=5.0)
    assert p.arc_to_head == pytest.approx(89.5)
