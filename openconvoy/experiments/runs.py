"""One simulated run: scenario + policy + link, seeded, written as a DESIGN.md log.

``run_sim`` is what ``openconvoy sim`` and every sweep run call. Each follower gets its
own copy of the policy (controllers keep state); the env's members get the policy's
member configuration, so topology, trigger, spacing and ladder are the policy's. The
vehicles start at the running policy's own desired gaps (DESIGN.md: scenarios start at the
desired gaps), so a CACC preset is not measured on closing a 15 m platooning gap.

The log gets one extra column after DESIGN.md's, ``length_m`` (the vehicle's length),
so ``report`` can count collisions from the log alone.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from openconvoy.comms.geodesy import Origin
from openconvoy.comms.loss import LossConfig
from openconvoy.core import metrics as mt
from openconvoy.core.config import Range, child, from_dict, to_dict
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import check_auth, fault_specs
from openconvoy.core.policy import ActGuard
from openconvoy.logs import COLUMNS, Log, LogWriter, read_log

EXTRA_COLUMNS: tuple[str, ...] = ("length_m",)
SCHEDSTAT = "/proc/thread-self/schedstat"
"""Linux's per-thread scheduler statistics: its second field is the time (ns) the thread
has waited on a run queue for a core."""


class UnloadedClock:
    """Seconds of ``time.perf_counter`` less the time this thread has waited for a core
    (``SCHEDSTAT``; plain ``perf_counter`` where the kernel does not say): what an ``act``
    would take on an idle machine, sleeps and I/O included. A simulated run times its
    policies with it, so the same run gives the same result on a loaded machine (an MPC
    solve once overran the 50 ms period three times in a row at load 17 on 2 cores and
    stopped its follower); a vehicle times them by the wall clock, which is what its
    control loop lives by. Read from the thread that created it."""

    def __init__(self, path: str = SCHEDSTAT) -> None:
        try:
            self._fd: int | None = os.open(path, os.O_RDONLY)
            self._waited_s()
        except (OSError, ValueError, IndexError):
            self._fd = None

    def _waited_s(self) -> float:
        assert self._fd is not None
        return int(os.pread(self._fd, 64, 0).split()[1]) * 1e-9

    def __call__(self) -> float:
        now = time.perf_counter()
        return now if self._fd is None else now - self._waited_s()

    def close(self) -> None:
        """Close the statistics file (idempotent)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


EVENTS_FILE = "events.json"
"""A run's events (``run_events``), written only when it had any."""


@dataclass(frozen=True)
class ConvoySection:
    """The convoy of a run or experiment (``[convoy]``): vehicle presets (leader first),
    size, ranging and GPS noise.

    Attributes:
        vehicles: vehicle presets (names or preset ``.toml`` files), leader first; empty =
            the scenario's.
        n_followers: convoy size; None = the scenario's (or ``vehicles``').
        ranging: give every follower without one a ranging sensor (range and range rate
            to the vehicle ahead, ``RangingSensor``'s noise), used by the degraded mode of
            the staleness ladder.
        ranging_max_range_m: that sensor's range, metres (20 m suits the small cars; a
            car's radar sees 150 m and more).
        gps_noise_m: standard deviation of the position noise members see, metres.
        plants: the vehicles as they drive (presets fitted by ``fit-plant --convoy``),
            leader first, when they differ from ``vehicles`` (what the members, safety
            rules and scenario know); empty = ``vehicles``.
    """

    vehicles: tuple[str, ...] = ()
    n_followers: Annotated[int, Range(1, 1000)] | None = None
    ranging: bool = False
    ranging_max_range_m: Annotated[float, Range(0.0, 10000.0, lo_open=True)] = 20.0
    gps_noise_m: Annotated[float, Range(0.0, 1000.0)] = 0.0
    plants: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "vehicles", tuple(self.vehicles))
        object.__setattr__(self, "plants", tuple(self.plants))
        if self.gps_noise_m < 0:
            raise ConfigError(f"gps_noise_m must be >= 0, got {self.gps_noise_m}")


