"""``openconvoy demo``: the whole sim2real path on one machine, in one command.

Three simulated MAVLink vehicles (``bridge.simvehicle.vehicle``, ArduPilot Rover by default, with
the recorded firmware's loops, vehicle model and boot sequence) start at the ``paper``
scenario's initial positions, and three ``openconvoy deploy`` processes
(leader + two followers, the ``paper`` policy) drive them over MAVLink (UDP on loopback)
while exchanging J2735 BSMs over real IPv6 multicast (or, ``--v2v ros2``, on a ROS 2
topic through Cyclone DDS on the same interface) — inside a private network namespace
(``unshare -rn``, see ``comms.netns``), so nothing leaves the machine. Live status lines
show the convoy; at the end every process is stopped cleanly (SIGTERM: stop, HOLD, log
flushed) and the run's metrics are printed side by side with the pure simulation of the
same scenario, policy and seed (``experiments.compare``).

The outer call checks that a namespace can be made (and says what is needed if not), then
re-runs itself inside one; the inner call (``OPENCONVOY_DEMO_INSIDE=1``) does the work.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from openconvoy.bridge.link import Autopilot
    from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig
    from openconvoy.convoy import VehicleLinkConfig

ENV_INSIDE = "OPENCONVOY_DEMO_INSIDE"
READY_AFTER_S = 3.0
"""The simulated autopilots allow arming this long after boot (real ArduPilot: ~42 s)."""
INIT_S = 2.34
"""ArduPilot's "ArduPilot Ready" (INITIAL_MODE MANUAL), then the RC mode switch's MANUAL
0.42 s later, as the firmware does at boot. The vehicles boot when their deploy connects
(as SITL waiting for serial0), so the GUIDED it sets first is lost and must be noticed."""
FOLLOWER_GRACE_S = 10.0
"""How long the followers may take to end by themselves once the leader's run ended."""
PHASE_SETTLE_S = 10.0
"""Speed tracking is judged from this long after each leader speed change."""


@dataclass(frozen=True)
class DemoOptions:
    """``openconvoy demo``'s options. ``duration_s`` None = the scenario's 60 s."""

    policy: str = "paper"
    per: float = 0.0
    autopilot: Autopilot = "ardupilot"
    duration_s: float | None = None
    out: str | None = None
    json: bool = False
    link: str = "mavlink"
    ros: int = 1
    bag: bool = False
    v2v: str = "multicast"


DEMO_LINKS = ("mavlink", "mavros", "mavros-ros1", "mavros-ros2", "px4-dds", "ap-dds")
"""What ``demo --link`` takes: one for every vehicle, or a comma list, one per vehicle."""


def vehicle_links(link: str, ros: int, n_vehicles: int) -> list[VehicleLinkConfig]:
    """Each vehicle's link from ``demo --link`` (one kind for all, or ``A,B,C`` leader
    first; ``mavros`` takes ``ros``, ``mavros-ros1``/``mavros-ros2`` say theirs), with the
    demo's namespaces (``/vehicle_N/mavros``, ``/vehicle_N/ap``, ``vehicle_N``). Raises
    ``ConfigError`` naming a kind it does not know or a count that is not the convoy's."""
    from openconvoy.convoy import VehicleLinkConfig
    from openconvoy.core.errors import ConfigError

    kinds = link.split(",")
    if len(kinds) == 1:
        kinds *= n_vehicles
    bad = [k for k in kinds if k not in DEMO_LINKS]
    if bad:
        raise ConfigError(f"--link: {bad[0]!r} is not one of {', '.join(DEMO_LINKS)}")
    if len(kinds) != n_vehicles:
        raise ConfigError(f"--link: {len(kinds)} links for {n_vehicles} vehicles")
    out = []
    for i, k in enumerate(kinds):
        version = {"mavros-ros1": 1, "mavros-ros2": 2}.get(k, ros)
        kind = "mavros" if k.startswith("mavros") else k
        ns = {
            "mavros": f"/vehicle_{i}/mavros", "ap-dds": f"/vehicle_{i}/ap",
            "px4-dds": f"vehicle_{i}",
        }.get(kind, "")  # fmt: skip
        out.append(VehicleLinkConfig(kind, version, ns))  # type: ignore[arg-type]
    return out


