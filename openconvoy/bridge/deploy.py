"""``openconvoy deploy`` and ``openconvoy abort``: assemble a runner from the command line.

``deploy`` builds, from a convoy config and a policy spec, the pieces ``bridge.runner``
plugs together — the MAVLink link to the vehicle, the V2V link (J2735 BSMs over IPv6
multicast on ``--iface``, loss emulated with ``--per``), the leader's scenario or track —
installs SIGINT/SIGTERM handlers (stop, HOLD, flush the log, exit 0) and runs.
``abort`` broadcasts the convoy-wide stop every ``deploy`` obeys.

On a vehicle's companion computer, for example (telemetry radio or autopilot serial)::

    openconvoy deploy --policy paper+ladder --vehicle-id 1 --convoy lab.toml \
        --mavlink /dev/ttyACM0 --baud 921600 --iface wlan0 --per 0.3 --log runs/today

and from any machine on the convoy's network: ``openconvoy abort --iface wlan0``.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from openconvoy.core.errors import ConfigError

if TYPE_CHECKING:  # imported when a deploy runs, after its signal handlers are in place
    from openconvoy.bridge.runner import DeployRunner
    from openconvoy.comms.geodesy import Origin
    from openconvoy.convoy import ConvoyConfig


@dataclass(frozen=True)
class DeployArgs:
    """``openconvoy deploy``'s arguments (see the CLI help for each)."""

    policy: str
    vehicle_id: int
    convoy: str
    mavlink: str | None
    iface: str
    per: float = 0.0
    drop_at: Literal["receiver", "sender"] = "receiver"
    log: str | None = None
    rate: float | None = None
    dry_run: bool = False
    passive: bool = False
    track: str | None = None
    duration: float | None = None
    baud: int = 57600
    seed: int = 0
    arm_timeout: float = 60.0
    connect_timeout: float = 30.0
    telemetry_hz: float | None = None
    quiet: bool = False
    link: Literal["mavlink", "mavros", "px4-dds", "ap-dds"] | None = None
    """None: the convoy file's ``[[vehicle]]`` entry for this vehicle (``with_vehicle_link``),
    MAVLink when it has none."""
    ros: int = 1
    mavros_ns: str = "/mavros"
    autopilot: Literal["ardupilot", "px4"] | None = None
    bag: bool = False
    stay_armed: bool = False
    px4_ns: str = ""
    ap_ns: str = "/ap"
    dds_domain: int = 0
    dds_localhost: bool = False
    v2v: Literal["multicast", "ros2"] | None = None
    ap_dds_via: Literal["cyclone", "rclpy"] = "cyclone"
    dds_iface: str | None = None


def _status(quiet: bool):
    def emit(line: str) -> None:
        if not quiet:
            print(line, file=sys.stderr, flush=True)

    return emit


