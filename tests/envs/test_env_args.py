"""The envs' numeric arguments: a bad one is one ConfigError naming it (both envs alike)."""

from __future__ import annotations

import math

import pytest

from openconvoy.core.errors import ConfigError
from openconvoy.envs import ConvoyEnv, VectorConvoyEnv


@pytest.mark.parametrize(
    "make", [ConvoyEnv, lambda **kw: VectorConvoyEnv(2, **kw)], ids=["ConvoyEnv", "VectorConvoyEnv"]
)
@pytest.mark.parametrize(
    ("arg", "value"),
    [
        ("gps_noise_m", math.nan),
        ("gps_noise_m", math.inf),
        ("gps_noise_m", -0.1),
        ("control_rate_hz", math.nan),
        ("control_rate_hz", math.inf),
        ("control_rate_hz", 0.0),
        ("gps_noise_m", "loud"),
    ],
)
def test_a_bad_rate_or_gps_noise_is_one_config_error_naming_it(make, arg: str, value) -> None:
    # A NaN noise once turned the noise off in ConvoyEnv and gave NaN observations in the
    # batched env; inf ended in an IndexError.
    with pytest.raises(ConfigError, match=f"^{arg}: "):
        make(**{arg: value})