def demo_from_namespace(args: argparse.Namespace) -> int:
    opts = DemoOptions(
        args.policy,
        args.per,
        args.autopilot,
        args.duration,
        args.out,
        args.json,
        getattr(args, "link", "mavlink"),
        getattr(args, "ros", 1),
        getattr(args, "bag", False),
        getattr(args, "v2v", "multicast"),
    )
    from openconvoy.convoy import ConvoyConfig
    from openconvoy.core.errors import ConfigError

    n = len(ConvoyConfig().vehicles)  # the demo's convoy: the default vehicles
    kinds = {v.link for v in vehicle_links(opts.link, opts.ros, n)}  # ConfigError: exit 2
    if "ap-dds" in kinds and opts.autopilot != "ardupilot":
        raise ConfigError("--link: ap-dds drives ArduPilot vehicles, not --autopilot px4")
    if "px4-dds" in kinds and opts.autopilot != "px4":
        raise ConfigError("--link: px4-dds drives PX4 vehicles: add --autopilot px4")
    if os.environ.get(ENV_INSIDE) == "1":
        return run_inside(opts)
    return run_outside(opts)


# --- outside: check and re-run in a namespace -----------------------------------------------


NEEDS = (
    "openconvoy demo runs its vehicles in a private network namespace so that multicast never "
    "leaves this machine. It needs `unshare` (util-linux) and `ip` (iproute2), and permission "
    "to create user and network namespaces: unprivileged user namespaces enabled "
    "(sysctl kernel.unprivileged_userns_clone=1 where that exists, user.max_user_namespaces > 0, "
    "and on Ubuntu 24.04+ kernel.apparmor_restrict_unprivileged_userns=0), or run as root. "
    "Inside containers, the container must allow unshare (e.g. Docker --privileged or a "
    "seccomp profile permitting it)."
)


def _argv(opts: DemoOptions) -> list[str]:
    argv = ["demo", "--policy", opts.policy, "--per", repr(opts.per), "--autopilot", opts.autopilot]
    if opts.duration_s is not None:
        argv += ["--duration", repr(opts.duration_s)]
    if opts.out:
        argv += ["--out", str(Path(opts.out).resolve())]
    if opts.json:
        argv.append("--json")
    if opts.link != "mavlink":
        argv += ["--link", opts.link, "--ros", str(opts.ros)]
    if opts.bag:
        argv.append("--bag")
    if opts.v2v != "multicast":
        argv += ["--v2v", opts.v2v]
    return argv


def run_outside(opts: DemoOptions) -> int:
    from openconvoy.comms.netns import netns_unavailable_reason

    reason = netns_unavailable_reason()
    if reason is not None:
        print(
            f"openconvoy demo: cannot create a private network namespace: {reason}", file=sys.stderr
        )
        print(NEEDS, file=sys.stderr)
        return 2
    env = {**os.environ, ENV_INSIDE: "1"}
    cmd = ["unshare", "-rn", sys.executable, "-m", "openconvoy.cli", *_argv(opts)]
    proc = subprocess.Popen(cmd, env=env)

    def forward(signum: int, frame: Any) -> None:
        if proc.poll() is None:
            proc.send_signal(signum)

    old = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return proc.wait()
    finally:
        for s, h in old.items():
            signal.signal(s, h)


# --- inside the namespace ---------------------------------------------------------------------


def _setup_network() -> str:
    from openconvoy.comms import netns

    return netns.setup_network()


