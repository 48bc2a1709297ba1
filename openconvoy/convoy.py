"""The convoy config: one TOML file describes a convoy for both ``sim`` and ``deploy``.

```toml
[convoy]
name = "lab"                      # also seeds the vehicles' default BSM temporary ids
scenario = "paper"                # or "track", "emergency-braking", "track-file:PATH"
vehicles = ["1/10", "1/6", "1/10"]  # presets (or preset .toml files), leader first
plants = ["fitted.vehicle_0.toml", ...]  # optional, sim only: the vehicles as they drive
origin = [28.6024, -81.2001, 0.0]   # ENU origin: latitude, longitude (deg), altitude (m)

[v2v]                             # optional; vehicles only
group = "ff15::4f43"              # IPv6 multicast group
port = 4200
hop_limit = 1
compat = false                    # also speak the original OpenConvoy JSON (IPv4)
temp_ids = ["4f430000", ...]      # optional explicit 4-byte BSM ids, leader first
auth = "required"                 # the default; "off" only when written here (see docs/security.md)
keys = "lab.keys"                 # the keys directory (default NAME.keys beside this file)
replay_window_s = 1.0             # clock tolerance (s): replay window, secMark rebuild, start skew
transport = "multicast"           # or "ros2": the same bytes on a ROS 2 topic (DDS; docs/ros.md)
ros2_topic = "/openconvoy/v2v"    # transport = "ros2": the topic ...
ros2_domain = 0                   # ... and the DDS domain id (0..232)

[[vehicle]]                       # optional; vehicles only: one per vehicle, leader first,
link = "mavlink"                  # how its deploy reaches its autopilot when deploy is given
                                  # no --link: "mavlink", "mavros", "ap-dds" or "px4-dds"
[[vehicle]]
link = "mavros"
ros = 2                           # mavros: ROS 1 (rospy) or 2 (rclpy)
namespace = "/vehicle_1/mavros"   # the link's namespace (default /mavros, /ap, none for px4-dds)
dds_domain = 0                    # px4-dds: the DDS domain id (0..232)

[safety]                          # optional; vehicles only
speed_cap_mps = 5.0
geofence_radius_m = 200.0         # around the origin
min_gap_m = 1.0                   # emergency stop below this measured gap
gap_margin_m = 0.2                # braking-aware stop margin between bumpers (m); default 1/4 length
max_msg_age_s = 3.0               # stop while needed messages are older than this

[channel]                         # optional; sim only: the simulated V2V links
per = 0.0                         # packet error rate (sim's --per overrides)
latency_s = 0.0                   # delivery delay (s; --latency overrides)
latency_samples_s = [0.033, ...]  # or a delay distribution (quantiles, s), as fit-plant
                                  # fits from a vehicle run's message ages
stamp_error_s = 0.0               # the senders' clock error (s), growing stamp_drift s/s
link_latency_s = [[0, 1, 0.033, ...]]  # per link: sender, receiver, its delay quantiles
staleness_s = [0.036, 0.033, 0.01]     # per sender: its messages stamped this much older (s)
lost_s = [[0, 1, 0.15, 1.71, ...]]     # per link: a vehicle run's dropped broadcasts, replayed
```

Strict: an unknown key, a value of the wrong type or out of its range is an error naming
the file, the key and what is allowed (``core.config.from_dict``), before anything moves.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from openconvoy.core.config import Range, check_fields, from_dict, load_toml
from openconvoy.core.errors import ConfigError

UCF_ORIGIN = (28.6024, -81.2001, 0.0)


AUTH_MODES = ("required", "off")
V2V_TRANSPORTS = ("multicast", "ros2")
"""``[v2v] transport``: IPv6 multicast (the default) or a ROS 2 topic over DDS."""


@dataclass(frozen=True)
class V2VConfig:
    """Where and how convoy members talk (see ``openconvoy.comms``).

    ``auth``: ``"required"`` (sign every BSM and abort as IEEE 1609.2 SPDUs, deliver only
    verified ones), ``"off"`` (unsigned: only when written explicitly), or ``""`` (not
    written: the same as ``"required"``; a deploy without keys then refuses to start —
    V2V fails closed). ``keys``: the keys directory (``load_convoy`` makes a relative
    one relative to the convoy file, and defaults it to ``NAME.keys`` beside it).
    ``replay_window_s``: the one clock tolerance (s) of the link: the replay window of
    signed messages, the slack of the secMark rebuild, and the largest clock offset
    between vehicles the convoy start accepts. ``transport``: ``"multicast"`` (IPv6, the
    default) or ``"ros2"`` (the same signed bytes on ROS 2 topic ``ros2_topic`` of DDS
    domain ``ros2_domain``: ``comms.dds``, which checks the topic name when a vehicle opens it).
    """

    group: str = "ff15::4f43"
    port: Annotated[int, Range(1, 65535)] = 4200
    hop_limit: Annotated[int, Range(1, 255)] = 1
    compat: bool = False
    temp_ids: tuple[str, ...] = ()
    auth: str = ""
    keys: str = ""
    # At least two control periods at 20 Hz: a shorter window rejects every message.
    replay_window_s: Annotated[float, Range(0.1, 60.0)] = 1.0
    transport: str = "multicast"
    ros2_topic: str = "/openconvoy/v2v"
    ros2_domain: Annotated[int, Range(0, 232)] = 0

    def __post_init__(self) -> None:
        check_fields(self, "v2v")
        if self.transport not in V2V_TRANSPORTS:
            raise ConfigError(
                f"v2v.transport: {self.transport!r} is not one of {', '.join(V2V_TRANSPORTS)}"
            )

        try:
            addr = ipaddress.ip_address(self.group)
        except ValueError:
            addr = None
        if addr is None or addr.version != 6 or not addr.is_multicast:
            raise ConfigError(
                f"v2v.group: {self.group!r} is not an IPv6 multicast group (e.g. ff15::4f43)"
            )
        if self.auth not in ("", *AUTH_MODES):
            raise ConfigError(f"v2v.auth: {self.auth!r} is not one of {', '.join(AUTH_MODES)}")
        if self.compat:
            _ = self.auth_required  # refuses compat with authentication, at load time

    @property
    def auth_required(self) -> bool:
        """Whether messages are signed and verified: always, unless ``auth = "off"`` is
        written (``ConfigError`` with compat, whose JSON cannot be signed)."""
        required = self.auth != "off"
        if required and self.compat:
            raise ConfigError(
                "v2v: compat = true cannot be combined with authentication (the JSON format "
                'cannot be signed): set compat = false, or auth = "off"'
            )
        return required


LinkKind = Literal["mavlink", "mavros", "px4-dds", "ap-dds"]
LINK_KINDS: tuple[str, ...] = ("mavlink", "mavros", "px4-dds", "ap-dds")
DEFAULT_NAMESPACES: dict[str, str] = {
    "mavlink": "",
    "mavros": "/mavros",
    "ap-dds": "/ap",
    "px4-dds": "",
}
"""Each link's namespace when none is written (``deploy``'s --mavros-ns, --ap-ns, --px4-ns)."""


@dataclass(frozen=True)
class VehicleLinkConfig:
    """How one vehicle's deploy reaches its autopilot (a ``[[vehicle]]`` table), used when
    ``deploy`` is given no ``--link``: ``link``, for ``mavros`` the ROS version ``ros``,
    ``namespace`` (MAVROS's, AP_DDS's or PX4's ``UXRCE_DDS_NS``; empty: the link's
    default, ``DEFAULT_NAMESPACES``), for ``px4-dds`` the DDS domain ``dds_domain``."""

    link: LinkKind = "mavlink"
    ros: Literal[1, 2] = 1
    namespace: str = ""
    dds_domain: Annotated[int, Range(0, 232)] = 0

    def __post_init__(self) -> None:
        check_fields(self, "vehicle")
        if self.link == "mavlink" and self.namespace:
            raise ConfigError("vehicle.namespace: MAVLink has no namespace (a ROS/DDS link has)")

    @property
    def ns(self) -> str:
        """The namespace, the link's default when none is written."""
        return self.namespace or DEFAULT_NAMESPACES[self.link]


