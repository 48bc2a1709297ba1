"""Runs as ROS 2 bags (MCAP storage), written and read with the ``rosbags`` library.

``sim --bag`` and ``deploy --bag`` record a run as a ROS 2 bag beside its CSV log; ROS
tools (``ros2 bag``, Foxglove, ``mcap_ros2``) open it, and ``read_bag`` gives back the very
log ``openconvoy.logs.read_log`` reads from the CSV (``read_log`` reads bags through it), so
``report`` and ``compare`` take a bag wherever they take a log.

Topics, per vehicle ``N`` (docs/ros.md):

- ``/vehicle_N/fix`` ``sensor_msgs/msg/NavSatFix``: latitude, longitude (deg); altitude NaN
  (not logged).
- ``/vehicle_N/odom`` ``nav_msgs/msg/Odometry``: frame ``map`` = ENU around the convoy
  origin (REP 103, the log's frame), child ``vehicle_N/base_link`` (FLU); pose x, y (m),
  orientation = yaw ``heading_rad`` (ENU, CCW from east, as REP 103's yaw); twist linear.x
  = forward speed (m/s).
- ``/vehicle_N/cmd`` ``geometry_msgs/msg/TwistStamped``: linear.x = commanded speed (m/s),
  angular.z = commanded heading change spread over one control tick (rad/s).
- ``/vehicle_N/status`` ``openconvoy_msgs/msg/ConvoyStatus`` (``openconvoy/msg/``): every
  log column of the tick; the source of ``read_bag``.
- ``/vehicle_N/v2v/tx``, ``/vehicle_N/v2v/rx`` ``openconvoy_msgs/msg/V2VBytes``: V2V
  datagrams as sent and received.

Values are stored rounded as the CSV stores them (6 decimals), so a bag and its CSV agree to
the bit. Stamps (header and bag time) are ``t_s`` in nanoseconds (sim time from 0 in a
simulation, the shared wall clock on vehicles).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from openconvoy.core.errors import DependencyMissing, InputFileError, MissingFileError
from openconvoy.logs import COLUMNS, Log

MSG_DIR = Path(__file__).resolve().parent / "msg"
"""Our message definitions (``openconvoy_msgs``), ROS 2 ``.msg`` text."""

MSG_PACKAGE = "openconvoy_msgs"
STATUS_TYPE = f"{MSG_PACKAGE}/msg/ConvoyStatus"
V2V_TYPE = f"{MSG_PACKAGE}/msg/V2VBytes"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
ODOMETRY = "nav_msgs/msg/Odometry"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"

_INT_COLUMNS = ("vehicle_id", "msgs_sent", "msgs_received", "msgs_lost")
_FLOAT_COLUMNS = tuple(c for c in COLUMNS if c not in _INT_COLUMNS and c != "mode")
_META = "metadata.yaml"


def _rosbags() -> Any:
    try:
        import rosbags.rosbag2  # noqa: F401
        import rosbags.typesys  # noqa: F401
    except ModuleNotFoundError:
        raise DependencyMissing(
            "ROS bags need the rosbags package: pip install 'openconvoy[ros]'"
        ) from None
    import rosbags

    return rosbags


def typestore() -> Any:
    """A ROS 2 Jazzy typestore with ``openconvoy_msgs`` registered from ``openconvoy/msg``."""
    _rosbags()
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for path in sorted(MSG_DIR.glob("*.msg")):
        types.update(
            get_types_from_msg(path.read_text(encoding="utf-8"), f"{MSG_PACKAGE}/msg/{path.stem}")
        )
    store.register(types)
    return store


def _round6(value: Any) -> float:
    """A float column's value as ``LogWriter`` writes it and ``read_log`` reads it back."""
    if value is None or value == "":
        return math.nan
    v = float(value)
    return float(round(v, 6)) if math.isfinite(v) else v


def _int(value: Any) -> int:
    """A counter column's value as ``read_log`` reads it back (missing = -1)."""
    if value is None or value == "" or (isinstance(value, float) and math.isnan(value)):
        return -1
    return int(float(value))


