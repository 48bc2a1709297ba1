"""Test helpers shipped as library code (as PettingZoo ships ``pettingzoo.test``).

One set of fakes for the deploy runner's seams and the helpers that hold two paths to the
same numbers, for OpenConvoy's own tests and for yours (a controller, a link, a plug-in):

- ``clock``: ``FakeClock``, monotonic time that moves only when slept on.
- ``links``: ``VehicleLink`` fakes: ``FakeLink`` (an ideal autopilot integrating the
  setpoints), ``ScriptedLink`` (takeovers, frozen telemetry, a rangefinder, finite
  braking), ``ReplayLink`` (telemetry exactly as set), ``RecordingLink`` (a real link,
  recording the setpoints that went out).
- ``v2v``: ``ReplayV2V``, a V2V endpoint delivering exactly what the test puts in.
- ``policies``: ``FixedPolicy``, the same action every tick.
- ``waiting``: free localhost ports, polling until something holds.
- ``parity``: deep equality (NaNs equal, dtypes checked) and directory trees compared
  file by file.

Nothing here needs torch or numba; the fakes need only ``core``, ``comms`` and ``bridge``.
"""

from __future__ import annotations

from openconvoy.testing.clock import WALL0, FakeClock
from openconvoy.testing.links import FakeLink, RecordingLink, ReplayLink, ScriptedLink
from openconvoy.testing.parity import same, tree_files
from openconvoy.testing.policies import FixedPolicy
from openconvoy.testing.v2v import Heard, ReplayV2V
from openconvoy.testing.waiting import drive_on_heading, free_port, run_for, wait_for, wait_until

__all__ = [
    "WALL0",
    "FakeClock",
    "FakeLink",
    "FixedPolicy",
    "Heard",
    "RecordingLink",
    "ReplayLink",
    "ReplayV2V",
    "ScriptedLink",
    "free_port",
    "run_for",
    "same",
    "tree_files",
    "drive_on_heading",
    "wait_for",
    "wait_until",
]