def build_runner(a: DeployArgs, convoy: ConvoyConfig | None = None) -> DeployRunner:
    """Everything ``deploy`` runs, not yet connected (sockets opened, no message sent)."""
    from openconvoy.bridge.recorder import RunRecorder
    from openconvoy.bridge.runner import DeployRunner, RunnerOptions
    from openconvoy.comms.geodesy import Origin
    from openconvoy.convoy import load_convoy
    from openconvoy.envs.vehicles import vehicle_preset
    from openconvoy.outputs import check_output_dir
    from openconvoy.policies import load_policy

    convoy = convoy or load_convoy(a.convoy)
    n = convoy.n_vehicles
    if not 0 <= a.vehicle_id < n:
        raise ConfigError(f"--vehicle-id {a.vehicle_id}: the convoy has vehicles 0..{n - 1}")
    a = with_vehicle_link(a, convoy)
    policy = load_policy(a.policy)
    presets = [vehicle_preset(v) for v in convoy.vehicles]
    origin = Origin(*convoy.origin)
    rate = a.rate if a.rate is not None else float(policy.control_rate_hz)
    status = _status(a.quiet)
    spec = f"track-file:{a.track}" if a.track else convoy.scenario
    leader, leader_origin = _leader_driver(a, spec, presets)
    options = RunnerOptions(  # checks rate and timeouts before any socket opens
        vehicle_id=a.vehicle_id,
        rate_hz=rate,
        dry_run=a.dry_run,
        passive=a.passive,
        duration_s=a.duration,
        connect_timeout_s=a.connect_timeout,
        arm_timeout_s=a.arm_timeout,
        seed=a.seed,
        stay_armed=a.stay_armed,
    )
    if a.link == "mavlink" and not a.mavlink:
        raise ConfigError("--mavlink URL is required with --link mavlink")
    if a.bag and a.log is None:
        raise ConfigError("--bag records beside the log: give --log DIR")
    auth = vehicle_authenticator(convoy, a.vehicle_id, a.convoy)  # before any file or socket
    v2v_config = _v2v_config(a, convoy)
    if a.log is not None:
        check_output_dir(a.log, "--log")  # before connecting, never after arming
        RunRecorder(a.log, a.vehicle_id).check_free()  # a second deploy of this vehicle
    if auth is not None:
        status(
            f"vehicle {a.vehicle_id}: V2V signed as {auth.credentials.certificate.name} "
            f"(IEEE 1609.2), accepting {auth.credentials.authority.name}'s certificates"
        )
        if a.vehicle_id == 0 and not a.passive and not _may_sign_completion(auth):
            status(
                "vehicle 0: its certificate predates the leader's completion message: the "
                "followers will not hear that the scenario ended (re-issue it: `openconvoy "
                f"keys issue --convoy {a.convoy} --vehicle-id 0 --force`)"
            )
    link = _make_link(a, origin, presets[a.vehicle_id], rate, status)
    bag = _make_bag(a, rate)
    v2v = _make_v2v(a, convoy, v2v_config, origin, auth, bag)  # opens the sockets
    if auth is None:  # only with auth = "off" written in the convoy file: say so at every start
        print(unauthenticated_warning(a.vehicle_id, a.convoy), file=sys.stderr, flush=True)
    runner = DeployRunner(
        options,
        convoy,
        policy,
        link,
        v2v,
        leader=leader,
        lengths=[p.length_m for p in presets],
        decels=[p.decel_max_mps2 for p in presets],
        log_dir=a.log,
        on_status=status,
        leader_origin=leader_origin,
        metadata={
            "per": a.per,
            "drop_at": a.drop_at,
            "policy_spec": a.policy,
            "scenario_spec": spec,
            "mavlink": a.mavlink,
            "link": _link_name(a),
            "iface": a.iface,
        },
    )
    runner.runlog.recorder.bag = bag
    return runner


def with_vehicle_link(a: DeployArgs, convoy: ConvoyConfig) -> DeployArgs:
    """``a`` with its link settled: ``--link`` given, the command line's; otherwise the
    convoy file's ``[[vehicle]]`` entry for ``a.vehicle_id`` (link, ROS version, namespace,
    DDS domain), MAVLink when the file has none."""
    if a.link is not None:
        return a
    v = convoy.vehicle_link(a.vehicle_id)
    ns_field = {"mavros": "mavros_ns", "ap-dds": "ap_ns", "px4-dds": "px4_ns"}.get(v.link)
    extra: dict[str, Any] = {ns_field: v.ns} if ns_field else {}
    return replace(a, link=v.link, ros=v.ros, dds_domain=v.dds_domain, **extra)


def _make_bag(a: DeployArgs, rate: float) -> Any:
    """``--bag``: the ROS 2 bag directory ``LOG/vehicle_N_bag`` (replaced, like the CSV),
    or None."""
    if not a.bag or a.log is None:
        return None
    import shutil

    from openconvoy.bag import BagWriter

    path = Path(a.log) / f"vehicle_{a.vehicle_id}_bag"
    if (path / "metadata.yaml").is_file():
        shutil.rmtree(path)
    return BagWriter(path, tick_s=1.0 / rate)