def free_udp_port() -> int:
    """A localhost UDP port nobody uses right now (for a simulated vehicle's MAVLink)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _say(line: str) -> None:
    print(line, flush=True)


def write_convoy_toml(
    path: Path,
    vehicles: tuple[str, ...],
    origin: tuple[float, float, float],
    *,
    keys: bool = True,
    links: Sequence[VehicleLinkConfig] = (),
) -> None:
    """The demo's convoy config (paper scenario, its vehicles, the default V2V group).

    With ``keys`` (the default) the convoy's authority and one key per vehicle are made in
    ``NAME.keys/`` beside it (``openconvoy keys init`` / ``issue``), so that every deploy
    signs and verifies its V2V messages; without, the caller makes its own keys (a deploy
    without keys refuses to start unless ``[v2v] auth = "off"`` is written). ``links``: a
    ``[[vehicle]]`` table per vehicle (its link, ROS version, namespace)."""
    vs = ", ".join(f'"{v}"' for v in vehicles)
    tables = "".join(
        f'\n[[vehicle]]\nlink = "{v.link}"\n'
        + (f"ros = {v.ros}\n" if v.link == "mavros" else "")
        + (f'namespace = "{v.namespace}"\n' if v.namespace else "")
        for v in links
    )
    path.write_text(
        "[convoy]\n"
        'name = "demo"\n'
        'scenario = "paper"\n'
        f"vehicles = [{vs}]\n"
        f"origin = [{origin[0]!r}, {origin[1]!r}, {origin[2]!r}]\n" + tables,
        encoding="utf-8",
    )
    if keys:
        from openconvoy.comms.security import keystore

        d = keystore.default_keys_dir(path)
        now = time.time()
        keystore.init_authority(d, "demo", now, force=True)
        for i in range(len(vehicles)):
            keystore.issue_vehicle(d, "demo", i, now, force=True)


PX4_HEADING_BIAS_MAX_DEG = 10.0
"""The simulated PX4s' EKF heading error is drawn within +- this (deg), per vehicle (its
seed): sitl-px4 shows +0.7..+5.8° per heading-step leg and a convoy leader at -11°."""


PX4_CLOCK_RATIO = 0.990
"""The simulated PX4s' clock, seconds per real second: the recorded SIH's."""


def sim_vehicle_configs(
    init: Any,
    origin: Any,
    presets: Sequence[Any],
    ids: Sequence[int] | None = None,
    **common: Any,
) -> list[SimVehicleConfig]:
    """A simulated vehicle's config for each convoy position ``i`` in ``ids`` (default:
    all): MAVLink system id i + 1, home at ``origin`` (an ``Origin``), the pose the
    scenario's initial state ``init`` gives vehicle i, ``presets[i]`` (None: the
    firmware's own loops and vehicle model), seed i; ``common`` (``SimVehicleConfig``
    fields) for all."""
    from openconvoy.bridge.simvehicle.vehicle import SimVehicleConfig

    return [
        SimVehicleConfig(
            system_id=i + 1,
            preset=presets[i],
            home=origin,
            start_x_m=float(init.x[i]),
            start_y_m=float(init.y[i]),
            start_heading_rad=float(init.heading[i]),
            seed=i,
            **common,
        )
        for i in (range(len(presets)) if ids is None else ids)
    ]


def start_local_sim_vehicles(
    configs: Sequence[SimVehicleConfig],
    before_start: Callable[[SimVehicle], None] | None = None,
) -> Iterator[tuple[SimVehicle, str]]:
    """Start a simulated vehicle per config, each on a free localhost UDP port (taken just
    before it binds), ``before_start`` applied first; yields each started vehicle with the
    MAVLink URL its deploy reaches it by."""
    from openconvoy.bridge.simvehicle.vehicle import SimVehicle

    for cfg in configs:
        port = free_udp_port()
        vehicle = SimVehicle(f"udpin:127.0.0.1:{port}", cfg)
        if before_start is not None:
            before_start(vehicle)
        yield vehicle.start(), f"udpout:127.0.0.1:{port}"


@dataclass(frozen=True)
class _DemoRun:
    """What one demo run drives: where, which convoy, how long."""

    iface: str
    out: Path
    convoy_path: Path
    convoy: Any
    n_vehicles: int
    init: Any
    duration_s: float


def _prepare(opts: DemoOptions) -> _DemoRun:
    """The network, the run directory, the convoy file and the scenario the demo runs."""
    from openconvoy.convoy import ConvoyConfig, load_convoy
    from openconvoy.envs.scenarios import make_scenario
    from openconvoy.envs.vehicles import vehicle_preset
    from openconvoy.policies import load_policy

    iface = _setup_network()
    out = Path(opts.out) if opts.out else Path(tempfile.mkdtemp(prefix="openconvoy-demo-"))
    out.mkdir(parents=True, exist_ok=True)
    convoy_path = out / "convoy.toml"
    defaults = ConvoyConfig()
    links = vehicle_links(opts.link, opts.ros, len(defaults.vehicles))
    write_convoy_toml(convoy_path, defaults.vehicles, defaults.origin, links=links)
    convoy = load_convoy(convoy_path)
    policy = load_policy(opts.policy)
    presets = [vehicle_preset(v) for v in convoy.vehicles]
    scenario = make_scenario("paper", presets=presets)
    member_config = policy.member_config
    if member_config is not None:
        scenario = scenario.with_changes(
            spacing=member_config.spacing
        )  # the policy's gaps, as `sim`
    duration = float(opts.duration_s or scenario.duration_s)
    return _DemoRun(
        iface, out, convoy_path, convoy, len(presets), scenario.initial_state(), duration
    )


_LINK_LABELS = {
    "mavlink": "MAVLink", "px4-dds": "PX4 DDS", "ap-dds": "AP_DDS", "mavros": "MAVROS",
    "mavros-ros1": "MAVROS", "mavros-ros2": "MAVROS",
}  # fmt: skip


def _via(opts: DemoOptions) -> str:
    """How the deploys reach their vehicles, for the demo's first line."""
    if "," in opts.link:
        return f" through {opts.link} (one link per vehicle, leader first; --ros {opts.ros})"
    return {
        "mavlink": "",
        "px4-dds": " through PX4 DDS stand-ins (Cyclone DDS)",
        "ap-dds": " through AP_DDS stand-ins on ROS 2",
        "mavros-ros1": " through MAVROS stand-ins on ROS 1",
        "mavros-ros2": " through MAVROS stand-ins on ROS 2",
    }.get(opts.link, f" through MAVROS stand-ins on ROS {opts.ros}")


