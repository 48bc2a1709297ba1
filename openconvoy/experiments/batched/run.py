"""Many runs of one policy in one ``VectorConvoyEnv``: the batched path of sweeps and tuning.

``run_batch(configs)`` runs ``RunConfig``s that differ only in PER and seed as the
convoys of one ``envs.VectorConvoyEnv``, the policy acting on every follower of every
convoy at once through its ``act_batch``, and returns for each run what ``run_sim`` would
give: its log (the same rows, from the env's infos and ``own_truth``), the metrics
computed from it, and, with ``logs``, the bytes of the ``log.csv`` and ``metrics.json``
that ``run_sim(config, out_dir)`` writes, and of its ``events.json`` when it had events
(the env's ``safety_events`` and ``forged_rejected`` when the run ended). Each convoy reproduces the ``ConvoyEnv`` run of
its seed (``tests/envs/test_vector_env.py``), and a classical policy's ``act_batch`` is
its ``act`` on arrays, so the numbers are the per-run path's to the bit
(``tests/experiments/test_batched.py`` holds the files byte-identical).

``refusal`` says why runs cannot be batched (the env refuses the configuration — highway
scenarios — or the policy has no ``act_batch``, or only an inexact one); callers then run
one ``ConvoyEnv`` per run. Ranging sensors and ``forge`` faults (either ``security.auth``) run
batched with the same files (``tests/experiments/test_batched.py``).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from openconvoy.core import metrics as mt
from openconvoy.core.errors import ConfigError, DependencyMissing
from openconvoy.core.policy import BatchPolicy
from openconvoy.experiments.batched import log as batched_log
from openconvoy.experiments.runs import EVENTS_FILE, EXTRA_COLUMNS, RunConfig, build_env, events_of
from openconvoy.logs import COLUMNS, Log

LOG_COLUMNS: tuple[str, ...] = COLUMNS + EXTRA_COLUMNS
"""The columns of a run's ``log.csv`` (``run_sim``'s, for the path scenarios batched)."""


def _same_but_per_and_seed(configs: Sequence[RunConfig]) -> None:
    first = dataclasses.replace(configs[0], per=0.0, seed=0)
    for c in configs[1:]:
        if dataclasses.replace(c, per=0.0, seed=0) != first:
            raise ConfigError("a batch's runs may differ only in PER and seed")


def refusal(config: RunConfig, exact: bool = True) -> str | None:
    """Why ``config``'s runs cannot run batched (None: they can). ``exact``: also refuse
    a policy whose ``act_batch`` is not its ``act`` to the bit (the learned ones: one
    forward pass for the batch), so that results are the per-run path's."""
    from openconvoy.envs.scenarios import is_traffic_scenario
    from openconvoy.experiments.executor import error_line
    from openconvoy.policies.classical import ClassicalPolicy
    from openconvoy.policies.spec import PolicySpec

    if is_traffic_scenario(config.scenario):
        return "the batched env has no traffic (highway scenarios)"
    if exact and PolicySpec.parse(config.policy).learned:
        return (
            "a learned policy's act_batch is close to its act, not bit-equal; --batched batches it"
        )
    try:
        env, policies = build_env(config)
    except Exception as exc:  # noqa: BLE001 - the per-run tasks report it, run by run
        return f"it does not load here: {error_line(exc, frame=False)}"
    policy = next(iter(policies.values()))
    if not isinstance(policy, BatchPolicy):
        return f"policy {config.policy} has no act_batch"
    if isinstance(policy, ClassicalPolicy):
        compiled_only = [p for p in policy.plugins if not p.startswith("topology ")]
        if compiled_only:
            return f"its plug-in {', '.join(compiled_only)} run in Python, per run"
    elif exact:
        from openconvoy.policies.plugin import PluginPolicy

        if not isinstance(policy, PluginPolicy):
            return f"policy {config.policy}'s act_batch is not known to be bit-equal to its act"
        why = batch_mismatch(config)
        if why:
            return f"policy {config.policy}'s act_batch {why}"
    try:
        _vector_env([config], env)
    except (ConfigError, DependencyMissing) as exc:
        return (
            str(exc).replace("VectorConvoyEnv", "the batched env").replace(" (use ConvoyEnv)", "")
        )
    return None