def _link_name(a: DeployArgs) -> str:
    """The link as the run's metadata names it."""
    if a.link == "px4-dds":
        return f"px4-dds (domain {a.dds_domain}, ns {a.px4_ns or '-'})"
    if a.link == "ap-dds":
        via = "ROS 2" if a.ap_dds_via == "rclpy" else f"DDS domain {a.dds_domain}"
        return f"ap-dds ({via}, {a.ap_ns})"
    return f"mavros (ROS {a.ros}, {a.mavros_ns})" if a.link == "mavros" else "mavlink"


def _make_link(
    a: DeployArgs, origin: Origin, preset: Any, rate: float, status: Callable[[str], None]
) -> Any:
    """The autopilot link (not yet connected); telemetry at the control rate within
    10..50 Hz unless ``telemetry_hz`` says otherwise. ``--link mavros``: through MAVROS
    (``bridge.ros.mavros_link``), its ROS 1 or ROS 2 node named after the vehicle. ``--link px4-dds``:
    PX4's DDS topics (``bridge.px4dds.link``). ``--link ap-dds``: ArduPilot's AP_DDS
    topics and services under ``ap_ns`` through a ROS 2 node (``bridge.ros.apdds_link``)."""
    if a.link == "ap-dds":
        from openconvoy.bridge.ros.apdds_link import ApDdsLink
        from openconvoy.bridge.ros.ros2 import Ros2Node

        if a.autopilot == "px4":
            raise ConfigError("--link ap-dds is ArduPilot's interface: not with --autopilot px4")
        name = f"/openconvoy_vehicle_{a.vehicle_id}"

        def ap_node() -> Any:
            if a.ap_dds_via == "rclpy":
                return Ros2Node(name)
            from openconvoy.bridge.ros.ros2 import CycloneNode

            return CycloneNode(name, iface=a.dds_iface, domain_id=a.dds_domain)

        return ApDdsLink(
            ap_node,
            a.ap_ns,
            origin,
            a.vehicle_id,
            on_status=status,
            length_m=preset.length_m,
            width_m=preset.width_m,
        )
    if a.link == "px4-dds":
        from openconvoy.bridge.px4dds.link import Px4DdsLink

        return Px4DdsLink(
            a.px4_ns,
            origin,
            a.vehicle_id,
            a.dds_domain,
            a.dds_localhost,
            on_status=status,
            iface=a.dds_iface,
        )
    if a.link == "mavros":
        from openconvoy.bridge.ros.mavros_link import MavrosLink, RosNode

        name = f"/openconvoy_vehicle_{a.vehicle_id}"

        def node() -> RosNode:
            if a.ros == 2:
                from openconvoy.bridge.ros.ros2 import Ros2Node

                return Ros2Node(name)
            from openconvoy.bridge.ros.ros1 import Ros1Node

            return Ros1Node(name)

        return MavrosLink(
            node,
            a.mavros_ns,
            origin,
            a.vehicle_id,
            autopilot=a.autopilot,
            on_status=status,
            length_m=preset.length_m,
            width_m=preset.width_m,
        )
    from openconvoy.bridge.mavlink.link import MavlinkLink

    if not a.mavlink:
        raise ConfigError("--mavlink URL is required with --link mavlink")
    return MavlinkLink(
        a.mavlink,
        origin,
        a.baud,
        vehicle_id=a.vehicle_id,
        telemetry_hz=a.telemetry_hz or min(max(rate, 10.0), 50.0),
        length_m=preset.length_m,
        width_m=preset.width_m,
        on_status=status,
    )


def _leader_driver(a: DeployArgs, spec: str, presets: list[Any]) -> tuple[Any, Origin | None]:
    """The leader's scenario or track driver and the track's own origin (None, None for a
    follower or a passive leader; origin None for a scenario, which uses the convoy's)."""
    if a.vehicle_id != 0 or a.passive:
        return None, None
    from openconvoy.envs.scenarios import make_scenario

    leader = make_scenario(spec, presets=presets)
    # A track has its own frame, reached through lat/lon.
    return leader, (leader.origin if spec.startswith("track-file:") else None)