def run_inside(opts: DemoOptions) -> int:
    run = _prepare(opts)
    convoy, out = run.convoy, run.out
    deploy_dir, sim_dir = out / "deploy", out / "sim"
    via = _via(opts)
    _say(
        f"openconvoy demo: {convoy.n_vehicles} simulated {opts.autopilot} vehicles{via}, policy "
        f"{opts.policy}, PER {opts.per:g}, {run.duration_s:g} s, V2V over IPv6 multicast on "
        f"{run.iface} (private network namespace); run in {out}"
    )
    code = _drive(opts, run, deploy_dir)
    if code == 130:
        return code
    if code != 0:
        for i in range(run.n_vehicles):
            tail = (out / f"deploy_{i}.txt").read_text(errors="replace").splitlines()[-8:]
            _say(f"--- deploy {i} (last lines) ---\n" + "\n".join(tail))
        return code
    _say("running the pure simulation of the same scenario ...")
    report = compare_with_sim(deploy_dir, sim_dir, opts, run.duration_s, convoy.origin)
    from openconvoy.experiments.compare import format_comparison

    _say(
        format_comparison(report["comparison"])
        .replace("A: ", "A (simulation): ", 1)
        .replace("B: ", f"B ({_LINK_LABELS.get(opts.link, opts.link)} + multicast): ", 1)
    )
    for vid, phases in report["speed_phases"].items():
        cells = ", ".join(f"{m:.2f}" for m in phases["mean_speed_mps"])
        _say(f"vehicle {vid}: mean speed per leader phase {cells} m/s")
    if opts.json:
        print(json.dumps(report, default=_json_default), flush=True)
    return 0