TEST_EPISODE_S = 5.0
"""Length (s) of the episode on which a plug-in's ``act_batch`` must match its ``act``."""


def batch_mismatch(config: RunConfig, duration_s: float = TEST_EPISODE_S) -> str:
    """Where a plug-in policy's ``act_batch`` differs from its ``act`` on a test episode
    (``config``'s scenario at PER 0, ``duration_s`` s), "" when bit-equal everywhere: one
    copy acts per follower, another on all followers at once, tick by tick, each fed the
    per-follower copies' observations; an ``act_batch`` that raises is a mismatch."""
    test = dataclasses.replace(
        config, per=0.0, duration_s=min(duration_s, config.duration_s or duration_s)
    )
    env, policies = build_env(test)
    agents = env.possible_agents
    batch = next(iter(policies.values()))
    import copy

    batch = copy.deepcopy(batch)
    for p in (*policies.values(), batch):
        p.reset(test.seed)
    obs, _ = env.reset(seed=test.seed)
    k = 0
    while env.agents:
        acts = np.stack([np.asarray(policies[a].act(obs[a]), dtype=np.float32) for a in agents])
        try:
            batched = np.asarray(batch.act_batch(np.stack([obs[a] for a in agents])))
        except Exception as exc:  # noqa: BLE001 - the plug-in's code
            return f"raised {type(exc).__name__}: {exc} at tick {k} of a test episode"
        if batched.shape != acts.shape or not np.array_equal(
            batched.astype(np.float32), acts, equal_nan=True
        ):
            return (
                f"differs from its act at tick {k} of a {test.duration_s:g} s test episode "
                f"({batched.tolist()} vs {acts.tolist()})"
            )
        obs, _, _, _, _ = env.step(dict(zip(agents, acts)))
        k += 1
    return ""


def batch_cells(config: RunConfig) -> int:
    """Ticks × vehicles of one of ``config``'s runs (what a batch holds per convoy)."""
    env, _ = build_env(config)
    return (env.max_steps + 1) * env.n_vehicles


def _vector_env(configs: Sequence[RunConfig], env: Any) -> Any:
    """The ``VectorConvoyEnv`` of ``configs``, one convoy each, built from the
    ``ConvoyEnv`` ``build_env`` makes for them (scenario, member side, rate, faults)."""
    from openconvoy.envs import VectorConvoyEnv

    c = configs[0]
    return VectorConvoyEnv(
        len(configs),
        env.scenario,
        member_config=env.member_config,
        loss=[rc.loss_config for rc in configs],
        control_rate_hz=env.control_rate_hz,
        gps_noise_m=env.gps_noise_m,
        max_time_s=env.max_time_s,
        faults=env.faults,
        auth=c.auth == "required",
        autoreset=False,
        link_counters="all",  # the counters `openconvoy sim` logs: every ordered pair
    )


_STATE = ("x_m", "y_m", "speed_mps", "heading_rad", "accel_mps2")
_MEMBER = ("gap_m", "desired_gap_m", "spacing_error_m", "pred_msg_age_s")
_COUNTERS = ("msgs_sent", "msgs_received", "msgs_lost")
_COMMANDS = ("cmd_speed_mps", "cmd_heading_change_rad")


