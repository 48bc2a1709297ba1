import math

import pytest

from openconvoy.core.controllers import (
    HeadingControlConfig,
    PIDSpeed,
    SpeedControlConfig,
    pure_pursuit,
    stanley,
)


def test_pd_feeds_forward_and_corrects_error():
    pd = PIDSpeed(SpeedControlConfig("pd", kp=0.3, kd=1.1), dt=0.05)
    assert pd(0.0, 2.0, 0.0) == pytest.approx(2.0)
    assert pd(1.0, 2.0, 0.0) == pytest.approx(2.3)
    assert pd(1.0, 2.0, 0.5) == pytest.approx(2.3 + 0.55)


def test_pd_finite_difference_without_rate_and_no_kick_after_reset():
    pd = PIDSpeed(SpeedControlConfig("pd", kp=0.0, kd=1.0), dt=0.1)
    assert pd(1.0, 0.0) == 0.0  # first call: no derivative
    assert pd(1.5, 0.0) == pytest.approx(5.0)
    pd.reset()
    assert pd(3.0, 0.0) == 0.0


def test_pid_integral_accumulates_and_is_bounded():
    pid = PIDSpeed(SpeedControlConfig("pid", kp=0.0, ki=1.0, kd=0.0, integral_limit=0.5), dt=0.1)
    outs = [pid(1.0, 0.0, 0.0) for _ in range(10)]
    assert outs[0] == pytest.approx(0.1) and outs[2] == pytest.approx(0.3)
    assert outs[-1] == pytest.approx(0.5)


def test_stanley_corrects_heading_and_cross_track():
    assert stanley(0.1, 0.0, 2.0, 0.2, 0.5) == pytest.approx(0.1)
    # Path 1 m to the left: steer left, less at higher speed.
    slow = stanley(0.0, 1.0, 0.5, 0.2, 0.5)
    fast = stanley(0.0, 1.0, 5.0, 0.2, 0.5)
    assert slow == pytest.approx(math.atan2(0.2, 1.0)) and 0 < fast < slow


def test_pure_pursuit_points_at_the_lookahead():
    assert pure_pursuit(1.0, 1.0) == pytest.approx(math.pi / 4)
    assert pure_pursuit(0.0, 0.0) == 0.0


def test_unknown_controllers_are_errors():
    with pytest.raises(ValueError, match="speed controller"):
        SpeedControlConfig("bang-bang")
    with pytest.raises(ValueError, match="heading controller"):
        HeadingControlConfig("lqr")
