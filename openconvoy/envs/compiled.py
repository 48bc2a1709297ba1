"""ConvoyEnv's compiled tick: one convoy stepped by ``VectorConvoyEnv`` (B = 1).

``ConvoyEnv`` steps through this when numba is installed (the ``batched`` extra) and its
configuration is one the batched kernels compile (a path scenario, built-in σ and τ,
the plant the members know, no rendering): the same spaces, observations, rewards,
terminations, infos and safety events as the Python path (``envs.world``, what vehicles
run), plant states within float rounding (``tests/envs/test_compiled.py``). The Python
path stays the reference; ``backend="python"`` or ``OPENCONVOY_ENV_BACKEND=python``
selects it, and it is what a caller gets who needs the world's objects (``sim``,
``members``, ``channel``, log rows).

Only what the API returns is built per tick: one compiled call of the fused tick
(``VectorConvoyEnv.step_fused``) writes into arrays made once (actions, rewards,
terminations, info rows), which become the per-agent dicts as Python numbers (two
``tolist()``s); nothing is computed for the leader's observation or infos. Observations
get a new array every tick and the dicts hold views of its rows: what a caller keeps from
one tick no later tick writes.
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


INFO_FLOAT_ROWS = (
    "gap_m",
    "desired_gap_m",
    "platooning_error_m",
    "spacing_error_m",
    "speed_mps",
    "accel_mps2",
    "cmd_speed_mps",
    "cmd_heading_change_rad",
    "pred_msg_age_s",
)
"""The float rows of the batched info arrays (``vector.measures.FLOAT_KEYS``), in the
order ``agent_infos`` unpacks them; NaN where ``ConvoyEnv`` has None."""
INFO_INT_ROWS = (
    "mode", "msgs_sent", "msgs_received", "msgs_kept", "msgs_lost", "policy_errors",
    "msgs_offered",
)  # fmt: skip
"""The integer rows (``vector.measures.INT_KEYS``), likewise; ``mode`` a code of
``vector.env.MODES``. ``msgs_offered`` is the batched env's own (``ConvoyEnv``'s infos do
not have it: ``agent_infos`` reads past it)."""

F32_SQUARE_BOUND = 1e76
"""Actions whose squares sum below this are finite and within float32's range (about
3.4e38, squared 1.2e77): the kernels take them as they are."""

Infos = dict[str, dict[str, Any]]
Step = tuple[dict[str, np.ndarray], dict[str, float], dict[str, bool], dict[str, bool], Infos, bool]


def agent_infos(
    agents: Sequence[str],
    t: float,
    leader_speed: float,
    floats: Sequence[Sequence[float]],
    ints: Sequence[Sequence[int]],
    collided: Sequence[bool],
    modes: Sequence[str],
) -> Infos:
    """``ConvoyEnv``'s per-agent infos (``INFO_KEYS``, in order) of one tick: ``t`` (s),
    the leader's speed (m/s), and per follower its ``INFO_FLOAT_ROWS`` values (SI, NaN
    for None), ``INFO_INT_ROWS`` values and collision flag; ``modes``: names by code.
    Fresh dicts of Python numbers every call (a caller may keep them)."""
    return {
        a: {
            "t_s": t,
            "gap_m": g,
            "desired_gap_m": None if dg != dg else dg,
            "platooning_error_m": None if pe != pe else pe,
            "spacing_error_m": None if se != se else se,
            "speed_mps": v,
            "accel_mps2": acc,
            "leader_speed_mps": leader_speed,
            "cmd_speed_mps": None if cv != cv else cv,
            "cmd_heading_change_rad": None if ch != ch else ch,
            "mode": modes[m],
            "collision": c,
            "msgs_sent": s,
            "msgs_received": r,
            "msgs_kept": k,
            "msgs_lost": lo,
            "pred_msg_age_s": None if age != age else age,
            "policy_errors": e,
        }
        for a, (g, dg, pe, se, v, acc, cv, ch, age), (m, s, r, k, lo, e, _offered), c in zip(
            agents, floats, ints, collided
        )
    }


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
        from openconvoy.envs.vector.measures import FLOAT_KEYS, INT_KEYS, info_arrays
        from openconvoy.envs.vector.plant import SPEED

        if (FLOAT_KEYS, INT_KEYS) != (INFO_FLOAT_ROWS, INFO_INT_ROWS):  # pragma: no cover
            raise ConfigError("envs.compiled: the batched info rows changed order; update it")
        self.vec = vec = VectorConvoyEnv(
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
            threads=1,
            link_counters="all",  # ConvoyEnv's counters: every ordered pair
        )
        self.modes = MODES
        self.n_followers = F = vec.n_vehicles - 1
        self._low = vec.action_low
        self._high = vec.action_high
        # The reason of each follower's first refused action this episode, as the Python
        # path words it (the kernels record a NaN action only).
        self._refusals: dict[int, str] = {}
        # The tick's arrays, reused: what the API returns of them is copied out (Python
        # numbers); only the observations are new every tick (the dicts hold views).
        self._act = np.zeros((1, F, 2), dtype=np.float32)
        self._obs_shape = (1, F, vec.layout.size)
        self._rewards = np.empty((1, F))
        self._terminated = np.empty(1, dtype=bool)
        self._truncated = np.empty(1, dtype=bool)
        self._filled = filled = info_arrays(1, F)
        self._floats, self._ints = filled[0][:, 0, :].T, filled[1][:, 0, :].T  # (F, rows)
        # Views of the env's arrays, which it updates in place: read, never handed out.
        self._t, self._speeds, self._collided = vec.t, vec.own[SPEED], vec.collided[0]

    def reset(self, seed: int | None, agents: Sequence[str]) -> tuple[dict[str, np.ndarray], Infos]:
        """Start an episode (``ConvoyEnv.reset``'s seeding): ``agents``' observations and
        infos."""
        self._refusals = {}
        obs, info = self.vec.reset(seed=seed)
        return dict(zip(agents, obs[0])), self._infos_of(info, agents)

    def step(self, ordered: Sequence[Any], agents: Sequence[str]) -> Step:
        """One tick with follower i's action at ``ordered[i - 1]`` (checked already):
        ``ConvoyEnv.step``'s dicts for ``agents`` (every follower), and whether the
        episode ended."""
        try:
            x = np.array(ordered, dtype=np.float64)
        except (TypeError, ValueError):  # a PolicyFailure among them
            x = None
        act = self._act
        if x is not None and np.vdot(x, x) < F32_SQUARE_BOUND:  # (NaN compares False)
            act[0] = x
        else:
            act[0] = self._refused(ordered)
        vec, rewards, term, trunc = self.vec, self._rewards, self._terminated, self._truncated
        obs = np.empty(self._obs_shape, dtype=np.float32)
        if vec.step_fused(act, obs, rewards, term, trunc, self._filled):
            infos = agent_infos(
                agents,
                self._t.item(0),
                self._speeds.item(0),  # the leader's
                self._floats.tolist(),
                self._ints.tolist(),
                self._collided.tolist(),
                self.modes,
            )
        else:  # a configuration the kernels step stage by stage
            obs, rewards, term, trunc, info = vec.step(act)
            infos = self._infos_of(info, agents)
        done, cut = term.item(), trunc.item()
        return (
            dict(zip(agents, obs[0])),
            dict(zip(agents, rewards[0].tolist())),
            dict.fromkeys(agents, done),
            dict.fromkeys(agents, cut),
            infos,
            done or cut,
        )

    def _infos_of(self, info: dict[str, Any], agents: Sequence[str]) -> Infos:
        """``agent_infos`` of the batched env's ``info`` arrays (``reset``, staged steps)."""
        if not agents:
            return {}
        rows = lambda keys: np.stack([info[k][0] for k in keys]).T.tolist()  # noqa: E731
        return agent_infos(
            agents,
            info["t_s"].item(),
            info["leader_speed_mps"].item(),
            rows(INFO_FLOAT_ROWS),
            rows(INFO_INT_ROWS),
            info["collision"][0].tolist(),
            self.modes,
        )

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

    def delivery_ratio(self) -> float:
        """Delivered / (delivered + lost) over all links so far (NaN before any)."""
        ch = self.vec.channel
        d = int(ch.delivered_to.sum())
        total = d + int(ch.lost_to.sum())
        return d / total if total else float("nan")