@dataclass(frozen=True)
class SafetyConfig:
    """Safety envelope on vehicles: limits that hold whatever the policy says."""

    speed_cap_mps: Annotated[float, Range(0.0, 50.0, lo_open=True)] = 5.0
    geofence_radius_m: Annotated[float, Range(0.0, 100_000.0, lo_open=True)] = 200.0
    min_gap_m: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 1.0
    max_msg_age_s: Annotated[float, Range(0.0, 60.0, lo_open=True)] = 3.0
    """Stop while the messages a follower needs are older than this (s): a backstop for
    policies running without the staleness ladder."""
    gap_margin_m: Annotated[float | None, Range(0.0, 100.0)] = None
    """Braking-aware emergency stop (``core.safety``): the clearance left between bumpers
    after braking at the preset's limit may not fall below this (m); None = a quarter of
    the vehicle's length."""

    def __post_init__(self) -> None:
        check_fields(self, "safety")


@dataclass(frozen=True)
class ChannelConfig:
    """The simulated V2V channel of a convoy (``sim`` only; vehicles have real radios):
    ``comms.loss.LossConfig``'s fields (seconds; ``latency_samples_s`` an empirical delay
    distribution, see ``comms.loss.Latency``). ``fit-plant RUN --convoy`` writes it from a vehicle
    run: the measured loss and the distribution of message ages at first use."""

    per: Annotated[float, Range(0.0, 1.0)] = 0.0
    model: str = "bernoulli"
    mean_burst_s: Annotated[float, Range(0.0, 3600.0, lo_open=True)] = 1.0
    latency_s: Annotated[float, Range(0.0, 60.0)] = 0.0
    jitter_s: Annotated[float, Range(0.0, 60.0)] = 0.0
    latency_samples_s: tuple[float, ...] = ()
    stamp_error_s: Annotated[float, Range(-60.0, 60.0)] = 0.0
    stamp_drift: Annotated[float, Range(-0.1, 0.1)] = 0.0
    link_latency_s: tuple[tuple[float, ...], ...] = ()
    staleness_s: tuple[float, ...] = ()
    lost_s: tuple[tuple[float, ...], ...] = ()
    lost_window_s: Annotated[float, Range(0.0, 1.0, lo_open=True)] = 0.05

    def __post_init__(self) -> None:
        object.__setattr__(self, "latency_samples_s", tuple(self.latency_samples_s))
        object.__setattr__(self, "staleness_s", tuple(self.staleness_s))
        object.__setattr__(self, "lost_s", tuple(tuple(e) for e in self.lost_s))
        check_fields(self, "channel")
        bad = [v for v in self.staleness_s if not 0.0 <= float(v) <= 60.0]
        if bad:
            raise ConfigError(f"channel.staleness_s: {bad[0]!r} is not seconds in [0, 60]")
        if self.model not in ("bernoulli", "gilbert-elliott"):
            raise ConfigError(
                f"channel.model: {self.model!r} is not one of bernoulli, gilbert-elliott"
            )
        bad = [v for v in self.latency_samples_s if not 0.0 <= float(v) <= 60.0]
        if bad:
            raise ConfigError(f"channel.latency_samples_s: {bad[0]!r} is not seconds in [0, 60]")
        object.__setattr__(self, "link_latency_s", tuple(tuple(e) for e in self.link_latency_s))
        if self.latency_samples_s and self.jitter_s > 0.0:
            raise ConfigError("channel: give either jitter_s or latency_samples_s, not both")


