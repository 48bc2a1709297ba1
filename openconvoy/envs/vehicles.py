"""Vehicle presets: size and the autopilot's inner-loop response, per vehicle class.

The numbers model a vehicle *with* its autopilot (DESIGN.md, Plant; AUTOPILOTS.md).
Two speed loops (``speed_loop``):

- ``lag`` (the original presets): speed follows the setpoint with a first-order lag and an
  acceleration limit.
- ``pi``: the autopilot's own speed controller, as in ArduPilot's ``AR_AttitudeControl``
  and PX4's rover speed control: the setpoint is ramped at the acceleration limits, a PI
  controller with feed-forward turns the ramp into a drive command, and the vehicle's
  speed follows that command with a first-order lag (the motor and body). This gives the
  firmware's ~0.3 s dead time and ~29 % overshoot that a lag cannot (shared/sitl/README.md
  §3). A static-friction dead zone (``breakaway_mps``) keeps a vehicle at rest until the
  drive command reaches it (PX4 SIH: ~0.75 m/s).

Heading follows with a rate limit (``err / heading_lag_s`` clipped to the turn-rate limit),
optionally slewed at a yaw acceleration limit and capped by the steering lock and a lateral
acceleration limit at speed. Every setpoint acts after its delay. The defaults of the new
fields keep the original presets' behaviour exactly. Presets load from TOML files too
(``fit-plant`` writes them, and the firmware-fitted presets ship as ``presets/*.toml``),
strictly: an unknown key is an error naming the key.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from openconvoy.core.config import Range, check_fields, from_dict, load_toml
from openconvoy.core.errors import ConfigError


@dataclass(frozen=True)
class RangingSensor:
    """A forward range sensor (lidar/radar) on the vehicle: range and range rate to the
    vehicle ahead, with Gaussian noise. Used by the degraded mode when present."""

    max_range_m: Annotated[float, Range(0.0, 10_000.0, lo_open=True)] = 20.0
    range_noise_m: Annotated[float, Range(0.0, 100.0)] = 0.05
    range_rate_noise_mps: Annotated[float, Range(0.0, 100.0)] = 0.05

    def __post_init__(self) -> None:
        check_fields(self, "ranging")


SPEED_LOOPS = ("lag", "pi")
"""The speed-loop models a preset can use (``VehiclePreset.speed_loop``)."""


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
        speed_loop: ``lag`` (first-order lag, ``speed_lag_s``) or ``pi`` (the autopilot's
            PI speed loop below; ``speed_lag_s`` unused). With ``pi`` the acceleration
            limits ramp the setpoint (ArduPilot ATC_ACCEL_MAX / ATC_DECEL_MAX).
        speed_kp: ``pi``: proportional gain, drive command (m/s) per m/s of error
            (ArduPilot: ATC_SPEED_P x the vehicle's m/s per unit throttle).
        speed_ki: ``pi``: integral gain, 1/s (ATC_SPEED_I x the same).
        speed_ff: ``pi``: feed-forward, drive command per m/s of ramped setpoint
            (ArduPilot: CRUISE_THROTTLE / CRUISE_SPEED x the same; 1 = exact).
        drive_lag_s: ``pi``: time constant of the vehicle's speed following the drive
            command (s).
        drive_drag_per_mps: ``pi``: quadratic drag; the steady speed v under drive d solves
            v + drag * v**2 = d (1/(m/s); 0 = linear, as ArduPilot's SITL rover; PX4 SIH's
            rover has drag that caps it near 2.55 m/s).
        stop_speed_mps: ``pi``: with the ramped setpoint at 0, below this speed the drive
            is cut and the integrator reset (ArduPilot ATC_STOP_SPEED): no undershoot.
        breakaway_mps: static friction: a vehicle at rest stays at rest while its drive
            command (``pi``) or speed setpoint (``lag``) is below this (m/s); 0 = none.
        kinetic_friction_mps: ``pi``: kinetic friction, the drive (m/s) it takes just to
            keep moving once broken away (PX4 SIH: rolling μ 0.3 against static μ 0.5,
            0.47 against 0.78 m/s of setpoint: a vehicle that breaks away lurches on, and
            a drive below this stops it again: stick-slip);
            0 = none (fitted by ``fit-plant`` only where static friction is).
        heading_delay_s: delay from a heading setpoint to its first effect (s); None =
            ``actuation_delay_s``.
        yaw_accel_max_radps2: slew limit of the heading loop's desired yaw rate (ArduPilot
            ATC_STR_ACC_MAX), rad/s²; inf = none.
        lateral_accel_max_mps2: yaw rate is also capped at this / speed (m/s²); inf = none.
        heading_bias_rad: the autopilot's heading estimate less the true heading (rad): what
            the vehicle reports and steers by (an EKF heading bias; PX4 SIH rovers logged
            -1 to -10 degrees, ArduPilot SITL about 0.5; ``fit-plant`` fits it from a run's
            logged headings against its track). The plant's speed is the one the vehicle
            reports, its velocity projected on the believed heading (as a deploy takes its
            forward speed), so the vehicle moves 1 / cos(b) as fast (the PX4 demo's follower
            1: -9.6 degrees, it logged 0.9855 of its track speed, cos(b) 0.9860). Scalar
            simulator only.
    """

    name: str
    length_m: Annotated[float, Range(0.0, 50.0, lo_open=True)]
    width_m: Annotated[float, Range(0.0, 10.0, lo_open=True)]
    wheelbase_m: Annotated[float, Range(0.0, 20.0, lo_open=True)]
    max_steer_rad: Annotated[float, Range(0.0, 1.5, lo_open=True)] = math.radians(30.0)
    speed_lag_s: Annotated[float, Range(0.0, 10.0)] = 0.3
    accel_max_mps2: Annotated[float, Range(0.0, 50.0, lo_open=True)] = 1.0
    decel_max_mps2: Annotated[float, Range(0.0, 50.0, lo_open=True)] = 1.0
    turn_rate_max_radps: Annotated[float, Range(0.0, 20.0, lo_open=True)] = math.radians(45.0)
    heading_lag_s: Annotated[float, Range(0.0, 10.0)] = 0.2
    actuation_delay_s: Annotated[float, Range(0.0, 2.0)] = 0.1
    max_speed_mps: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 5.0
    ranging: RangingSensor | None = None
    speed_loop: Literal["lag", "pi"] = "lag"
    speed_kp: Annotated[float, Range(0.0, 100.0)] = 0.0
    speed_ki: Annotated[float, Range(0.0, 100.0)] = 0.0
    speed_ff: Annotated[float, Range(0.0, 10.0)] = 1.0
    drive_lag_s: Annotated[float, Range(0.0, 10.0)] = 0.5
    drive_drag_per_mps: Annotated[float, Range(0.0, 10.0)] = 0.0
    stop_speed_mps: Annotated[float, Range(0.0, 10.0)] = 0.1
    breakaway_mps: Annotated[float, Range(0.0, 10.0)] = 0.0
    kinetic_friction_mps: Annotated[float, Range(0.0, 10.0)] = 0.0
    heading_delay_s: Annotated[float, Range(0.0, 2.0)] | None = None
    yaw_accel_max_radps2: Annotated[float, Range(0.0, lo_open=True, allow_inf=True)] = math.inf
    lateral_accel_max_mps2: Annotated[float, Range(0.0, lo_open=True, allow_inf=True)] = math.inf
    heading_bias_rad: Annotated[float, Range(-0.5, 0.5)] = 0.0

    def __post_init__(self) -> None:
        check_fields(self, f"vehicle preset {self.name!r}")
        if self.speed_loop not in SPEED_LOOPS:
            raise ConfigError(
                f"vehicle preset {self.name!r}: speed_loop must be one of "
                f"{', '.join(SPEED_LOOPS)}, got {self.speed_loop!r}"
            )

    @property
    def heading_delay(self) -> float:
        """The heading setpoint's delay (s): ``heading_delay_s`` or the actuation delay."""
        return self.actuation_delay_s if self.heading_delay_s is None else self.heading_delay_s

    def with_ranging(self, sensor: RangingSensor | None = None) -> VehiclePreset:
        """This preset carrying a ranging sensor (the default one if none given)."""
        return dataclasses.replace(self, ranging=sensor or RangingSensor())


