"""ConvoyEnv's compiled tick: one convoy stepped by ``VectorConvoyEnv`` (B = 1).

``ConvoyEnv`` steps through this when numba is installed (the ``batched`` extra) and its
configuration is one the batched kernels compile (a path scenario, built-in σ and τ,
the plant the members know, no rendering): the same spaces, observations, rewards,
terminations, infos and safety events as the Python path (``envs.world``, what vehicles
run), plant states within float rounding (``tests/envs/test_compiled.py``). The Python
path stays the reference; ``backend="python"`` or ``OPENCONVOY_ENV_BACKEND=python``
selects it, and it is what a caller gets who needs the world's objects (``sim``,
``members``, ``channel``, log rows).

Only what the API returns is built per tick: the batched step's arrays become the
per-agent dicts; nothing is computed for the leader's observation.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from openconvoy.comms.loss import LossConfig
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import Fault
from openconvoy.core.member import MemberConfig
from openconvoy.core.policy import PolicyFailure
from openconvoy.core.tick import non_finite_reason
from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.scenarios import PathScenario, Scenario

BACKENDS = ("auto", "compiled", "python")
"""``ConvoyEnv(backend=...)``: ``compiled`` (the batched kernels, an error if they cannot
run this convoy), ``python`` (``envs.world``), ``auto`` (compiled where it can)."""
BACKEND_ENV_VAR = "OPENCONVOY_ENV_BACKEND"
"""Environment variable giving the backend when ``ConvoyEnv``'s argument is None."""


def backend_choice(backend: str | None, environ: Mapping[str, str] = os.environ) -> str:
    """The backend asked for: ``backend``, else ``environ[BACKEND_ENV_VAR]``, else
    ``auto``; ``ConfigError`` naming the source for anything not in ``BACKENDS``."""
    source = "backend"
    if backend is None:
        backend, source = environ.get(BACKEND_ENV_VAR) or "auto", BACKEND_ENV_VAR
    if backend not in BACKENDS:
        raise ConfigError(f"{source} must be one of {', '.join(BACKENDS)}, got {backend!r}")
    return backend


def python_only_reason(
    scenario: Scenario, python_world: bool, plant_presets: object, render_mode: str | None
) -> str | None:
    """Why this convoy must run on the Python path (None when the kernels can run it)."""
    if not python_world:
        return "a world with more in it (traffic) is Python"
    if not isinstance(scenario, PathScenario):
        return "the compiled tick drives path scenarios only"
    if plant_presets is not None:
        return "plant_presets (a fitted plant) run on the Python path"
    if render_mode is not None:
        return "rendering runs on the Python path"
    return None


INFO_FLOATS = ("gap_m", "speed_mps", "accel_mps2")
"""Info keys that always have a value."""
INFO_OPTIONAL = (
    "desired_gap_m",
    "platooning_error_m",
    "spacing_error_m",
    "cmd_speed_mps",
    "cmd_heading_change_rad",
    "pred_msg_age_s",
)
"""Info keys that are None (NaN in the batched arrays) until they exist."""
INFO_INTS = ("msgs_sent", "msgs_received", "msgs_kept", "msgs_lost", "policy_errors")


def _column(values: np.ndarray) -> list[Any]:
    """The first convoy's values of an info key ``(1, F)`` as Python numbers, NaN as
    None."""
    return [None if v != v else v for v in values.tolist()[0]]


