"""Fixtures of the bridge tests: a simulated vehicle with a link (the fakes and waits
are ``openconvoy.testing``)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.envs.vehicles import VEHICLE_PRESETS
from openconvoy.testing import free_port


@pytest.fixture
def vehicle_and_link() -> Iterator[Callable[..., tuple[SimVehicle, MavlinkLink, list[str]]]]:
    """Factory: ``make(autopilot=..., link_kwargs={...}, **config)`` -> (vehicle, link,
    status lines); the link is connected over localhost UDP with real MAVLink bytes."""
    made: list[tuple[SimVehicle, MavlinkLink]] = []

    def make(
        link_kwargs: dict[str, Any] | None = None, connect: bool = True, **config: Any
    ) -> tuple[SimVehicle, MavlinkLink, list[str]]:
        port = free_port()
        config.setdefault("ready_after_s", 0.0)
        # The link tests drive the 1/10 preset plant from a booted autopilot; the firmware
        # loops and the boot race are the conformance tests' subject.
        config.setdefault("preset", VEHICLE_PRESETS["1/10"])
        config.setdefault("init_s", 0.0)
        config.setdefault("rc_mode_switch", False)
        vehicle = SimVehicle(f"udpin:127.0.0.1:{port}", SimVehicleConfig(**config)).start()
        lines: list[str] = []
        kwargs = dict(on_status=lines.append)
        kwargs.update(link_kwargs or {})
        origin = kwargs.pop("origin", DEFAULT_HOME)
        link = MavlinkLink(f"udpout:127.0.0.1:{port}", origin, **kwargs)
        made.append((vehicle, link))
        if connect:
            link.connect(timeout_s=5.0)
        return vehicle, link, lines

    yield make
    for vehicle, link in made:
        with contextlib.suppress(Exception):
            link.close()
        vehicle.stop()