class Recorder:
    """Every tick of every convoy of a batched run, as a run's log rows report them:
    ``state(k, ...)`` the state, members' values and counters at tick ``k``;
    ``decision(k, ...)`` the commands and modes decided at tick ``k`` (known after the
    step). Arrays ``(ticks, B, N)``, the leader in column 0; ``events[b]``: run ``b``'s
    ``runs.run_events`` (``ended``)."""

    def __init__(self, ticks: int, B: int, N: int) -> None:
        shape = (ticks, B, N)
        self.f = {k: np.full(shape, np.nan) for k in _STATE + _MEMBER + _COMMANDS}
        self.i = {k: np.zeros(shape, dtype=np.int64) for k in _COUNTERS}
        self.mode = np.zeros(shape, dtype=np.int8)
        self.t = np.zeros(ticks)
        self.events: list[list[dict[str, Any]]] = [[] for _ in range(B)]

    def ended(self, venv: Any, which: np.ndarray) -> None:
        """The runs ``which`` (B,) ended at this tick of ``venv`` (a ``VectorConvoyEnv``):
        their events now (the batch steps on while other runs go on)."""
        rejected = venv.forged_rejected
        for b in np.flatnonzero(which).tolist():
            self.events[b] = events_of(
                venv.safety_events(b), float(venv.t[b]), rejected[b].tolist()
            )

    def state(self, k: int, info: dict[str, Any], truth: Sequence[np.ndarray]) -> None:
        for name, values in zip(_STATE, truth):
            self.f[name][k] = values
        for name in _MEMBER:
            self.f[name][k, :, 1:] = info[name]
        for name in _COUNTERS:
            self.i[name][k, :, 0] = info[f"leader_{name}"]
            self.i[name][k, :, 1:] = info[name]
        self.t[k] = info["t_s"][0]

    def decision(self, k: int, info: dict[str, Any]) -> None:
        for name in _COMMANDS:
            self.f[name][k, :, 0] = info[f"leader_{name}"]
            self.f[name][k, :, 1:] = info[name]
        self.mode[k, :, 0] = info["leader_mode"]
        self.mode[k, :, 1:] = info["mode"]

    def log(self, b: int, end: int, lengths: np.ndarray, geodetic: Any = None) -> Log:
        """Run ``b``'s log columns, ticks 0..``end`` (the last with empty commands and
        the last modes decided, as ``ConvoyEnv.final_log_rows``); ``geodetic(x, y)``
        gives lat/lon (omitted: NaN, for metrics only)."""
        from openconvoy.envs.vector.env import MODES

        n = end + 1
        N = self.mode.shape[2]
        cols: Log = {"t_s": np.repeat([round(float(t), 9) for t in self.t[:n]], N)}
        cols["vehicle_id"] = np.tile(np.arange(N, dtype=np.int64), n)
        for name in _STATE + _MEMBER + _COMMANDS:
            cols[name] = self.f[name][:n, b].ravel()
        for name in _COMMANDS:
            cols[name][-N:] = np.nan
        modes = self.mode[:n, b].copy()
        modes[end] = modes[end - 1]
        cols["mode"] = np.array(MODES, dtype=object)[modes.ravel()]
        for name in _COUNTERS:
            cols[name] = self.i[name][:n, b].ravel()
        lat, lon = geodetic(cols["x_m"], cols["y_m"]) if geodetic else (np.nan, np.nan)
        cols["lat_deg"] = np.broadcast_to(lat, (n * N,)).astype(np.float64)
        cols["lon_deg"] = np.broadcast_to(lon, (n * N,)).astype(np.float64)
        cols["length_m"] = np.tile(lengths, n)
        return {c: cols[c] for c in LOG_COLUMNS}


STEPPING_SHARE = 0.3
"""The share of a batch's time its stepping takes (the rest: each run's log, metrics and
files); measured, 0.15 s of 0.54 s for 8 ``paper`` runs of 30 s. ``run_batch`` reports
progress on that scale, so a bar moves at an even pace through both."""


class _Progress:
    """``on_progress(fraction)`` of a batch, called only when it moved by ``step`` or more
    (a queue between processes need not carry every tick)."""

    def __init__(self, on_progress: Callable[[float], None] | None, step: float = 0.01) -> None:
        self.on_progress, self.step, self.last = on_progress, step, 0.0

    def __call__(self, fraction: float) -> None:
        if self.on_progress is not None and fraction - self.last >= self.step:
            self.last = fraction
            self.on_progress(fraction)