@dataclass(frozen=True)
class LossSection:
    """The link model of a run or experiment (``[loss]``), all but the PER (which a run
    sets and a sweep varies); times in seconds.

    Attributes:
        model: ``bernoulli`` or ``gilbert-elliott``.
        mean_burst_s: mean loss burst of the Gilbert–Elliott model.
        latency_s, jitter_s: delivery delay and its uniform jitter.
        latency_samples_s: or a delay distribution (quantiles) in place of the jitter, as
            ``fit-plant`` fits from a vehicle run's message ages (``comms.loss.Latency``).
        stamp_error_s, stamp_drift: the senders' clock error, s and s/s (``Latency``).
        link_latency_s: per link ``[sender, receiver, quantile s, ...]`` (``LossConfig``).
        staleness_s: per sender, how much older its messages are stamped (``LossConfig``).
        lost_s, lost_window_s: per link, a vehicle run's dropped broadcasts, replayed
            (``LossConfig``).
    """

    model: str = "bernoulli"
    mean_burst_s: Annotated[float, Range(0.0, 3600.0, lo_open=True)] = 1.0
    latency_s: Annotated[float, Range(0.0, 60.0)] = 0.0
    jitter_s: Annotated[float, Range(0.0, 60.0)] = 0.0
    latency_samples_s: tuple[float, ...] = ()
    stamp_error_s: Annotated[float, Range(-60.0, 60.0)] = 0.0
    stamp_drift: Annotated[float, Range(-0.1, 0.1)] = 0.0
    link_latency_s: tuple[tuple[float, ...], ...] = ()
    staleness_s: tuple[float, ...] = ()
    lost_s: tuple[tuple[float, ...], ...] = ()
    lost_window_s: Annotated[float, Range(0.0, 1.0, lo_open=True)] = 0.05

    def __post_init__(self) -> None:
        object.__setattr__(self, "latency_samples_s", tuple(self.latency_samples_s))
        object.__setattr__(self, "staleness_s", tuple(self.staleness_s))
        object.__setattr__(self, "lost_s", tuple(tuple(e) for e in self.lost_s))
        if self.model not in ("bernoulli", "gilbert-elliott"):
            raise ConfigError(
                f"unknown loss model {self.model!r} (expected 'bernoulli' or 'gilbert-elliott')"
            )
        self.at(0.0)  # the channel's own checks (latency samples)
        if self.mean_burst_s <= 0:
            raise ConfigError(f"mean_burst_s must be positive, got {self.mean_burst_s}")

    def at(self, per: float) -> LossConfig:
        """The channel's ``LossConfig`` for this section at packet error rate ``per``."""
        return LossConfig(
            per=per,
            model=self.model,
            mean_burst_s=self.mean_burst_s,
            latency_s=self.latency_s,
            jitter_s=self.jitter_s,
            latency_samples_s=self.latency_samples_s,
            stamp_error_s=self.stamp_error_s,
            stamp_drift=self.stamp_drift,
            link_latency_s=self.link_latency_s,
            staleness_s=self.staleness_s,
            lost_s=self.lost_s,
            lost_window_s=self.lost_window_s,
        )


# Keys a run config had before it nested [convoy] and [loss]: where each lives now.
_MOVED_KEYS: dict[str, str] = {
    "loss_model": "loss.model",
    "mean_burst_s": "loss.mean_burst_s",
    "latency_s": "loss.latency_s",
    "jitter_s": "loss.jitter_s",
    "n_followers": "convoy.n_followers",
    "vehicles": "convoy.vehicles",
    "ranging": "convoy.ranging",
    "ranging_max_range_m": "convoy.ranging_max_range_m",
    "gps_noise_m": "convoy.gps_noise_m",
}


@dataclass(frozen=True)
class RunConfig:
    """Everything that determines one simulated run (SI units): one point of an
    experiment, with the experiment file's ``[convoy]`` and ``[loss]`` tables nested.

    Attributes:
        scenario: scenario spec (``paper``, ``track``, ``emergency-braking``,
            ``track-file:PATH``, ``highway-*``).
        policy: policy spec (preset name, optionally ``+ladder``; ``.toml``, ``.zip``,
            ``.npz`` file).
        per: packet error rate of every link, 0..1.
        seed: seeds the channel, GPS noise and ranging noise.
        duration_s: run length; None = the scenario's.
        convoy: the vehicles, their number, ranging and GPS noise (``ConvoySection``).
        loss: the link model but its PER (``LossSection``).
        origin: convoy origin (latitude deg, longitude deg, altitude m); None = scenario's.
        start_at_policy_gap: place vehicles at the policy's desired gaps (else the
            scenario's).
        faults: injected faults, ``KIND:VEHICLE@T_S`` specs (``core.faults``).
        auth: ``"required"`` (members reject forged messages, ``envs.forgery``) or ``"off"``.
    """

    scenario: str = "paper"
    policy: str = "paper"
    per: Annotated[float, Range(0.0, 1.0)] = 0.0
    seed: Annotated[int, Range(0, 4294967295)] = 0
    duration_s: Annotated[float, Range(0.0, 604800.0, lo_open=True)] | None = None
    convoy: ConvoySection = field(default_factory=ConvoySection)
    loss: LossSection = field(default_factory=LossSection)
    origin: (
        tuple[
            Annotated[float, Range(-90.0, 90.0)],
            Annotated[float, Range(-180.0, 180.0)],
            Annotated[float, Range(-1000.0, 10000.0)],
        ]
        | None
    ) = None
    start_at_policy_gap: bool = True
    faults: tuple[str, ...] = ()
    auth: str = "required"

    def __post_init__(self) -> None:
        object.__setattr__(self, "faults", fault_specs(self.faults))
        if self.origin is not None:
            object.__setattr__(self, "origin", tuple(float(v) for v in self.origin))
        self.loss_config  # validates the PER  # noqa: B018
        check_auth(self.auth)
        if self.duration_s is not None and self.duration_s <= 0:
            raise ConfigError(f"duration must be positive, got {self.duration_s} s")

    @property
    def loss_config(self) -> LossConfig:
        """The channel's ``LossConfig``: ``loss`` at this run's ``per``."""
        return self.loss.at(self.per)

    def to_dict(self) -> dict[str, Any]:
        return to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "run") -> RunConfig:
        """A run config from its table (``convoy`` and ``loss`` nested), strictly; a key
        of the older flat form is an error naming where it lives now."""
        for key in data:
            if key in _MOVED_KEYS:
                raise ConfigError(
                    f"{child(where, key)}: now {_MOVED_KEYS[key]} (a run nests its convoy and loss tables)"
                )
        return from_dict(cls, dict(data), where)