def _drive(opts: DemoOptions, run: _DemoRun, deploy_dir: Path) -> int:
    """Start the simulated vehicles and their deploys, watch the run, clean up; the exit
    status (130 when interrupted)."""
    from openconvoy.comms.geodesy import Origin

    vehicles: list[SimVehicle] = []
    procs: list[subprocess.Popen] = []
    logs: list[Any] = []
    ros: list[Any] = []  # roscore, then the MAVROS stand-ins (--link mavros)
    code = 1

    def on_term(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt  # SIGTERM cleans up like Ctrl-C: no orphaned deploys

    signal.signal(signal.SIGTERM, on_term)
    try:
        # The firmware's own loops and vehicle model (preset None), RC switch at boot.
        configs = sim_vehicle_configs(
            run.init,
            Origin(*run.convoy.origin),
            [None] * run.n_vehicles,
            autopilot=opts.autopilot,
            ready_after_s=READY_AFTER_S,
            init_s=INIT_S,
            rc_mode_switch=True,
            boot_on_connect=True,
            # PX4's EKF heading stays off by up to ~10° for a run (shared/AUTOPILOTS.md).
            heading_bias_max_deg=PX4_HEADING_BIAS_MAX_DEG if opts.autopilot == "px4" else 0.0,
            # and SIH's clock runs at 0.990 of real time (sitl-px4 README, row 24).
            px4_clock_ratio=PX4_CLOCK_RATIO if opts.autopilot == "px4" else None,
        )
        urls = []
        for vehicle, url in start_local_sim_vehicles(configs):
            vehicles.append(vehicle)
            urls.append(url)
        deploy_dir.mkdir(parents=True, exist_ok=True)
        links = run.convoy.vehicle
        env = _start_standins(ros, urls, links, opts.autopilot)
        for i, url in enumerate(urls):
            cmd = deploy_argv(
                i, run.convoy_path, url, run.iface, deploy_dir,
                "--per", repr(opts.per), "--seed", "0",
                policy=opts.policy,
            )  # fmt: skip
            # No --link: each deploy takes its link from the convoy file's [[vehicle]].
            if links[i].link != "mavlink":
                cmd = [c for c in cmd if c not in ("--mavlink", url)]
            if links[i].link == "mavros":
                cmd += ["--autopilot", opts.autopilot]
            if links[i].link == "px4-dds":
                cmd.append("--dds-localhost")
            if links[i].link == "ap-dds":
                cmd += ["--dds-iface", run.iface]  # Cyclone meets the rclpy stand-ins there
            if opts.bag:
                cmd.append("--bag")
            if opts.v2v != "multicast":
                cmd += ["--v2v", opts.v2v]  # the same signed bytes on a ROS 2 topic (DDS)
            if opts.duration_s is not None and i == 0:
                cmd += ["--duration", repr(run.duration_s)]
            err = open(run.out / f"deploy_{i}.txt", "w")
            logs.append(err)
            procs.append(subprocess.Popen(cmd, stdout=err, stderr=subprocess.STDOUT, env=env))
        code = _watch(procs, vehicles, run.duration_s)
    except KeyboardInterrupt:
        # Further Ctrl-C / SIGTERM must not cut the cleanup short.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        _say("interrupted: stopping the convoy")
        code = 130
    finally:
        stop_convoy(procs, vehicles)
        for f in logs:
            f.close()
        for r in reversed(ros):
            r.close()
    return code


def _start_standins(
    ros: list[Any], urls: Sequence[str], links: Sequence[VehicleLinkConfig], autopilot: str
) -> dict[str, str]:
    """The stand-in each vehicle's link needs in front of its simulated autopilot (none for
    MAVLink), appended to ``ros`` (closed last first); the deploys' environment
    (``ROS_MASTER_URI`` when a vehicle uses ROS 1).

    The ROS 2 stand-ins (MAVROS's and AP_DDS's) of all vehicles share one rclpy node
    process, ``/openconvoy_standins``: their topics and services are absolute
    (``/vehicle_N/...``), so what the deploys' links see is the same as with one node per
    vehicle, and the demo runs two rclpy processes fewer on a machine whose cores the
    deploys need (each rclpy process: Fast DDS's threads and its own discovery)."""
    env = dict(os.environ)
    ros2: Any = None
    if any((v.link == "mavros" and v.ros == 2) or v.link == "ap-dds" for v in links):
        from openconvoy.bridge.ros.ros2 import Ros2Node, build_interfaces, build_mavros_msgs

        build_mavros_msgs()
        build_interfaces("ardupilot_msgs")  # every ROS 2 node loads both packages
        # The ap-dds deploys' nodes are Cyclone DDS on the namespace's veth
        # (``--dds-iface``): the stand-ins' Fast DDS must look for peers there too.
        subnet = any(v.link == "ap-dds" for v in links)
        ros2 = Ros2Node("/openconvoy_standins", discovery="SUBNET" if subnet else None)
        ros.append(ros2)
    if any(v.link == "mavros" and v.ros == 1 for v in links):
        from openconvoy.bridge.ros.ros1 import Roscore

        core = Roscore()
        ros.append(core)
        env["ROS_MASTER_URI"] = core.uri
        _say(f"roscore at {core.uri}")
    for i, (url, v) in enumerate(zip(urls, links, strict=True)):
        standin: Any = None
        if v.link == "mavros":
            from openconvoy.bridge.ros.mavros_standin import MavrosStandIn

            node = ros2
            if v.ros == 1:
                from openconvoy.bridge.ros.ros1 import Ros1Node

                node = Ros1Node(f"/mavros_vehicle_{i}", env["ROS_MASTER_URI"])
                ros.append(node)
            standin = MavrosStandIn(node, url, v.ns)
            what = f"MAVROS stand-in under {v.ns} (ROS {v.ros})"
        elif v.link == "px4-dds":
            from openconvoy.bridge.px4dds.standin import Px4DdsStandIn

            standin = Px4DdsStandIn(url, ns=v.ns, localhost=True)
            what = f"PX4 DDS stand-in on rt/{v.ns}/fmu/... (Cyclone DDS, loopback)"
        elif v.link == "ap-dds":
            from openconvoy.bridge.ros.apdds_standin import ApDdsStandIn

            standin = ApDdsStandIn(ros2, url, v.ns)
            what = f"AP_DDS stand-in under {v.ns} (ROS 2, rclpy)"
        if standin is not None:
            ros.append(_Stopper(standin.start()))
            _say(f"vehicle {i}: {what} ({autopilot})")
    return env


class _Stopper:
    """``close`` = the stand-in's ``stop``."""

    def __init__(self, standin: Any) -> None:
        self.standin = standin

    def close(self) -> None:
        self.standin.stop()


def _json_default(v: Any) -> Any:
    if isinstance(v, float | np.floating) and not math.isfinite(v):
        return None
    if isinstance(v, np.generic):
        return v.item()
    return str(v)


def _watch(procs: list[subprocess.Popen], vehicles: list[Any], duration: float) -> int:
    """Status lines until the leader's run ends; then stop the followers. Exit status."""
    t0 = time.monotonic()
    # Start-up (imports, arming after READY_AFTER_S, hearing each other) plus the run.
    deadline = t0 + duration + 90.0
    last = -math.inf
    while procs[0].poll() is None:
        now = time.monotonic()
        # A follower ends by itself (exit 0) when it hears the leader's signed completion,
        # which may come just before the leader's own process exits.
        if any(p.poll() is not None and p.returncode != 0 for p in procs[1:]):
            _say("a follower's deploy ended early")
            return 1
        if now > deadline:
            _say("the leader did not finish in time")
            return 1
        if now - last >= 2.0:
            last = now
            _say(_status_line(now - t0, vehicles))
        time.sleep(0.1)
    if procs[0].returncode != 0:
        _say(f"the leader's deploy failed (exit {procs[0].returncode})")
        return 1
    # The followers end by themselves on the leader's signed completion; those still
    # running after a grace period are stopped.
    grace = time.monotonic() + FOLLOWER_GRACE_S
    while time.monotonic() < grace and any(p.poll() is None for p in procs[1:]):
        time.sleep(0.1)
    codes = stop_all(procs)
    _say(_status_line(time.monotonic() - t0, vehicles) + " | stopped")
    if any(c != 0 for c in codes):
        _say(f"deploy exit statuses {codes}")
        return 1
    return 0


def _status_line(t: float, vehicles: list[Any]) -> str:
    states = [v.state() for v in vehicles]
    parts = [f"t {t:5.1f} s", f"leader {states[0].speed:4.2f} m/s {vehicles[0].mode}"]
    for i in range(1, len(states)):
        gap = states[i].distance_to(states[i - 1])
        parts.append(f"v{i} {states[i].speed:4.2f} m/s gap {gap:5.2f} m {vehicles[i].mode}")
    return " | ".join(parts)


def deploy_argv(
    vehicle_id: int,
    convoy_path: Path,
    mavlink_url: str,
    iface: str,
    log_dir: Path,
    *extra: str,
    policy: str = "paper",
) -> list[str]:
    """The ``openconvoy deploy`` command line for one vehicle of a local convoy (this
    Python, the installed package), ``extra`` flags appended."""
    return [
        sys.executable, "-m", "openconvoy.cli", "deploy",
        "--policy", policy,
        "--vehicle-id", str(vehicle_id),
        "--convoy", str(convoy_path),
        "--mavlink", mavlink_url,
        "--iface", iface,
        "--log", str(log_dir),
        *extra,
    ]  # fmt: skip


def stop_all(procs: list[subprocess.Popen], timeout_s: float = 10.0) -> list[int]:
    """SIGTERM every deploy still running (stop, HOLD, flush), kill stragglers."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    codes = []
    for p in procs:
        try:
            codes.append(p.wait(timeout=timeout_s))
        except subprocess.TimeoutExpired:
            p.kill()
            codes.append(p.wait())
    return codes


def stop_convoy(procs: list[subprocess.Popen], vehicles: Sequence[Any]) -> list[int]:
    """Stop a local convoy: its deploys first (``stop_all``: they stop and HOLD their
    vehicles), then the simulated vehicles; the deploys' exit statuses."""
    codes = stop_all(procs)
    for v in vehicles:
        v.stop()
    return codes


def trim_to_run(
    log: dict[str, np.ndarray], t_start: float, duration: float
) -> dict[str, np.ndarray]:
    """The rows of a merged vehicle log within the leader's scenario window, with ``t_s``
    shifted to start at 0 (so its ticks read like a simulator log's)."""
    t = np.asarray(log["t_s"], dtype=float)
    keep = (t >= t_start) & (t <= t_start + duration)
    out = {k: v[keep] for k, v in log.items()}
    out["t_s"] = out["t_s"] - t_start
    return out


def speed_phases(log: dict[str, np.ndarray], duration: float) -> dict[int, dict[str, list[float]]]:
    """Each vehicle's mean speed in each leader speed phase of the paper scenario, from
    ``PHASE_SETTLE_S`` after the phase began to its end (``t_s`` from the run's start)."""
    from openconvoy.envs.scenarios import PAPER_PHASES

    t = np.asarray(log["t_s"], dtype=float)
    vid = np.asarray(log["vehicle_id"])
    out: dict[int, dict[str, list[float]]] = {}
    for v in sorted(set(vid.tolist())):
        means, targets = [], []
        for start, end, speed in PAPER_PHASES:
            lo, hi = start + PHASE_SETTLE_S, min(end, duration)
            if hi <= lo:
                continue
            sel = (vid == v) & (t >= lo) & (t < hi)
            means.append(float(np.mean(log["speed_mps"][sel])) if sel.any() else math.nan)
            targets.append(speed)
        out[int(v)] = {"mean_speed_mps": means, "leader_phase_mps": targets}
    return out


def compare_with_sim(
    deploy_dir: Path,
    sim_dir: Path,
    opts: DemoOptions,
    duration: float,
    origin: tuple[float, float, float],
) -> dict[str, Any]:
    """Metrics of the deploy run (trimmed to the leader's window) and of the pure
    simulation, and their comparison (``experiments.compare``: B = deploy, A = sim). The
    pure simulation's links delay messages as the deploys' V2V did (``fit_channel`` of the
    deploy logs: the phases between their loops), so both see messages equally old."""
    from openconvoy.core.metrics import compute_metrics
    from openconvoy.experiments.calibration import (
        fit_channel,
        median_telemetry_age,
        message_ages_at_first_use,
    )
    from openconvoy.experiments.compare import Side, compare
    from openconvoy.experiments.runs import LossSection, RunConfig, run_sim
    from openconvoy.logs import read_log

    meta = json.loads((deploy_dir / "vehicle_0.json").read_text())
    t_start = meta["t_start_s"]
    if t_start is None:
        raise RuntimeError("the leader never started driving")
    log = trim_to_run(read_log(deploy_dir), float(t_start), duration)
    ids = sorted(int(v) for v in np.unique(log["vehicle_id"]))
    # The simulated vehicles' clocks are the host's: their telemetry age is staleness.
    channel = fit_channel(log, {v: median_telemetry_age(log, v) for v in ids})
    sim = run_sim(
        RunConfig(
            scenario="paper",
            policy=opts.policy,
            per=opts.per,
            seed=0,
            duration_s=duration,
            origin=origin,
            loss=LossSection(
                latency_samples_s=channel.latency_samples_s,
                link_latency_s=channel.link_latency_s,
                stamp_error_s=channel.stamp_error_s,
                stamp_drift=channel.stamp_drift,
                staleness_s=channel.staleness_s,
            ),
        ),
        out_dir=sim_dir,
    )
    ages = {
        side: {
            str(v): float(np.median(message_ages_at_first_use(lg, v)))
            for v in ids
            if v > 0 and len(message_ages_at_first_use(lg, v))
        }
        for side, lg in (("deploy", log), ("sim", sim.log))
    }
    deploy_metrics = compute_metrics(log, sim.lengths)
    a = Side(sim_dir, "run", metrics=sim.metrics)
    b = Side(deploy_dir, "run", metrics=deploy_metrics)
    return {
        "deploy": deploy_metrics,
        "sim": sim.metrics,
        "comparison": compare(a, b),
        "speed_phases": speed_phases(log, duration),
        "sim_speed_phases": speed_phases(sim.log, duration),
        "deploy_dir": str(deploy_dir),
        "sim_dir": str(sim_dir),
        "t_start_s": t_start,
        "duration_s": duration,
        "first_use_message_age_s": ages,
    }
