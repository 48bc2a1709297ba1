"""VehicleWatch's status texts, from real STATUSTEXT bytes as the recorded firmware sent them."""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from openconvoy.bridge.mavlink.watch import VehicleWatch

CRITICAL, INFO = 2, 6


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _statustext(severity: int, text: str, chunk_id: int = 0, seq: int = 0) -> Any:
    """A STATUSTEXT packed to bytes and parsed back, as the link receives it."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    msg = mavlink2.MAVLink_statustext_message(severity, text.encode(), chunk_id, seq)
    return mav.parse_char(msg.pack(mav))


def _watch_fed(texts: list[tuple[float, int, str, int, int]]) -> VehicleWatch:
    clock = _Clock()
    watch = VehicleWatch(clock)
    for t, severity, text, chunk_id, seq in texts:
        clock.t = t
        watch.on_text(_statustext(severity, text, chunk_id, seq))
    return watch


def test_px4s_chunked_arming_refusal_is_kept_whole() -> None:
    # shared/sitl-px4/boot_and_arm: the refusal comes in two chunks, id 1, "…firs" + "t\t".
    watch = _watch_fed(
        [
            (2.775369, CRITICAL, "Arming denied: Resolve system health failures firs", 1, 0),
            (2.775444, CRITICAL, "t\t", 1, 1),
        ]
    )
    assert [text for _, _, text in watch.texts] == [
        "Arming denied: Resolve system health failures first"
    ]
    assert watch.refusal(2.7) == "Arming denied: Resolve system health failures first"


def test_a_chunked_text_whose_end_was_lost_is_kept_as_it_came() -> None:
    head = "Arming denied: Resolve system health failures firs"
    watch = _watch_fed(
        [
            (1.0, CRITICAL, head, 3, 0),
            (1.5, CRITICAL, head, 4, 0),  # a new text; id 3's end never came
            (1.5, CRITICAL, "t", 4, 1),
            (9.0, CRITICAL, head, 5, 0),
            (10.5, CRITICAL, "t", 5, 1),  # over a second late: not this text's end
            (10.6, INFO, "Takeoff detected", 0, 0),
        ]
    )
    assert [text for _, _, text in watch.texts] == [
        head,
        head[:-4] + "first",
        head,
        "t",
        "Takeoff detected",
    ]


def test_ardupilots_refusal_names_every_failed_check() -> None:
    # shared/sitl/speed_steps at 14.16 s: the ACK, then one text per failed arming check;
    # an info text before the attempt is no reason.
    watch = _watch_fed(
        [
            (13.6, INFO, "Field Elevation Set: 0m", 0, 0),
            (14.1579, CRITICAL, "Arm: Gyros inconsistent", 0, 0),
            (14.157971, CRITICAL, "Arm: AHRS: not using configured AHRS type", 0, 0),
        ]
    )
    assert watch.refusal(13.6) == (
        "Arm: Gyros inconsistent; Arm: AHRS: not using configured AHRS type"
    )
    assert watch.refusal(14.158) == ""
    # Without warnings since, the newest text is the reason.
    assert _watch_fed([(1.0, INFO, "Flight mode change failed", 0, 0)]).refusal(0.5) == (
        "Flight mode change failed"
    )
