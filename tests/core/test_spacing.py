import pytest

from openconvoy.core.spacing import SpacingConfig, SpacingPolicy


def test_constant_distance_ignores_speed_and_length():
    p = SpacingPolicy(SpacingConfig("constant-distance", distance_m=15.0))
    assert p.pair_gap(0.0, 0.78, 0.97) == 15.0
    assert p.pair_gap(2.0, 0.78, 0.97) == 15.0
    assert p.gap_to(2, 0, 1.0, [0.78, 0.97, 0.78]) == 30.0


def test_constant_time_headway_is_bumper_gap_plus_half_lengths():
    p = SpacingPolicy(SpacingConfig("constant-time-headway", standstill_m=2.0, headway_s=0.6))
    # 2 m + 0.6 s * 25 m/s between bumpers, plus two half lengths of 4.8 m cars.
    assert p.pair_gap(25.0, 4.8, 4.8) == pytest.approx(2.0 + 15.0 + 4.8)
    assert p.pair_gap(-1.0, 4.8, 4.8) == pytest.approx(2.0 + 4.8)
    assert p.gap_to(2, 0, 25.0, [4.8, 4.8, 4.8]) == pytest.approx(2 * 21.8)


def test_quadratic_adds_a_speed_squared_term():
    p = SpacingPolicy(
        SpacingConfig("quadratic", standstill_m=2.0, headway_s=0.6, quadratic_s2_per_m=0.02)
    )
    assert p.pair_gap(10.0, 0.0, 0.0) == pytest.approx(2.0 + 6.0 + 2.0)


def test_unknown_spacing_is_an_error():
    with pytest.raises(ValueError, match="spacing"):
        SpacingConfig("ideal")