@dataclass
class RunResult:
    """A finished run: its config, log (columns), metrics, and wall time (s)."""

    config: RunConfig
    log: Log
    metrics: dict[str, Any]
    lengths: dict[int, float]
    wall_s: float = math.nan
    events: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    """Injected faults and emergency stops: ``{"t_s", "vehicle_id", "reason"}``."""


def build_env(config: RunConfig):
    """The ``ConvoyEnv`` and one policy per follower for ``config``: ``(env, policies)``."""
    from openconvoy.envs import ConvoyEnv
    from openconvoy.envs.scenarios import make_scenario
    from openconvoy.envs.vehicles import RangingSensor, vehicle_preset
    from openconvoy.policies import load_policy

    policy = load_policy(config.policy)
    convoy = config.convoy
    presets = [vehicle_preset(v) for v in convoy.vehicles] or None
    scenario = make_scenario(config.scenario, convoy.n_followers, presets)
    member_config = policy.member_config
    changes: dict[str, Any] = {}
    if member_config is not None and config.start_at_policy_gap:
        # The scenario places its vehicles at the desired gaps of its ``spacing``.
        changes["spacing"] = member_config.spacing
    if convoy.ranging:
        sensor = RangingSensor(max_range_m=convoy.ranging_max_range_m)
        changes["presets"] = tuple(
            p if i == 0 or p.ranging is not None else p.with_ranging(sensor)
            for i, p in enumerate(scenario.presets)
        )
    if config.origin is not None:
        changes["origin"] = Origin(*config.origin)
    if changes:
        scenario = scenario.with_changes(**changes)
    env = ConvoyEnv(
        scenario,
        member_config=member_config,
        loss=config.loss_config,
        control_rate_hz=float(policy.control_rate_hz),
        gps_noise_m=convoy.gps_noise_m,
        max_time_s=config.duration_s,
        faults=config.faults,
        auth=config.auth == "required",
        plant_presets=[vehicle_preset(v) for v in convoy.plants] or None,
        backend="python",  # its log rows and plans are the world's (what vehicles run)
    )
    policies = {a: copy.deepcopy(policy) for a in env.possible_agents}
    for i, a in enumerate(env.possible_agents, start=1):
        bind = getattr(policies[a], "bind_vehicle", None)
        if bind is not None:  # a model-based policy predicts with its vehicle's numbers
            bind(env.presets[i])
    return env, policies


