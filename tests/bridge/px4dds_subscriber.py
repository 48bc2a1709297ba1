"""A plain Cyclone DDS subscriber of PX4's ``/fmu/in/trajectory_setpoint`` and
``/fmu/in/offboard_control_mode``, as any px4_msgs user would write one: its own type
definitions (px4_msgs' fields, ROS 2's type names), Cyclone configured only by
CYCLONEDDS_URI. Nothing of OpenConvoy is imported.

Usage: python px4dds_subscriber.py NAMESPACE SECONDS; prints one JSON line per sample, then
"done"; prints "ready" once its readers exist.
"""

import json
import sys
import time
from dataclasses import dataclass

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic


@dataclass
class TrajectorySetpoint(IdlStruct, typename="px4_msgs::msg::dds_::TrajectorySetpoint_"):
    timestamp: t.uint64
    position: t.array[t.float32, 3]
    velocity: t.array[t.float32, 3]
    acceleration: t.array[t.float32, 3]
    jerk: t.array[t.float32, 3]
    yaw: t.float32
    yawspeed: t.float32


@dataclass
class OffboardControlMode(IdlStruct, typename="px4_msgs::msg::dds_::OffboardControlMode_"):
    timestamp: t.uint64
    position: bool
    velocity: bool
    acceleration: bool
    attitude: bool
    body_rate: bool
    thrust_and_torque: bool
    direct_actuator: bool


def main() -> None:
    ns, seconds = sys.argv[1], float(sys.argv[2])
    dp = DomainParticipant(0)
    qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(100))
    sp = DataReader(
        dp, Topic(dp, f"rt/{ns}/fmu/in/trajectory_setpoint", TrajectorySetpoint), qos=qos
    )
    ocm = DataReader(
        dp, Topic(dp, f"rt/{ns}/fmu/in/offboard_control_mode", OffboardControlMode), qos=qos
    )
    print("ready", flush=True)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for s in sp.take(N=100):
            print(
                json.dumps(
                    {
                        "topic": "trajectory_setpoint",
                        "velocity": list(s.velocity),
                        "position": list(s.position),
                        "yaw": s.yaw,
                        "t": time.monotonic(),
                    }
                ),
                flush=True,
            )
        for s in ocm.take(N=100):
            print(
                json.dumps(
                    {
                        "topic": "offboard_control_mode",
                        "velocity": s.velocity,
                        "position": s.position,
                        "t": time.monotonic(),
                    }
                ),
                flush=True,
            )
        time.sleep(0.005)
    print("done", flush=True)


if __name__ == "__main__":
    main()
