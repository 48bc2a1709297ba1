"""The convoy config: one TOML file describes a convoy for both ``sim`` and ``deploy``.

```toml
[convoy]
name = "lab"                      # also seeds the vehicles' default BSM temporary ids
scenario = "paper"                # or "track", "emergency-braking", "track-file:PATH"
vehicles = ["1/10", "1/6", "1/10"]  # presets (or preset .toml files), leader first
origin = [28.6024, -81.2001, 0.0]   # ENU origin: latitude, longitude (deg), altitude (m)

[v2v]                             # optional; vehicles only
group = "ff15::4f43"              # IPv6 multicast group
port = 4200
hop_limit = 1
compat = false                    # also speak the original OpenConvoy JSON (IPv4)
temp_ids = ["4f430000", ...]      # optional explicit 4-byte BSM ids, leader first
auth = "required"                 # or "off"; default: required whenever keys exist
keys = "lab.keys"                 # the keys directory (default NAME.keys beside this file)
replay_window_s = 1.0             # reject signed messages generated longer ago than this

[safety]                          # optional; vehicles only
speed_cap_mps = 5.0
geofence_radius_m = 200.0         # around the origin
min_gap_m = 1.0                   # emergency stop below this measured gap
max_msg_age_s = 3.0               # stop while needed messages are older than this
```

Strict: an unknown key is an error naming it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from openconvoy.core.config import from_dict, load_toml

UCF_ORIGIN = (28.6024, -81.2001, 0.0)


AUTH_MODES = ("required", "off")


@dataclass(frozen=True)
class V2VConfig:
    """Where and how convoy members talk (see ``openconvoy.comms``).

    ``auth``: ``"required"`` (sign every BSM and abort as IEEE 1609.2 SPDUs, deliver only
    verified ones), ``"off"``, or ``""`` (the default: required when ``keys`` holds a
    convoy authority). ``keys``: the keys directory (``load_convoy`` makes a relative
    one relative to the convoy file, and defaults it to ``NAME.keys`` beside it).
    """

    group: str = "ff15::4f43"
    port: int = 4200
    hop_limit: int = 1
    compat: bool = False
    temp_ids: tuple[str, ...] = ()
    auth: str = ""
    keys: str = ""
    replay_window_s: float = 1.0

    def __post_init__(self) -> None:
        if self.auth not in ("", *AUTH_MODES):
            raise ValueError(f"v2v.auth: {self.auth!r} is not one of {', '.join(AUTH_MODES)}")
        if not (isinstance(self.replay_window_s, (int, float)) and self.replay_window_s > 0):
            raise ValueError(f"v2v.replay_window_s must be > 0 s, got {self.replay_window_s!r}")
        if self.compat:
            _ = self.auth_required  # refuses compat with authentication, at load time

    @property
    def auth_required(self) -> bool:
        """Whether messages are signed and verified (``ValueError`` with compat)."""
        required = self.auth == "required" or (
            self.auth == "" and bool(self.keys) and (Path(self.keys) / "authority.cert").is_file()
        )
        if required and self.compat:
            raise ValueError(
                "v2v: compat = true cannot be combined with authentication (the JSON format "
                "cannot be signed): set compat = false, or auth = \"off\""
            )
        return required


@dataclass(frozen=True)
class SafetyConfig:
    """Safety envelope on vehicles: limits that hold whatever the policy says."""

    speed_cap_mps: float = 5.0
    geofence_radius_m: float = 200.0
    min_gap_m: float = 1.0
    max_msg_age_s: float = 3.0
    """Stop while the messages a follower needs are older than this (s): a backstop for
    policies running without the staleness ladder."""


@dataclass(frozen=True)
class ConvoyConfig:
    """A convoy: scenario, vehicles (leader first), ENU origin, V2V and safety settings."""

    name: str = "openconvoy"
    scenario: str = "paper"
    vehicles: tuple[str, ...] = ("1/10", "1/6", "1/10")
    origin: tuple[float, float, float] = UCF_ORIGIN
    v2v: V2VConfig = field(default_factory=V2VConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, "vehicles", tuple(self.vehicles))
        object.__setattr__(self, "origin", tuple(float(v) for v in self.origin))
        if len(self.vehicles) < 2:
            raise ValueError("convoy.vehicles: a convoy needs a leader and at least one follower")
        if len(self.origin) != 3:
            raise ValueError("convoy.origin: expected [latitude_deg, longitude_deg, altitude_m]")

    @property
    def n_vehicles(self) -> int:
        return len(self.vehicles)


def load_convoy(path: str | Path) -> ConvoyConfig:
    """Read a convoy TOML file (tables ``[convoy]``, ``[v2v]``, ``[safety]``)."""
    data = load_toml(path)
    unknown = set(data) - {"convoy", "v2v", "safety"}
    if unknown:
        raise ValueError(f"{path}: unknown table(s) {', '.join(sorted(unknown))}; expected convoy, v2v, safety")
    table = dict(data.get("convoy", {}))
    for key in ("v2v", "safety"):
        if key in data:
            table[key] = data[key]
    if isinstance(table.get("v2v"), dict) and "temp_ids" in table["v2v"]:
        table["v2v"] = {**table["v2v"], "temp_ids": tuple(table["v2v"]["temp_ids"])}
    v2v = table.get("v2v") or {}
    if not isinstance(v2v, dict):
        raise ValueError(f"{path}: [v2v] must be a table")
    v2v = dict(v2v)
    keys = Path(str(v2v.get("keys") or Path(path).with_suffix(".keys").name))
    v2v["keys"] = str(keys if keys.is_absolute() else Path(path).parent / keys)
    table["v2v"] = v2v
    return from_dict(ConvoyConfig, table, str(path))