def run_sim(
    config: RunConfig,
    out_dir: str | Path | None = None,
    progress: bool = False,
    bag: str | Path | None = None,
) -> RunResult:
    """Run ``config`` to the end (or a collision).

    With ``out_dir``, writes ``log.csv`` there and computes the metrics from the written
    log (what ``openconvoy report`` recomputes, to the digit); ``progress`` shows a
    progress bar on stderr when the run lasts more than a couple of seconds; ``bag``: also
    record the log rows as a ROS 2 bag directory there (``openconvoy.bag``).
    """
    import time

    from openconvoy.envs.plans import PlanRelay

    start = time.perf_counter()
    env, policies = build_env(config)
    relay = PlanRelay(env, policies)
    lengths = {i: p.length_m for i, p in enumerate(env.presets)}
    obs, _ = env.reset(seed=config.seed)
    for p in policies.values():
        p.reset(config.seed)
    writer = None
    rows: list[dict[str, Any]] = []
    if out_dir is not None:
        writer = LogWriter(
            Path(out_dir) / "log.csv",
            extra_columns=EXTRA_COLUMNS + env.LOG_EXTRA_COLUMNS,
            flush_every=500,
        )
    bag_writer = None
    if bag is not None:
        from openconvoy.bag import BagWriter

        bag_writer = BagWriter(bag, tick_s=env.dt)

    def emit(tick_rows: list[dict[str, Any]]) -> None:
        for r in tick_rows:
            r["length_m"] = lengths[r["vehicle_id"]]
            if bag_writer is not None:
                bag_writer.row(r)
            if writer is not None:
                writer.write(r)
            else:
                rows.append(r)

    bar = _progress_bar(env.max_steps, config.scenario) if progress else None
    # Each act is timed and caught as on a vehicle (``core.policy.ActGuard``): an act
    # that raises or overruns the control period is a policy error, decided in the tick.
    # Timed without the waits for a core, so a busy machine does not change a run.
    clock = UnloadedClock()
    guards = {a: ActGuard(p, env.dt, clock) for a, p in policies.items()}
    try:
        while env.agents:
            relay.before_act()
            actions = {a: guards[a](obs[a]) for a in env.agents}
            relay.after_act()
            obs, _, _, _, _ = env.step(actions)
            emit(env.log_rows())
            if bar is not None:
                bar.update(1)
        emit(env.final_log_rows())
    finally:
        clock.close()
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
        if bag_writer is not None:
            bag_writer.close()
    log = read_log(writer.path) if writer is not None else rows_to_log(rows)
    metrics = run_metrics(log, lengths)
    result = RunResult(config, log, metrics, lengths, time.perf_counter() - start)
    result.events = run_events(env)
    if out_dir is not None:
        write_json(Path(out_dir) / "metrics.json", metrics)
        if result.events:
            write_json(Path(out_dir) / EVENTS_FILE, result.events)
    return result


def run_metrics(log: Log, lengths: dict[int, float]) -> dict[str, Any]:
    """DESIGN.md's metrics of a run's log (and the traffic ones where it has traffic)."""
    metrics = mt.compute_metrics(log, lengths)
    if mt.has_traffic_columns(log):
        metrics.update(mt.traffic_metrics(log, lengths))
    return metrics


def _progress_bar(steps: int, scenario: str) -> Any:
    """A tqdm bar on stderr, shown when the run lasts more than a couple of seconds."""
    from tqdm import tqdm

    return tqdm(total=steps, unit="tick", desc=f"sim {scenario}", delay=2.0, leave=False)


def run_events(env: Any) -> list[dict[str, Any]]:
    """A finished run's events: injected faults, refused actions, emergency stops, and
    what authentication stopped (forge faults), as ``{"t_s", "vehicle_id", "reason"}``."""
    return events_of(env.safety_events, env.t, env.forged_rejected)


def events_of(
    safety_events: Sequence[tuple[float, int, str]], t_s: float, forged_rejected: Sequence[int]
) -> list[dict[str, Any]]:
    """``run_events`` of a run that ended at ``t_s`` (s) with these ``safety_events``
    (``ConvoyEnv.safety_events``) and forged messages rejected per vehicle."""
    events = [{"t_s": t, "vehicle_id": v, "reason": r} for t, v, r in safety_events]
    events += [
        {"t_s": t_s, "vehicle_id": r, "reason": f"rejected {n} forged messages"}
        for r, n in enumerate(forged_rejected)
        if n
    ]
    return events


def rows_to_log(rows: Sequence[dict[str, Any]]) -> Log:
    """Log rows (dicts) as columns, typed like ``openconvoy.logs.read_log``'s."""
    if not rows:
        return {c: np.array([]) for c in COLUMNS}
    out: Log = {}
    for name in rows[0]:
        values = [r[name] for r in rows]
        if name == "mode":
            out[name] = np.array(values, dtype=object)
        elif name in ("vehicle_id", "msgs_sent", "msgs_received", "msgs_lost"):
            out[name] = np.array(values, dtype=np.int64)
        else:
            out[name] = np.array(values, dtype=float)
    return out


def write_json(path: str | Path, data: Any) -> None:
    """JSON with NaN as null, keys in insertion order, newline-terminated."""
    Path(path).write_text(json.dumps(mt.json_safe(data), indent=2) + "\n", encoding="utf-8")


def replace(config: RunConfig, **changes: Any) -> RunConfig:
    """``config`` with some fields changed."""
    return dataclasses.replace(config, **changes)