def _stamp_ns(t_s: float) -> int:
    """Bag time (ns since the epoch, never negative) of a log time ``t_s`` (s)."""
    return max(0, round(t_s * 1e9))


class BagWriter:
    """Writes run log rows (and V2V datagrams) as a ROS 2 bag directory ``path`` (MCAP).

    ``tick_s``: the control period (s), to express heading changes as rates on the
    ``cmd`` topic. Use as a context manager, or call ``close``; ``path`` must not exist.
    """

    def __init__(self, path: str | Path, tick_s: float) -> None:
        _rosbags()
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        self.tick_s = float(tick_s)
        self.store = typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections: dict[tuple[str, str], Any] = {}
        self._closed = False
        self.rows = 0
        self.datagrams = 0
        self._t = self.store.types

    def _connection(self, topic: str, msgtype: str) -> Any:
        key = (topic, msgtype)
        if key not in self._connections:
            self._connections[key] = self._writer.add_connection(
                topic, msgtype, typestore=self.store
            )
        return self._connections[key]

    def _put(self, topic: str, msgtype: str, t_ns: int, msg: Any) -> None:
        data = self.store.serialize_cdr(msg, msgtype)
        self._writer.write(self._connection(topic, msgtype), t_ns, data)

    def _header(self, t_ns: int, frame_id: str) -> Any:
        t = self._t
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9),
            frame_id=frame_id,
        )

    def row(self, row: Mapping[str, Any]) -> None:
        """One log row (``openconvoy.logs.COLUMNS`` and extra columns) on the vehicle's topics."""
        t = self._t
        f = {c: _round6(row.get(c)) for c in _FLOAT_COLUMNS}
        n = {c: _int(row.get(c)) for c in _INT_COLUMNS}
        vid = n["vehicle_id"]
        ns = f"/vehicle_{vid}"
        t_ns = _stamp_ns(f["t_s"])
        extras = [k for k in row if k not in COLUMNS]
        status = t[STATUS_TYPE](
            header=self._header(t_ns, "map"),
            **f,
            **n,
            mode=str(row.get("mode") or ""),
            extra_names=extras,
            extra_values=np.array([_round6(row[k]) for k in extras], dtype=np.float64),
        )
        self._put(f"{ns}/status", STATUS_TYPE, t_ns, status)
        self._put(
            f"{ns}/fix",
            NAVSATFIX,
            t_ns,
            t[NAVSATFIX](
                header=self._header(t_ns, f"vehicle_{vid}/gps"),
                status=t["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
                latitude=f["lat_deg"],
                longitude=f["lon_deg"],
                altitude=math.nan,
                position_covariance=np.zeros(9, dtype=np.float64),
                position_covariance_type=0,
            ),
        )
        yaw = f["heading_rad"] if math.isfinite(f["heading_rad"]) else 0.0
        vec3, quat = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
        twist = t["geometry_msgs/msg/Twist"](
            linear=vec3(x=f["speed_mps"], y=0.0, z=0.0), angular=vec3(x=0.0, y=0.0, z=0.0)
        )
        odom = t[ODOMETRY](
            header=self._header(t_ns, "map"),
            child_frame_id=f"vehicle_{vid}/base_link",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](x=f["x_m"], y=f["y_m"], z=0.0),
                    orientation=quat(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
                ),
                covariance=np.zeros(36, dtype=np.float64),
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=twist, covariance=np.zeros(36, dtype=np.float64)
            ),
        )
        self._put(f"{ns}/odom", ODOMETRY, t_ns, odom)
        cmd = t[TWIST_STAMPED](
            header=self._header(t_ns, f"vehicle_{vid}/base_link"),
            twist=t["geometry_msgs/msg/Twist"](
                linear=vec3(x=f["cmd_speed_mps"], y=0.0, z=0.0),
                angular=vec3(x=0.0, y=0.0, z=f["cmd_heading_change_rad"] / self.tick_s),
            ),
        )
        self._put(f"{ns}/cmd", TWIST_STAMPED, t_ns, cmd)
        self.rows += 1

    def rows_many(self, rows: Iterable[Mapping[str, Any]]) -> None:
        for r in rows:
            self.row(r)

    def v2v(self, t_s: float, vehicle_id: int, direction: str, data: bytes) -> None:
        """One V2V datagram (``direction`` ``"tx"`` or ``"rx"``) at log time ``t_s`` (s)."""
        if direction not in ("tx", "rx"):
            raise ValueError(f"direction must be tx or rx, not {direction!r}")
        t_ns = _stamp_ns(t_s)
        msg = self._t[V2V_TYPE](
            header=self._header(t_ns, f"vehicle_{vehicle_id}"),
            vehicle_id=int(vehicle_id),
            direction=direction,
            data=np.frombuffer(bytes(data), dtype=np.uint8),
        )
        self._put(f"/vehicle_{vehicle_id}/v2v/{direction}", V2V_TYPE, t_ns, msg)
        self.datagrams += 1

    def close(self) -> None:
        """Finish the bag (its ``metadata.yaml`` and MCAP summary); idempotent."""
        if not self._closed:
            self._closed = True
            self._writer.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def is_bag(path: str | Path) -> bool:
    """True for a ROS 2 bag directory (with ``metadata.yaml``) or a file inside one."""
    p = Path(path)
    return (p / _META).is_file() if p.is_dir() else p.parent.joinpath(_META).is_file()