def _v2v_config(a: DeployArgs, convoy: ConvoyConfig) -> Any:
    """The V2V link's ``LinkConfig``: the convoy file's ``[v2v]`` on ``--iface``, its
    transport overridden by ``--v2v`` (``ConfigError`` for a bad ROS 2 topic name)."""
    from dataclasses import replace

    from openconvoy.comms.v2v import LinkConfig

    config = LinkConfig.from_v2v(convoy.v2v, a.iface)
    return replace(config, transport=a.v2v) if a.v2v else config


def _make_v2v(
    a: DeployArgs,
    convoy: ConvoyConfig,
    config: Any,
    origin: Origin,
    auth: Any,
    bag: Any = None,
) -> Any:
    """The vehicle's V2V endpoint on ``config`` (its socket or DDS topic open), with the
    emulated loss of ``--per``; with a ``bag``, every datagram sent and received is
    recorded in it too."""
    import numpy as np

    from openconvoy.comms.loss import LossConfig
    from openconvoy.comms.tempids import TempIds
    from openconvoy.comms.v2v import V2V, open_transport

    temp_ids = TempIds(convoy.name, convoy.n_vehicles, dict(enumerate(convoy.v2v.temp_ids)) or None)
    loss = LossConfig(per=a.per) if a.per > 0 else None
    transport = None
    if bag is not None:
        from openconvoy.bridge.ros.bagtap import BagTap

        socket_ = open_transport(config, a.vehicle_id, convoy.n_vehicles)
        transport = BagTap(socket_, bag, a.vehicle_id, time.time)
    return V2V(
        config,
        temp_ids,
        origin,
        a.vehicle_id,
        loss=loss,
        drop_at=a.drop_at,
        rng=np.random.default_rng(a.seed + 7919 * a.vehicle_id),
        transport=transport,
        auth=auth,
    )


def _may_sign_completion(auth: Any) -> bool:
    from openconvoy.comms.security.certs import PSID_COMPLETE

    return PSID_COMPLETE in auth.credentials.certificate.psids


def unauthenticated_warning(vehicle_id: int, convoy_path: str) -> str:
    """The one line a deploy prints at every start with ``[v2v] auth = "off"``."""
    return (
        f'vehicle {vehicle_id}: WARNING: V2V is unauthenticated ([v2v] auth = "off" in '
        f"{convoy_path}): any station on the link can speak for any vehicle of this convoy"
    )


def vehicle_authenticator(convoy: ConvoyConfig, vehicle_id: int, convoy_path: str = "") -> Any:
    """The vehicle's ``Authenticator``, or None only with ``[v2v] auth = "off"``.

    V2V fails closed: without keys (no convoy authority in the keys directory), and
    without ``auth = "off"`` written in the convoy file, this is a one-line
    ``KeyFileError`` (exit 2) saying both ways out; so are missing, unprotected or
    mismatched key files (``security.keystore``)."""
    if not convoy.v2v.auth_required:
        return None
    from openconvoy.comms.security.auth import Authenticator
    from openconvoy.comms.security.keystore import KeyFileError, has_keys, load_vehicle

    keys = convoy.v2v.keys
    where = convoy_path or "the convoy file"
    if not has_keys(keys):
        raise KeyFileError(
            f"V2V authentication is required and {keys} holds no convoy keys: run "
            f"`openconvoy keys init --convoy {where}` and `openconvoy keys issue --convoy "
            f'{where} --vehicle-id N` for each vehicle, or write [v2v] auth = "off" in '
            f"{where} to run unauthenticated"
        )
    creds = load_vehicle(keys, vehicle_id, time.time())
    return Authenticator(creds, window_s=convoy.v2v.replay_window_s)