def simulate(
    configs: Sequence[RunConfig], on_step: Callable[[float], None] | None = None
) -> tuple[Recorder, np.ndarray, Any]:
    """Run ``configs`` (differing only in PER and seed) as one batch: the recorder, each
    run's last tick, and the ``ConvoyEnv`` that ``build_env`` made for the first one.
    ``on_step(fraction)`` after each tick: the share of the longest run's ticks done."""
    _same_but_per_and_seed(configs)
    env, policies = build_env(configs[0])
    policy = next(iter(policies.values()))
    venv = _vector_env(configs, env)
    policy.reset(configs[0].seed)
    rec = Recorder(venv.max_steps + 1, len(configs), venv.n_vehicles)
    obs, info = venv.reset(seed=[c.seed for c in configs])
    rec.state(0, info, venv.own_truth)
    end = np.full(len(configs), -1)
    k = 0
    while k < venv.max_steps and (end < 0).any():
        obs, _, term, trunc, info = venv.step(policy.act_batch(obs))
        rec.decision(k, info)
        k += 1
        rec.state(k, info, venv.own_truth)
        ended = (term | trunc) & (end < 0)
        if ended.any():
            end[ended] = k
            rec.ended(venv, ended)
        if on_step is not None:
            on_step(k / venv.max_steps)
    return rec, end, env


def run_batch(
    configs: Sequence[RunConfig],
    read_back: bool = True,
    logs: bool = True,
    series: Sequence[bool] = (),
    on_progress: Callable[[float], None] | None = None,
) -> list[dict[str, Any]]:
    """Run ``configs`` batched; per run ``{"metrics", "files", "series"}`` as a sweep's
    task returns them. ``read_back``: metrics from the log as written and read back
    (``run_sim`` with an output directory; else from the values in memory, as without
    one); ``logs``: ``files`` holds ``log.csv`` too (else only ``metrics.json``; and
    ``events.json`` either way when the run had events);
    ``series[i]``: run ``i`` also returns its figure series (``sweep.run_series``);
    ``on_progress(fraction)``: how much of the batch is done, as it goes (stepping counts
    for ``STEPPING_SHARE``, each run's files for an equal part of the rest)."""
    from openconvoy.comms.geodesy import enu_to_geodetic
    from openconvoy.experiments.sweep import run_series

    progress = _Progress(on_progress)
    rec, end, env = simulate(configs, lambda f: progress(STEPPING_SHARE * f))
    lengths = np.array([p.length_m for p in env.presets])
    by_id = dict(enumerate(lengths.tolist()))
    origin = env.scenario.origin

    def geodetic(x: np.ndarray, y: np.ndarray) -> tuple[Any, Any]:
        return enu_to_geodetic(origin, x, y)[:2]

    out = []
    for b in range(len(configs)):
        log = rec.log(b, int(end[b]), lengths, geodetic if logs else None)
        if read_back:
            log = batched_log.rounded(log)
        metrics = mt.compute_metrics(log, by_id)
        files = {"metrics.json": _json_bytes(metrics)}
        if logs:
            files = {"log.csv": batched_log.csv_bytes(log, LOG_COLUMNS), **files}
        if rec.events[b]:
            files[EVENTS_FILE] = _json_bytes(rec.events[b])
        keep = b < len(series) and series[b]
        out.append(
            {"files": files, "metrics": metrics, "series": run_series(log, by_id) if keep else None}
        )
        progress(STEPPING_SHARE + (1.0 - STEPPING_SHARE) * (b + 1) / len(configs))
    return out


def _json_bytes(data: Any) -> bytes:
    """What ``runs.write_json`` writes for ``data``."""
    return (json.dumps(mt.json_safe(data), indent=2) + "\n").encode("utf-8")