class CompiledConvoy:
    """One convoy on the batched kernels, shaped as ``ConvoyEnv``'s dicts.

    Arguments are ``ConvoyEnv``'s (resolved); ``ConfigError`` or ``ImportError`` when the
    kernels cannot run it (``ConvoyEnv``'s ``auto`` then takes the Python path)."""

    def __init__(
        self,
        scenario: PathScenario,
        member_config: MemberConfig,
        loss: LossConfig,
        control_rate_hz: float,
        gps_noise_m: float,
        max_time_s: float,
        reward_config: RewardConfig,
        faults: Sequence[Fault],
        gap_margin_m: float | None,
        emergency_stop: bool,
        auth: bool,
    ) -> None:
        from openconvoy.envs.vector.env import MODES, VectorConvoyEnv  # needs numba

        self.vec = VectorConvoyEnv(
            1,
            scenario,
            member_config=member_config,
            loss=loss,
            control_rate_hz=control_rate_hz,
            gps_noise_m=gps_noise_m,
            max_time_s=max_time_s,
            reward_config=reward_config,
            faults=faults,
            gap_margin_m=gap_margin_m,
            emergency_stop=emergency_stop,
            auth=auth,
            autoreset=False,
            link_counters="all",  # ConvoyEnv's counters: every ordered pair
        )
        self.modes = MODES
        self.n_followers = self.vec.n_vehicles - 1
        self._low = self.vec.action_low
        self._high = self.vec.action_high
        # The reason of each follower's first refused action this episode, as the Python
        # path words it (the kernels record a NaN action only).
        self._refusals: dict[int, str] = {}

    def reset(self, seed: int | None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode (``ConvoyEnv.reset``'s seeding); the batched obs and infos."""
        self._refusals = {}
        obs, info = self.vec.reset(seed=seed)
        return obs, info

    def step(
        self, ordered: Sequence[Any]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One tick with follower i's action at ``ordered[i - 1]`` (checked already):
        the batched (obs, rewards, terminated, truncated, infos)."""
        try:
            with np.errstate(over="ignore"):  # beyond float32: inf, then clipped below
                a = np.array(ordered, dtype=np.float32)
        except (TypeError, ValueError):  # a PolicyFailure among them
            a = None
        if a is None or not np.isfinite(a).all():  # (a float32 cast overflows to inf)
            a = self._refused(ordered)
        return self.vec.step(a.reshape(1, self.n_followers, 2))

    def _refused(self, ordered: Sequence[Any]) -> np.ndarray:
        """The actions as the kernels take them when some are refused (NaN: a stop and a
        policy error) or out of float32's range (clipped as the Python path clips)."""
        a = np.empty((len(ordered), 2), dtype=np.float32)
        for f, x in enumerate(ordered):
            i = f + 1
            if isinstance(x, PolicyFailure):
                a[f] = np.nan
                self._refusals.setdefault(i, x.reason)
                continue
            speed, change = float(x[0]), float(x[1])
            if not (math.isfinite(speed) and math.isfinite(change)):
                a[f] = (speed, change)
                self._refusals.setdefault(i, non_finite_reason(speed, change))
                continue
            a[f] = (
                min(max(speed, self._low[f, 0]), self._high[f, 0]),
                min(max(change, self._low[f, 1]), self._high[f, 1]),
            )
        return a

    def safety_events(self) -> list[tuple[float, int, str]]:
        """``ConvoyEnv.safety_events``: the kernels' events, refusals in the Python
        path's words."""
        out = self.vec.safety_events(0)
        if not self._refusals:
            return out
        return [
            (t, i, f"policy error: {self._refusals[i]}")
            if why.startswith("policy error: ") and i in self._refusals
            else (t, i, why)
            for t, i, why in out
        ]

    def infos(self, info: dict[str, Any], agents: Sequence[str]) -> dict[str, dict[str, Any]]:
        """``ConvoyEnv``'s per-agent infos (``INFO_KEYS``, in order) of the batched
        ``info`` arrays."""
        if not agents:
            return {}
        n = len(agents)
        # (``.tolist()[0]``: a list of the one convoy's row, without a view of it.)
        t = info["t_s"].tolist()[0]
        lead = info["leader_speed_mps"].tolist()[0]
        col = {k: info[k].tolist()[0] for k in (*INFO_FLOATS, *INFO_INTS)}
        opt = {k: _column(info[k]) for k in INFO_OPTIONAL}
        modes = self.modes
        mode = [modes[c] for c in info["mode"].tolist()[0]]
        collision = info["collision"].tolist()[0]
        return {
            a: {
                "t_s": t,
                "gap_m": g,
                "desired_gap_m": dg,
                "platooning_error_m": pe,
                "spacing_error_m": se,
                "speed_mps": v,
                "accel_mps2": acc,
                "leader_speed_mps": lead,
                "cmd_speed_mps": cv,
                "cmd_heading_change_rad": ch,
                "mode": m,
                "collision": c,
                "msgs_sent": s,
                "msgs_received": r,
                "msgs_kept": k,
                "msgs_lost": lo,
                "pred_msg_age_s": age,
                "policy_errors": e,
            }
            for a, g, dg, pe, se, v, acc, cv, ch, m, c, s, r, k, lo, age, e in zip(
                agents,
                col["gap_m"],
                opt["desired_gap_m"],
                opt["platooning_error_m"],
                opt["spacing_error_m"],
                col["speed_mps"],
                col["accel_mps2"],
                opt["cmd_speed_mps"],
                opt["cmd_heading_change_rad"],
                mode[:n],
                collision,
                col["msgs_sent"],
                col["msgs_received"],
                col["msgs_kept"],
                col["msgs_lost"],
                opt["pred_msg_age_s"],
                col["policy_errors"],
            )
        }

    def delivery_ratio(self) -> float:
        """Delivered / (delivered + lost) over all links so far (NaN before any)."""
        ch = self.vec.channel
        d = int(ch.delivered_to.sum())
        total = d + int(ch.lost_to.sum())
        return d / total if total else float("nan")
