"""A small convoy of deploy runners on simulated MAVLink vehicles, in one process.

Each car is a ``SimVehicle`` (real MAVLink bytes over localhost UDP), a ``MavlinkLink``
wrapped so the test sees every setpoint actually sent, and a ``DeployRunner`` in a thread;
V2V goes through an in-process ``LocalBus`` (multicast is exercised by the namespace tests).
"""

from __future__ import annotations

import dataclasses
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from openconvoy.bridge.localv2v import LocalBus, LocalV2V
from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.bridge.runner import DeployRunner, RunnerOptions, RunResult
from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig
from openconvoy.bridge.simvehicle.world import SimWorld
from openconvoy.comms.geodesy import Origin
from openconvoy.convoy import ConvoyConfig, SafetyConfig
from openconvoy.envs.scenarios import make_scenario
from openconvoy.envs.vehicles import RangingSensor, vehicle_preset
from openconvoy.policies import load_policy
from openconvoy.testing import RecordingLink, free_port


@dataclass
class Car:
    vehicle: SimVehicle
    link: RecordingLink
    runner: DeployRunner
    v2v: Any  # LocalV2V, or a real comms.v2v.V2V
    port: int
    thread: threading.Thread | None = None
    result: RunResult | None = None

    def start(self) -> Car:
        def run() -> None:
            self.result = self.runner.run()

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()
        return self

    def join(self, timeout: float = 10.0) -> RunResult:
        assert self.thread is not None
        self.thread.join(timeout)
        assert not self.thread.is_alive(), "runner did not end"
        assert self.result is not None
        return self.result

    def first_event(self, prefix: str) -> float:
        """Monotonic time the failsafe whose reason starts with ``prefix`` first fired."""
        for t, reason in self.runner.failsafes.events:
            if reason.startswith(prefix):
                return t
        raise AssertionError(f"no failsafe event {prefix!r}: {self.runner.failsafes.events}")


@dataclass
class Convoy:
    cars: list[Car]
    bus: LocalBus
    log_dir: Path
    convoy: ConvoyConfig
    extra: list[Any] = field(default_factory=list)

    def stop(self) -> None:
        for c in self.cars:
            c.runner.request_stop("test over")
        for c in self.cars:
            if c.thread is not None:
                c.thread.join(10.0)
        for c in self.cars:
            c.vehicle.stop()
        for v in self.extra:
            v.stop()


def make_convoy(
    tmp_path: Path,
    n: int = 2,
    policy: str = "paper",
    autopilot: str = "ardupilot",
    safety: SafetyConfig | None = None,
    options: dict[int, dict[str, Any]] | None = None,
    vehicle_config: dict[str, Any] | None = None,
    start: bool = True,
    policies: dict[int, Any] | None = None,
    tcp: bool = False,
    v2v_factory: Callable[[int, ConvoyConfig], Any] | None = None,
    ranging: dict[int, RangingSensor] | None = None,
) -> Convoy:
    """``n`` cars at the paper scenario's initial positions; started unless ``start`` is False.
    ``v2v_factory(i, convoy)`` gives car ``i`` its V2V endpoint (default: the in-process bus).
    ``ranging``: the cars whose simulated vehicle has that forward rangefinder (all cars
    then share one ``SimWorld``, so it sees the others)."""
    names = ("1/10", "1/6", "1/10", "1/6")[:n]
    convoy = ConvoyConfig(name="test", vehicles=names, safety=safety or SafetyConfig())
    origin = Origin(*convoy.origin)
    presets = [vehicle_preset(v) for v in names]
    scenario = make_scenario("paper", presets=presets)
    init = scenario.initial_state()
    bus = LocalBus()
    world = SimWorld() if ranging else None
    log_dir = tmp_path / "run"
    cars = []
    for i in range(n):
        port = free_port(socket.SOCK_STREAM if tcp else socket.SOCK_DGRAM)
        cfg = SimVehicleConfig(
            **{
                "system_id": i + 1,
                "autopilot": autopilot,
                "home": origin,
                "preset": presets[i].with_ranging(ranging[i])
                if ranging and i in ranging
                else presets[i],
                "start_x_m": float(init.x[i]),
                "start_y_m": float(init.y[i]),
                "start_heading_rad": float(init.heading[i]),
                "ready_after_s": 0.0,
                **(vehicle_config or {}),
            }
        )
        vehicle = SimVehicle(
            f"{'tcpin' if tcp else 'udpin'}:127.0.0.1:{port}", cfg, world=world
        ).start()
        link = RecordingLink(
            MavlinkLink(
                f"{'tcp' if tcp else 'udpout'}:127.0.0.1:{port}",
                origin,
                vehicle_id=i,
                length_m=presets[i].length_m,
                on_status=lambda line: None,
            )
        )
        v2v = v2v_factory(i, convoy) if v2v_factory is not None else LocalV2V(bus)
        opts = RunnerOptions(
            **{
                "vehicle_id": i,
                "status_period_s": 0.0,
                "connect_timeout_s": 5.0,
                "arm_timeout_s": 10.0,
                **(options or {}).get(i, {}),
            }
        )
        pol = (policies or {}).get(i) or load_policy(policy)
        runner = DeployRunner(
            opts,
            convoy,
            pol,
            link,
            v2v,
            leader=scenario if i == 0 else None,
            lengths=[p.length_m for p in presets],
            decels=[p.decel_max_mps2 for p in presets],
            log_dir=log_dir,
            on_status=lambda line: None,
        )
        cars.append(Car(vehicle, link, runner, v2v, port))
    c = Convoy(cars, bus, log_dir, convoy)
    if start:
        for car in cars:
            car.start()
    return c


def replace_safety(**kw: Any) -> SafetyConfig:
    return dataclasses.replace(SafetyConfig(), **kw)