def bag_dirs(path: str | Path) -> list[Path]:
    """The bags a path designates: the bag itself (or the bag of a file in it), or the bags
    directly inside a directory (a vehicle run's log directory)."""
    p = Path(path)
    if not p.exists():
        raise MissingFileError(f"no such bag or directory: {p}")
    if is_bag(p):
        return [p if p.is_dir() else p.parent]
    if p.is_dir():
        return sorted(d for d in p.iterdir() if d.is_dir() and (d / _META).is_file())
    return []


def read_bag(path: str | Path) -> Log:
    """The run log recorded in a bag (or merged from the bags in a directory), columns as
    ``openconvoy.logs.read_log`` returns them, sorted by time then vehicle.

    A bag that cannot be read, or holds no ``ConvoyStatus`` message, is an
    ``InputFileError`` naming it."""
    _rosbags()
    from rosbags.rosbag2 import Reader

    bags = bag_dirs(path)
    if not bags:
        raise InputFileError(f"{path}: not a ROS 2 bag (no {_META}) and no bag inside")
    store = typestore()
    rows: list[Any] = []
    for bag in bags:
        try:
            with Reader(bag) as reader:
                status = [c for c in reader.connections if c.msgtype == STATUS_TYPE]
                # (an empty ``connections`` would mean every connection to rosbags)
                for conn, _, raw in reader.messages(connections=status) if status else ():
                    rows.append(store.deserialize_cdr(raw, conn.msgtype))
        except Exception as exc:  # rosbags raises its own errors for a broken bag
            raise InputFileError(f"{bag}: not a readable ROS 2 bag ({exc})") from None
    if not rows:
        raise InputFileError(f"{path}: the bag holds no {STATUS_TYPE} messages")
    return status_log(rows)


def status_log(msgs: list[Any]) -> Log:
    """Log columns from ``ConvoyStatus`` messages (rosbags or ``mcap_ros2`` objects alike)."""
    out: Log = {}
    for c in _FLOAT_COLUMNS:
        out[c] = np.array([float(getattr(m, c)) for m in msgs], dtype=np.float64)
    for c in _INT_COLUMNS:
        out[c] = np.array([int(getattr(m, c)) for m in msgs], dtype=np.int64)
    texts: dict[str, str] = {}
    out["mode"] = np.array([texts.setdefault(m.mode, m.mode) for m in msgs], dtype=object)
    extras = [dict(zip(m.extra_names, (float(v) for v in m.extra_values))) for m in msgs]
    for name in [n for n in extras[0] if all(n in e for e in extras)]:
        out[name] = np.array([e[name] for e in extras], dtype=np.float64)
    ordered: Log = {c: out[c] for c in COLUMNS}
    ordered.update({c: v for c, v in out.items() if c not in ordered})
    order = np.lexsort((ordered["vehicle_id"], ordered["t_s"]))
    return {c: v[order] for c, v in ordered.items()}