class SignalGate:
    """SIGINT/SIGTERM from the moment ``deploy`` starts: remembered while the runner is
    being built (imports, sockets), then passed on to it (``DeployRunner.request_stop``):
    a signal at any time ends the deploy with its line and exit 0 (D66)."""

    def __init__(self) -> None:
        self.name = ""
        self.runner: DeployRunner | None = None
        self._previous: dict[signal.Signals, Any] = {}

    def install(self) -> SignalGate:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.name = self.name or signal.Signals(signum).name
        if self.runner is not None:
            self.runner.request_stop(signal.Signals(signum).name)

    def attach(self, runner: DeployRunner) -> None:
        """From now on signals go to ``runner`` (one that came already, too)."""
        self.runner = runner
        if self.name:
            runner.request_stop(self.name)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()


def run_deploy(a: DeployArgs, gate: SignalGate | None = None) -> int:
    """Build, pass signals on, run; the exit status (0 after a clean stop)."""
    own = gate is None
    gate = gate or SignalGate().install()
    try:
        if gate.name:
            print(f"vehicle {a.vehicle_id}: stopped before starting ({gate.name})", file=sys.stderr)
            return 0
        runner = build_runner(a)
        gate.attach(runner)
        result = runner.run()
    finally:
        if own:
            gate.restore()
    summary = (
        f"vehicle {a.vehicle_id}: {result.reason}; {result.ticks} ticks, "
        f"{result.overruns} overruns, {result.policy_errors} policy errors"
    )
    written = runner.runlog.recorder.written
    if written is not None:  # only a log that was created (not one never opened)
        summary += f"; log in {written}"
    elif a.log:
        summary += "; no log written (the run ended before it began)"
    print(summary, file=sys.stderr, flush=True)
    return result.exit_code


def deploy_from_namespace(args: argparse.Namespace) -> int:
    """The CLI handler: argparse namespace -> ``run_deploy``; signals are caught from
    here on, before the runner's modules are imported."""
    gate = SignalGate().install()
    try:
        fields = DeployArgs.__dataclass_fields__
        a = DeployArgs(**{k: v for k, v in vars(args).items() if k in fields})
        return run_deploy(a, gate)
    finally:
        gate.restore()


def abort_from_namespace(args: argparse.Namespace) -> int:
    """``openconvoy abort``: the convoy-wide stop on ``--iface`` (IPv6 group, and the IPv4
    compatibility group when the convoy speaks it or ``--compat`` is given; the convoy's
    ROS 2 topic too when its V2V goes over ROS 2)."""
    from openconvoy.comms.v2v import send_abort

    kwargs: dict[str, Any] = {}
    compat = bool(args.compat)
    required = False
    keys_dir: Path | None = None
    if args.convoy:
        from openconvoy.convoy import load_convoy

        v = load_convoy(args.convoy).v2v
        kwargs.update(group=v.group, port=v.port, hop_limit=v.hop_limit)
        if v.transport == "ros2":
            kwargs.update(ros2=(v.ros2_topic, v.ros2_domain))
        compat = compat or v.compat
        required, keys_dir = v.auth_required, Path(v.keys)
    key = getattr(args, "key", None)
    auth = None
    if key:
        auth = abort_authenticator(key, keys_dir)
        compat = False
    elif required:
        raise ConfigError(
            f"this convoy only obeys signed aborts: give --key (e.g. {keys_dir}/authority.key)"
        )
    n = send_abort(
        args.iface, compat_enabled=compat, now=None, repeat=args.repeat, auth=auth, **kwargs
    )
    signed = f", signed by {auth.credentials.certificate.name}" if auth is not None else ""
    print(f"abort sent on {args.iface} ({n} datagrams{signed})", file=sys.stderr)
    return 0


def abort_authenticator(key_path: str, keys_dir: Path | None) -> Any:
    """An ``Authenticator`` signing with ``key_path`` (its certificate beside it), trusting
    the authority of ``keys_dir`` (default: the key's own directory)."""
    from openconvoy.comms.security.auth import Authenticator
    from openconvoy.comms.security.keystore import signer_of_key

    return Authenticator(signer_of_key(key_path, keys_dir, time.time()))
