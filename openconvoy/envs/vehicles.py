"""Vehicle presets: size and the autopilot's inner-loop response, per vehicle class.

The numbers model a vehicle *with* its autopilot (DESIGN.md, Plant; AUTOPILOTS.md):
speed follows the setpoint with a first-order lag and an acceleration limit, heading
follows with a turn-rate limit, and every setpoint acts after an actuation delay.
Presets load from TOML files too (``fit-plant`` writes them), strictly: an unknown key
is an error naming the key.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from openconvoy.core.errors import ConfigError


@dataclass(frozen=True)
class RangingSensor:
    """A forward range sensor (lidar/radar) on the vehicle: range and range rate to the
    vehicle ahead, with Gaussian noise. Used by the degraded mode when present."""

    max_range_m: float = 20.0
    range_noise_m: float = 0.05
    range_rate_noise_mps: float = 0.05


@dataclass(frozen=True)
class VehiclePreset:
    """A vehicle class with its autopilot, in SI units.

    Attributes:
        name: preset name.
        length_m, width_m: body size; the reference point (GPS antenna) is the centre.
        wheelbase_m: bicycle wheelbase.
        max_steer_rad: steering lock; with the wheelbase it bounds curvature.
        speed_lag_s: time constant of the speed loop (first-order lag).
        accel_max_mps2: acceleration limit when speeding up.
        decel_max_mps2: deceleration limit when slowing down (positive number).
        turn_rate_max_radps: yaw-rate limit of the heading loop.
        heading_lag_s: time constant of the heading loop below the rate limit.
        actuation_delay_s: delay from setpoint to first actuator change.
        max_speed_mps: speed cap of the autopilot (ArduPilot WP_SPEED).
        ranging: optional forward ranging sensor.
    """

    name: str
    length_m: float
    width_m: float
    wheelbase_m: float
    max_steer_rad: float = math.radians(30.0)
    speed_lag_s: float = 0.3
    accel_max_mps2: float = 1.0
    decel_max_mps2: float = 1.0
    turn_rate_max_radps: float = math.radians(45.0)
    heading_lag_s: float = 0.2
    actuation_delay_s: float = 0.1
    max_speed_mps: float = 5.0
    ranging: RangingSensor | None = None

    def with_ranging(self, sensor: RangingSensor | None = None) -> VehiclePreset:
        """This preset carrying a ranging sensor (the default one if none given)."""
        return dataclasses.replace(self, ranging=sensor or RangingSensor())


VEHICLE_PRESETS: dict[str, VehiclePreset] = {
    "1/10": VehiclePreset(
        name="1/10", length_m=0.779, width_m=0.29, wheelbase_m=0.33,
        speed_lag_s=0.3, accel_max_mps2=1.0, decel_max_mps2=1.0,
        turn_rate_max_radps=math.radians(45.0), actuation_delay_s=0.1, max_speed_mps=5.0,
    ),
    "1/6": VehiclePreset(
        name="1/6", length_m=0.97, width_m=0.49, wheelbase_m=0.57,
        speed_lag_s=0.35, accel_max_mps2=1.0, decel_max_mps2=1.0,
        turn_rate_max_radps=math.radians(45.0), actuation_delay_s=0.12, max_speed_mps=5.0,
    ),
    "full-size": VehiclePreset(
        name="full-size", length_m=4.8, width_m=1.9, wheelbase_m=2.9,
        max_steer_rad=math.radians(35.0), speed_lag_s=0.4, accel_max_mps2=3.0,
        decel_max_mps2=8.0, turn_rate_max_radps=math.radians(30.0), heading_lag_s=0.3,
        actuation_delay_s=0.15, max_speed_mps=40.0,
    ),
}


def vehicle_preset(name_or_path: str) -> VehiclePreset:
    """A preset by name, or loaded from a TOML file path (as ``fit-plant`` writes)."""
    if name_or_path in VEHICLE_PRESETS:
        return VEHICLE_PRESETS[name_or_path]
    path = Path(name_or_path)
    if path.suffix == ".toml" and path.is_file():
        return load_vehicle_preset(path)
    raise ConfigError(
        f"unknown vehicle preset {name_or_path!r}; expected one of "
        f"{', '.join(VEHICLE_PRESETS)} or a .toml preset file"
    )


def load_vehicle_preset(path: Path) -> VehiclePreset:
    """Load a preset from TOML: a ``[vehicle]`` table (or top-level keys), strict."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    data = tomllib.loads(Path(path).read_text())
    table = data.get("vehicle", data)
    known = {f.name for f in dataclasses.fields(VehiclePreset)}
    unknown = set(table) - known
    if unknown:
        raise ConfigError(f"{path}: unknown vehicle preset key(s): {', '.join(sorted(unknown))}")
    table = dict(table)
    table.setdefault("name", Path(path).stem)
    if isinstance(table.get("ranging"), dict):
        table["ranging"] = RangingSensor(**table["ranging"])
    return VehiclePreset(**table)


def preset_to_toml(preset: VehiclePreset) -> str:
    """Serialize a preset as a ``[vehicle]`` TOML table that ``load_vehicle_preset`` reads."""
    lines = ["[vehicle]"]
    for f in dataclasses.fields(preset):
        value = getattr(preset, f.name)
        if value is None:
            continue
        if isinstance(value, RangingSensor):
            continue
        lines.append(f"{f.name} = {value!r}" if not isinstance(value, str) else f'{f.name} = "{value}"')
    if preset.ranging is not None:
        lines.append("")
        lines.append("[vehicle.ranging]")
        for f in dataclasses.fields(preset.ranging):
            lines.append(f"{f.name} = {getattr(preset.ranging, f.name)!r}")
    return "\n".join(lines) + "\n"
