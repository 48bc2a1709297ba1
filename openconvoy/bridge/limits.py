"""Bounds of a deploy's settings, shared by the CLI's flag parsing and ``RunnerOptions``
(light: the CLI imports it before any command runs)."""

MIN_RATE_HZ = 5.0
"""The lowest control rate (Hz). Below it a deploy cannot keep its autopilot in the guided
mode nor react in time: PX4 leaves OFFBOARD after ``COM_OF_LOSS_T`` 1 s without a setpoint
and arming needs a stream above 2 Hz (shared/AUTOPILOTS.md); ArduPilot stops 3 s after the
last setpoint; the link watchdog declares telemetry lost after 0.5 s; and the staleness rules
count message ages in ticks of the 20 Hz default. (D59: ``--rate 0.05`` armed, then ticked
once every 20 s.)"""