VEHICLE_PRESETS: dict[str, VehiclePreset] = {
    "1/10": VehiclePreset(
        name="1/10",
        length_m=0.779,
        width_m=0.29,
        wheelbase_m=0.33,
        speed_lag_s=0.3,
        accel_max_mps2=1.0,
        decel_max_mps2=1.0,
        turn_rate_max_radps=math.radians(45.0),
        actuation_delay_s=0.1,
        max_speed_mps=5.0,
    ),
    "1/6": VehiclePreset(
        name="1/6",
        length_m=0.97,
        width_m=0.49,
        wheelbase_m=0.57,
        speed_lag_s=0.35,
        accel_max_mps2=1.0,
        decel_max_mps2=1.0,
        turn_rate_max_radps=math.radians(45.0),
        actuation_delay_s=0.12,
        max_speed_mps=5.0,
    ),
    "full-size": VehiclePreset(
        name="full-size",
        length_m=4.8,
        width_m=1.9,
        wheelbase_m=2.9,
        max_steer_rad=math.radians(35.0),
        speed_lag_s=0.4,
        accel_max_mps2=3.0,
        decel_max_mps2=8.0,
        turn_rate_max_radps=math.radians(30.0),
        heading_lag_s=0.3,
        actuation_delay_s=0.15,
        max_speed_mps=40.0,
    ),
}


PRESET_DIR = Path(__file__).with_name("presets")
"""Shipped presets fitted from real-firmware recordings (``fit-plant``), one TOML file each."""


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
    """Load a preset from TOML: a ``[vehicle]`` table (or top-level keys), strict: unknown
    keys, wrong types and values out of range are errors naming the file and key."""
    data = load_toml(path)
    table = data.get("vehicle", data)
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: vehicle must be a table ([vehicle]), got {table!r}")
    table = dict(table)
    table.setdefault("name", Path(path).stem)
    return from_dict(VehiclePreset, table, f"{path}: vehicle" if "vehicle" in data else str(path))


def preset_to_toml(preset: VehiclePreset) -> str:
    """Serialize a preset as a ``[vehicle]`` TOML table that ``load_vehicle_preset`` reads."""
    lines = ["[vehicle]"]
    for f in dataclasses.fields(preset):
        value = getattr(preset, f.name)
        if value is None:
            continue
        if isinstance(value, RangingSensor):
            continue
        lines.append(
            f"{f.name} = {value!r}" if not isinstance(value, str) else f'{f.name} = "{value}"'
        )
    if preset.ranging is not None:
        lines.append("")
        lines.append("[vehicle.ranging]")
        for f in dataclasses.fields(preset.ranging):
            lines.append(f"{f.name} = {getattr(preset.ranging, f.name)!r}")
    return "\n".join(lines) + "\n"


VEHICLE_PRESETS.update((f.stem, load_vehicle_preset(f)) for f in sorted(PRESET_DIR.glob("*.toml")))
