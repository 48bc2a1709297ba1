"""The MAVLink vehicle link: connection, modes, commands, setpoints, telemetry, watch."""
