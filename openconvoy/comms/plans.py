"""The plan message: a vehicle's speed forecast (``core.plans.Plan``) on the wire.

J2735's BSM has no field for a plan (Part II's ``PathPrediction`` is a radius of curvature
and a confidence), so the plan travels as its own message beside the BSM, sent at the same
trigger. SAE J2945/6 (cooperative adaptive cruise control and platooning) carries what a
plan needs — an acceleration forecast and the actuator time constant — but its ASN.1 may
not be redistributed, so this is a compact binary message of our own with that content,
signed like the BSM: an IEEE 1609.2 SPDU under ``PSID_PLAN`` (``security.certs``: from the
4-octet private range, as the abort's PSID; a foreign 1609.2 stack drops a PSID it does not
serve, and the datagram does not start with a J2735 frame's ``00 14``, so a J2735-only
listener skips it too).

Layout (big-endian), 22 + 2·n octets::

    "OCPL"  magic                       4
    version (1)                         1
    temp_id (the sender's J2735 id)     4
    t0: time of validity, ms since the Unix epoch (shared clock)   8 (uint64)
    step (ms)                           2 (uint16, > 0)
    tau (ms): actuator time constant    2 (uint16)
    n: forecast points                  1 (1 .. core.plans.MAX_PLAN_POINTS)
    n speeds, units of 0.02 m/s         2 each (uint16, as J2735's Speed)
"""

from __future__ import annotations

import math
import struct

from openconvoy.core.plans import MAX_PLAN_POINTS, Plan

PLAN_MAGIC = b"OCPL"
PLAN_VERSION = 1
SPEED_UNIT_MPS = 0.02
_HEAD = struct.Struct(">4sB4sQHHB")


class PlanDecodeError(ValueError):
    """Bytes that are not a plan message (network input: counted and dropped)."""


def encode_plan(plan: Plan, temp_id: bytes) -> bytes:
    """``plan`` as a plan message from the vehicle whose J2735 id is ``temp_id``."""
    if len(temp_id) != 4:
        raise ValueError(f"temp_id must be 4 octets, got {len(temp_id)}")
    if not plan.valid():
        raise ValueError(f"not a valid plan: {plan}")
    speeds = [min(max(round(v / SPEED_UNIT_MPS), 0), 0xFFFF) for v in plan.speeds]
    head = _HEAD.pack(
        PLAN_MAGIC,
        PLAN_VERSION,
        temp_id,
        max(0, round(plan.t0 * 1000.0)),
        min(max(round(plan.step_s * 1000.0), 1), 0xFFFF),
        min(max(round(plan.tau_s * 1000.0), 0), 0xFFFF),
        len(speeds),
    )
    return head + struct.pack(f">{len(speeds)}H", *speeds)


def peek_plan_id(data: bytes) -> bytes | None:
    """The sender's temp id of a plan message, without decoding the rest (None: not one)."""
    if len(data) < _HEAD.size or data[:4] != PLAN_MAGIC:
        return None
    return bytes(data[5:9])


def decode_plan(data: bytes, vehicle_id: int) -> tuple[bytes, Plan]:
    """``(temp_id, plan)`` of a plan message whose sender is convoy vehicle ``vehicle_id``
    (the caller maps the id); ``PlanDecodeError`` for anything else."""
    if len(data) < _HEAD.size:
        raise PlanDecodeError(f"plan message too short ({len(data)} octets)")
    magic, version, temp_id, t0_ms, step_ms, tau_ms, n = _HEAD.unpack_from(data)
    if magic != PLAN_MAGIC:
        raise PlanDecodeError("not a plan message (magic)")
    if version != PLAN_VERSION:
        raise PlanDecodeError(f"plan message version {version}, expected {PLAN_VERSION}")
    if not 1 <= n <= MAX_PLAN_POINTS:
        raise PlanDecodeError(f"plan message with {n} points (1..{MAX_PLAN_POINTS})")
    if step_ms == 0:
        raise PlanDecodeError("plan message with a zero step")
    if len(data) != _HEAD.size + 2 * n:
        raise PlanDecodeError(
            f"plan message of {len(data)} octets, {_HEAD.size + 2 * n} expected for {n} points"
        )
    speeds = struct.unpack_from(f">{n}H", data, _HEAD.size)
    plan = Plan(
        vehicle_id,
        t0_ms / 1000.0,
        step_ms / 1000.0,
        tuple(s * SPEED_UNIT_MPS for s in speeds),
        tau_ms / 1000.0,
    )
    if not plan.valid() or not math.isfinite(plan.t0):
        raise PlanDecodeError("plan message with invalid values")
    return bytes(temp_id), plan
