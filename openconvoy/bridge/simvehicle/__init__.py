"""Simulated ArduPilot and PX4 autopilots (firmware models checked against recordings)."""