@dataclass(frozen=True)
class ConvoyConfig:
    """A convoy: scenario, vehicles (leader first), ENU origin, V2V and safety settings."""

    name: str = "openconvoy"
    scenario: str = "paper"
    vehicles: tuple[str, ...] = ("1/10", "1/6", "1/10")
    plants: tuple[str, ...] = ()
    """sim only: the vehicles as they drive (``fit-plant --convoy``'s fitted presets), when
    they differ from ``vehicles`` (what the members and the scenario know); empty = those."""
    origin: tuple[
        Annotated[float, Range(-90.0, 90.0)],
        Annotated[float, Range(-180.0, 180.0)],
        Annotated[float, Range(-1000.0, 10_000.0)],
    ] = UCF_ORIGIN
    v2v: V2VConfig = field(default_factory=V2VConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    channel: ChannelConfig = field(default_factory=ChannelConfig)
    vehicle: tuple[VehicleLinkConfig, ...] = ()
    """Per vehicle (``[[vehicle]]`` tables, leader first): its link; empty = MAVLink for
    all (or what ``deploy --link`` says)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "vehicles", tuple(self.vehicles))
        object.__setattr__(self, "vehicle", tuple(self.vehicle))
        object.__setattr__(self, "origin", tuple(self.origin))
        check_fields(self, "convoy")
        object.__setattr__(self, "origin", tuple(float(v) for v in self.origin))
        if len(self.vehicles) < 2:
            raise ConfigError("convoy.vehicles: a convoy needs a leader and at least one follower")
        object.__setattr__(self, "plants", tuple(self.plants))
        if self.plants and len(self.plants) != len(self.vehicles):
            raise ConfigError(
                f"convoy.plants: {len(self.plants)} given for {len(self.vehicles)} vehicles"
            )
        if self.vehicle and len(self.vehicle) != len(self.vehicles):
            raise ConfigError(
                f"vehicle: {len(self.vehicle)} [[vehicle]] tables for {len(self.vehicles)} "
                "vehicles: give one per vehicle, leader first"
            )

    def vehicle_link(self, vehicle_id: int) -> VehicleLinkConfig:
        """Vehicle ``vehicle_id``'s link (MAVLink when the file names none)."""
        return self.vehicle[vehicle_id] if self.vehicle else VehicleLinkConfig()

    @property
    def n_vehicles(self) -> int:
        return len(self.vehicles)


def load_convoy(path: str | Path) -> ConvoyConfig:
    """Read a convoy TOML file (tables ``[convoy]``, ``[v2v]``, ``[safety]``, ``[channel]``,
    ``[[vehicle]]``)."""
    data = load_toml(path)
    unknown = set(data) - {"convoy", "v2v", "safety", "channel", "vehicle"}
    if unknown:
        raise ConfigError(
            f"{path}: unknown table(s) {', '.join(sorted(unknown))}; "
            "expected convoy, v2v, safety, channel, vehicle"
        )
    vehicle_tables = data.pop("vehicle", [])
    if not isinstance(vehicle_tables, list) or not all(isinstance(v, dict) for v in vehicle_tables):
        raise ConfigError(f"{path}: vehicle must be tables, one per vehicle ([[vehicle]])")
    for key, value in data.items():
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: {key} must be a table ([{key}]), got {value!r}")
    table: dict[str, Any] = dict(data.get("convoy", {}))
    for key in ("v2v", "safety", "channel"):
        if key in data:
            if key in table:
                raise ConfigError(f"{path}: {key} given twice ([{key}] and convoy.{key})")
            table[key] = data[key]
    v2v = dict(table.get("v2v") or {})
    if not isinstance(v2v.get("keys", ""), str):
        raise ConfigError(f"{path}: v2v.keys: expected a string (a directory), got {v2v['keys']!r}")
    keys = Path(str(v2v.get("keys") or Path(path).with_suffix(".keys").name))
    v2v["keys"] = str(keys if keys.is_absolute() else Path(path).parent / keys)
    table["v2v"] = v2v
    if vehicle_tables:
        if "vehicle" in table:
            raise ConfigError(f"{path}: vehicle given twice ([[vehicle]] and convoy.vehicle)")
        table["vehicle"] = vehicle_tables
    # A preset file named relative to the convoy file (as fit-plant --out-convoy writes).
    here = Path(path).parent
    for key in ("vehicles", "plants"):
        listed = table.get(key)
        if isinstance(listed, list):
            table[key] = [
                str(here / v)
                if isinstance(v, str) and v.endswith(".toml") and not Path(v).is_absolute()
                and not Path(v).is_file() and (here / v).is_file()
                else v
                for v in listed
            ]  # fmt: skip
    return from_dict(ConvoyConfig, table, str(path))
