"""One calibration workflow: trust a sim result for your own vehicles (docs/calibration.md).

From a vehicle run's logs (``openconvoy deploy``: ``vehicle_N.csv`` + ``vehicle_N.json``):

1. ``fit-plant RUN --convoy CONVOY.toml --out-convoy FITTED.toml`` fits each vehicle's
   autopilot response (``fitplant.fit_pi_plant`` on its own log) and the V2V channel
   (``fit_channel``: the loss the run applied and the distribution of message ages at first
   use), and writes a convoy file naming the fitted presets with a ``[channel]`` table;
2. ``sim --convoy FITTED.toml --policy P`` runs the same scenario in the simulator;
3. ``compare RUN SIM`` puts both side by side on the scenario's window and ends with a
   verdict line (``verdict``): p95 platooning error, string stability and mean speed
   difference, each as a ratio sim / vehicle.

Vehicles: each log is replayed as its controller saw it (a row's command against the rows'
states, not shifted by the telemetry age), so the fitted delay is the whole loop's dead time
(autopilot + telemetry staleness), which is what the simulator's plant needs: its members
see the plant's state at once. When the base preset (the autopilot's shipped,
firmware-fitted one) explains the run at its best loop delay within ``KEEP_BASE_RATIO`` of a
free fit, only that delay is taken (one run of the ``paper`` profile cannot pin nine loop
parameters; the recordings did); otherwise the free fit is.

Channel: a logged message age at first use = its delivery delay (the phase between the
loops, the link) + the sender's telemetry staleness + the sender's clock error. The staleness
is not part of the simulated link's delay: the fitted plant's loop delay already holds it (the
simulated state lags as the logged one did), so the simulated sender's messages leave with
the delay alone and are stamped older by its staleness (``[channel] staleness_s``), as on
the vehicle, where the message carried a telemetry sample that old. Counting it twice made
the news reach the followers one staleness late (sitl/convoy vx-fixed-2, staleness 36 ms:
p95 ratio 1.10 against 1.04). A vehicle's clock error
is what its logged telemetry age shows beyond the staleness its loop-delay fit found: the
deploy stamps its state with the autopilot's clock mapped onto the system clock, and when
the autopilot's clock runs slow (PX4 SIH at 0.990; a loaded ArduPilot SITL host) that
mapping falls behind while the state is fresh (sitl/convoy vx-fixed-per0.3: +4 ms/s,
sitl-px4/convoy r2: +9 ms/s, from 0.09-0.16 s). It is fitted as a line per vehicle; the
delays are the ages less the sender's error, and the simulated channel stamps messages that
much older (``stamp_error_s + stamp_drift t``): members dead-reckon received states to
their system clock, so they place the predecessor that much further on (and past the
ladder's fresh age as if it were braking).

The fitted convoy file keeps the deployed ``vehicles`` (what the members, the safety rules
and the scenario's leader profile knew) and names the fitted presets as ``plants`` (how the
vehicles drive).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from openconvoy.core import metrics as mt
from openconvoy.core.errors import InputFileError
from openconvoy.envs.vehicles import VehiclePreset, preset_to_toml, vehicle_preset
from openconvoy.logs import Log, read_log

AUTOPILOT_BASES = {"ardupilot": "ardupilot-rover", "px4": "px4-sih-rover"}
"""The shipped firmware-fitted preset a vehicle fit starts from, by the run's autopilot."""

MAX_FIRST_USE_AGE_S = 1.0
"""Message ages at first use above this (s) are outages, not the link's delay: left out."""

QUANTILES = 21
"""Quantiles (0, 5, ..., 100 %) of the message ages kept as the channel's delay samples."""

KEEP_BASE_RATIO = 1.5
"""The base preset's loop is kept when its speed RMS at its best delay is at most this times
a free fit's (plus ``KEEP_BASE_SLACK_MPS``)."""

KEEP_BASE_SLACK_MPS = 0.005

CLOCK_ERROR_MIN_S = 0.03
"""A fitted clock error smaller than this over the whole run is noise: none is modelled."""

TOLERANCE = 0.10
"""The verdict's tolerance on the p95 ratio (sim / vehicle)."""


def run_metadata(run_dir: str | Path) -> dict[int, dict[str, Any]]:
    """Each vehicle's deploy metadata (``vehicle_N.json``) by vehicle id; {} for a sim run."""
    p = Path(run_dir)
    out: dict[int, dict[str, Any]] = {}
    if not p.is_dir():
        return out
    for f in sorted(p.glob("vehicle_*.json")):
        try:
            meta = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputFileError(f"{f}: not readable deploy metadata ({exc})") from None
        if isinstance(meta, dict) and isinstance(meta.get("vehicle_id"), int):
            out[meta["vehicle_id"]] = meta
    return out


def scenario_start(run_dir: str | Path) -> float | None:
    """The scenario's t = 0 on a vehicle run's clock: the leader's ``t_start_s`` (s), or
    None for a run without deploy metadata (a sim run starts at 0)."""
    meta = run_metadata(run_dir)
    lead = meta.get(0) or (meta[min(meta)] if meta else None)
    t = lead.get("t_start_s") if lead else None
    return float(t) if isinstance(t, (int, float)) else None


def window(log: Log, t0: float, t1: float) -> Log:
    """The rows with ``t0 <= t_s <= t1``, their times shifted so that ``t0`` is 0."""
    t = np.asarray(log["t_s"], dtype=float)
    keep = (t >= t0) & (t <= t1)
    out = {k: np.asarray(v)[keep] for k, v in log.items()}
    out["t_s"] = t[keep] - t0
    return out


def message_ages_at_first_use(log: Log, vehicle_id: int) -> np.ndarray:
    """The predecessor message ages (s) a follower logged on the ticks where a new message
    from its predecessor was first used: where the age fell instead of growing by the tick
    (``pred_msg_age_s``); ages above ``MAX_FIRST_USE_AGE_S`` are left out."""
    return _ages_and_times(log, vehicle_id)[0]


def _ages_and_times(log: Log, vehicle_id: int) -> tuple[np.ndarray, np.ndarray]:
    """``message_ages_at_first_use`` and the log times (s) they were used at."""
    sel = np.asarray(log["vehicle_id"]) == vehicle_id
    t = np.asarray(log["t_s"], dtype=float)[sel]
    age = np.asarray(log["pred_msg_age_s"], dtype=float)[sel]
    ok = np.isfinite(age)
    t, age = t[ok], age[ok]
    if len(age) == 0:
        return age, t
    grew = age[:-1] + np.diff(t)
    new = np.concatenate([[True], age[1:] < grew - 1e-3])
    first, when = age[new], t[new]
    keep = first <= MAX_FIRST_USE_AGE_S
    return first[keep], when[keep]


def median_telemetry_age(log: Log, vehicle_id: int) -> float:
    """The median age (s) of the own state a vehicle's ticks acted on (``telemetry_age_s``);
    0 for a log without the column (a sim run)."""
    if "telemetry_age_s" not in log:
        return 0.0
    sel = np.asarray(log["vehicle_id"]) == vehicle_id
    age = np.asarray(log["telemetry_age_s"], dtype=float)[sel]
    age = age[np.isfinite(age)]
    return float(np.median(age)) if len(age) else 0.0


@dataclass(frozen=True)
class ChannelFit:
    """The V2V channel of a vehicle run, as the simulator models it.

    Attributes:
        latency_samples_s: quantiles of the followers' message ages at first use less the
            senders' clock error and staleness (s), the simulated channel's delay
            distribution (``comms.loss.Latency``).
        per: the packet error rate the run's links applied (lost / offered, followers).
        ages_s: per follower, the ages at first use the fit used.
        stamp_error_s, stamp_drift: the senders' clock error at the scenario's start (s)
            and its growth (s/s): the least of the measured links' senders' errors and the
            mean of their drifts; 0 when below
            ``CLOCK_ERROR_MIN_S`` over the run.
        link_latency_s: per link ``(sender, receiver, quantile, ...)`` (``link_delays``).
        staleness_s: per vehicle (by index), its telemetry staleness and its clock's error
            beyond ``stamp_error_s`` (s): its messages are stamped that much older than the
            simulated state (``LossConfig.staleness_s``).
        lost_s, lost_window_s: per measured link ``(sender, receiver, send time, ...)``, the
            broadcasts it dropped on the run (``recorded_losses``), for the sim to replay;
            empty when the run lost nothing.
    """

    latency_samples_s: tuple[float, ...]
    per: float
    ages_s: dict[int, np.ndarray]
    stamp_error_s: float = 0.0
    stamp_drift: float = 0.0
    link_latency_s: tuple[tuple[float, ...], ...] = ()
    staleness_s: tuple[float, ...] = ()
    lost_s: tuple[tuple[float, ...], ...] = ()
    lost_window_s: float = 0.05

    def summary(self) -> str:
        """One line per follower: how many ages, their median and 5-95 % range (ms)."""
        lines = [
            f"channel: per {self.per:.3f}; delay quantiles 0/50/100 % "
            f"{1e3 * self.latency_samples_s[0]:.1f} / "
            f"{1e3 * float(np.median(self.latency_samples_s)):.1f} / "
            f"{1e3 * self.latency_samples_s[-1]:.1f} ms; clock error "
            f"{1e3 * self.stamp_error_s:.0f} ms + {1e3 * self.stamp_drift:.1f} ms/s; "
            "senders' staleness " + " / ".join(f"{1e3 * v:.0f}" for v in self.staleness_s) + " ms"
        ]
        for e in self.link_latency_s:
            lines.append(
                f"  link {int(e[0])} -> {int(e[1])}: delay median "
                f"{1e3 * float(np.median(e[2:])):.1f} ms"
                + (" (composed from the links between)" if e[1] - e[0] > 1 else "")
            )
        for vid, a in sorted(self.ages_s.items()):
            if len(a):
                p5, p50, p95 = np.percentile(a, [5, 50, 95]) * 1e3
                lines.append(
                    f"  follower {vid}: {len(a)} first-use ages, median {p50:.1f} ms "
                    f"(5-95 % {p5:.1f}-{p95:.1f})"
                )
        return "\n".join(lines)


def clock_error(log: Log, vehicle_id: int, staleness_s: float) -> tuple[float, float]:
    """A vehicle's clock error ``(error at t = 0 (s), drift (s/s))``: a straight line
    through its 2-s median telemetry ages (log time from the scenario's start) less the
    staleness ``staleness_s`` its loop delay shows; (0, 0) when it stays below
    ``CLOCK_ERROR_MIN_S`` over the run or the log has no telemetry ages."""
    if "telemetry_age_s" not in log:
        return 0.0, 0.0
    sel = np.asarray(log["vehicle_id"]) == vehicle_id
    t = np.asarray(log["t_s"], dtype=float)[sel]
    age = np.asarray(log["telemetry_age_s"], dtype=float)[sel]
    ok = np.isfinite(age) & np.isfinite(t)
    t, age = t[ok], age[ok]
    if len(t) < 20:
        return 0.0, 0.0
    edges = np.arange(t.min(), t.max() + 2.0, 2.0)
    idx = np.digitize(t, edges)
    mids = [(float(t[idx == k].mean()), float(np.median(age[idx == k]))) for k in np.unique(idx)]
    if len(mids) < 3:
        return 0.0, 0.0
    tm, am = np.array(mids).T
    drift, at0 = np.polyfit(tm, am, 1)
    err0 = float(at0) - staleness_s
    ends = [err0 + drift * float(t.min()), err0 + drift * float(t.max())]
    if max(abs(e) for e in ends) < CLOCK_ERROR_MIN_S:
        return 0.0, 0.0
    return round(err0, 4), round(float(drift), 5)


def _quantiles(a: np.ndarray, n: int) -> tuple[float, ...]:
    return tuple(round(float(q), 4) for q in np.quantile(a, np.linspace(0.0, 1.0, n)))


def _tick_s(log: Log) -> float:
    """The run's control period (s): the median interval between one vehicle's rows."""
    ids = np.asarray(log["vehicle_id"])
    t = np.asarray(log["t_s"], dtype=float)
    steps = np.concatenate([np.diff(t[ids == v]) for v in np.unique(ids)] or [np.zeros(0)])
    steps = steps[steps > 0]
    return float(np.median(steps)) if len(steps) else 0.05


STAMP_MATCH_S = 0.002
"""A first-use stamp matches a sender's logged row when their stamps differ by less (s)."""


STAMP_SOURCES = ("telemetry", "send")
"""What a message's stamp is: its sender's telemetry sample's time (an unsigned BSM's
secMark: the sender row's time less its ``telemetry_age_s``), or the time it was sent (a
signed one's generation time, D50: the sender row's time)."""


def _sender_rows(log: Log, sender: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A vehicle's rows in time order: (times s, telemetry ages s or NaN, msgs_sent or NaN)."""
    sel = np.asarray(log["vehicle_id"]) == sender
    ts = np.asarray(log["t_s"], dtype=float)[sel]
    order = np.argsort(ts, kind="stable")

    def col(name: str) -> np.ndarray:
        if name not in log:
            return np.full(len(ts), np.nan)
        return np.asarray(log[name], dtype=float)[sel][order]

    return ts[order], col("telemetry_age_s"), col("msgs_sent")


def stamp_source(log: Log, vehicle_id: int) -> str | None:
    """How ``vehicle_id``'s predecessor stamped its messages (``STAMP_SOURCES``): the one
    whose stamps the receiver's first uses (``t - age``) match, within ``STAMP_MATCH_S``, for
    most of them; None when neither does for half (a log without telemetry ages). Measured:
    all of sitl/convoy and sitl-px4/convoy r2 (unsigned) match the telemetry, 99 % of a
    signed ``demo`` the send times, and at most 24 % the other."""
    a, when = _ages_and_times(log, vehicle_id)
    ts, tel, _ = _sender_rows(log, vehicle_id - 1)
    if len(a) == 0 or len(ts) == 0:
        return None
    used = when - a
    share = {
        name: float(np.mean(_nearest_distance(np.sort(st[np.isfinite(st)]), used) < STAMP_MATCH_S))
        for name, st in (("telemetry", ts - tel), ("send", ts))
    }
    best = max(share, key=lambda n: share[n])
    return best if share[best] >= 0.5 else None


def _stamps(ts: np.ndarray, tel: np.ndarray, source: str) -> np.ndarray:
    """The stamps (s) a sender's rows gave their messages, by ``stamp_source``."""
    return ts - tel if source == "telemetry" else ts.copy()


def delivery_delays(
    log: Log, vehicle_id: int, fallback_s: np.ndarray, source: str | None = None
) -> np.ndarray:
    """Each new predecessor message's delivery delay (s): from the sender's tick that sent
    it to the receiver's tick that first used it. The first use of stamp ``t - age`` is
    matched to the sender's first row that gave that stamp (``source``, default
    ``stamp_source``; within ``STAMP_MATCH_S``). With telemetry stamps what is left of the
    age is the sender's staleness and clock error, which vary per message (sitl/convoy
    vx-fixed-2: ages 8 or 46 ms, delays 7 ms, the leader's telemetry 0.1 or 38 ms old).
    Unmatched messages (a log without telemetry ages) get ``fallback_s`` (per first use,
    same order as ``message_ages_at_first_use``)."""
    a, when = _ages_and_times(log, vehicle_id)
    out = np.asarray(fallback_s, dtype=float).copy()
    source = source or stamp_source(log, vehicle_id)
    if source is None or len(a) == 0:
        return out
    ts, tel, _ = _sender_rows(log, vehicle_id - 1)
    stamps = _stamps(ts, tel, source)
    for k, (w, age) in enumerate(zip(when, a)):
        hit = np.flatnonzero((np.abs(stamps - (w - age)) < STAMP_MATCH_S) & (ts <= w + 1e-6))
        if len(hit):
            out[k] = w - ts[hit[0]]
    return out


def _nearest_distance(sorted_values: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Each ``x``'s distance to the nearest of ``sorted_values`` (inf when there are none)."""
    if len(sorted_values) == 0:
        return np.full(len(x), np.inf)
    k = np.searchsorted(sorted_values, x)
    lo = sorted_values[np.clip(k - 1, 0, len(sorted_values) - 1)]
    hi = sorted_values[np.clip(k, 0, len(sorted_values) - 1)]
    return np.minimum(np.abs(x - lo), np.abs(x - hi))


def recorded_losses(
    log: Log, vehicle_id: int, source: str | None = None
) -> tuple[np.ndarray, float] | None:
    """The broadcasts of ``vehicle_id``'s predecessor that never reached it on the run: their
    send times (s, log time) and half the sender's broadcast period (s); None when the log
    cannot tell (no ``msgs_sent``, no ``stamp_source``). A broadcast is a row where the
    sender's ``msgs_sent`` grew; it carried that row's stamp (``source``), and it arrived
    when the receiver first used that stamp (``STAMP_MATCH_S``; at 10 Hz broadcasts and
    20 Hz ticks nothing arrives unused). sitl/convoy vx-fixed-per0.3: 29 % and 31 % of the
    leader's and follower 1's broadcasts lost, 0 on the PER 0 runs."""
    source = source or stamp_source(log, vehicle_id)
    if source is None or "msgs_sent" not in log:
        return None
    ts, tel, sent = _sender_rows(log, vehicle_id - 1)
    stamps = _stamps(ts, tel, source)
    rows = np.flatnonzero(np.diff(sent) > 0) + 1
    rows = rows[np.isfinite(stamps[rows])]
    if len(rows) < 2:
        return None
    a, when = _ages_and_times(log, vehicle_id)
    near = _nearest_distance(np.sort(when - a), stamps[rows])
    lost = ts[rows][near >= STAMP_MATCH_S]
    return lost, 0.5 * float(np.median(np.diff(ts[rows])))


def _broadcast_times(log: Log, vehicle_id: int) -> np.ndarray:
    """The log times (s) of a vehicle's broadcasts: the rows where its ``msgs_sent`` grew."""
    sel = np.asarray(log["vehicle_id"]) == vehicle_id
    ts = np.asarray(log["t_s"], dtype=float)[sel]
    order = np.argsort(ts, kind="stable")
    sent = np.asarray(log["msgs_sent"], dtype=float)[sel][order]
    return ts[order][np.flatnonzero(np.diff(sent) > 0) + 1]


ARRIVAL_SLACK_S = 0.0125
"""How much earlier than its median delay says a message may arrive (s): delays vary by a few
ms per message, and the receiver's rows are a tick apart, so a drop is looked for from a
quarter tick before (vx-fixed-per0.3: 2->1 drops 249 attributed at no slack, 184 at 2-15 ms)."""


def other_sender_losses(
    log: Log,
    receiver: int,
    sender: int,
    pred_lost_s: np.ndarray,
    pred_delay_s: float,
    sender_delay_s: float,
) -> np.ndarray:
    """The broadcasts of ``sender`` (not ``receiver``'s predecessor) that ``receiver``
    dropped: send times (s). Its log counts drops from all senders (``msgs_lost``); those
    of the predecessor (``pred_lost_s``, each counted on the receiver's first row after it
    would have arrived, ``pred_delay_s`` after it left) are taken out, and each drop left is
    ``sender``'s latest broadcast due (``sender_delay_s`` after it left) by that row. Only
    right when the receiver hears one vehicle besides its predecessor (a three-vehicle
    convoy's last follower hears the leader: vx-fixed-per0.3, 216 of 619 dropped)."""
    sel = np.asarray(log["vehicle_id"]) == receiver
    ts = np.asarray(log["t_s"], dtype=float)[sel]
    order = np.argsort(ts, kind="stable")
    ts = ts[order]
    drops = np.diff(np.asarray(log["msgs_lost"], dtype=float)[sel][order])
    pred = np.bincount(
        np.searchsorted(ts, np.asarray(pred_lost_s) + pred_delay_s - ARRIVAL_SLACK_S),
        minlength=len(ts) + 1,
    )[1 : len(ts)]
    left = np.maximum(drops - pred, 0).astype(int)
    sent = _broadcast_times(log, sender)
    out = []
    for k in np.flatnonzero(left):
        i = int(np.searchsorted(sent + sender_delay_s - ARRIVAL_SLACK_S, ts[k + 1])) - 1
        out.extend([float(sent[i])] * int(left[k]) if i >= 0 else [])
    return np.unique(np.round(out, 3))


def link_delays(
    delays: dict[int, np.ndarray], tick_s: float, quantiles: int
) -> tuple[tuple[float, ...], ...]:
    """Per link, its delay quantiles (s): measured for each follower's link from its
    immediate predecessor (``delays``: ``delivery_delays``); composed for a link that skips
    vehicles. On a vehicle a message from ``s`` is first used at the receiver's next tick
    after it arrives: its delay is the phase of ``r``'s loop after ``s``'s (mod the tick),
    and phases add up along the string, so ``s -> r`` gets ``(sum of the links' median
    delays) mod tick``. The senders' staleness is not in them: the channel stamps it
    (``LossConfig.staleness_s``)."""
    out: list[tuple[float, ...]] = []
    ids = sorted(delays)
    for r in ids:
        if len(delays[r]):
            out.append((r - 1.0, float(r), *_quantiles(delays[r], quantiles)))
    for r in ids:
        for s in range(0, r - 1):
            chain = range(s + 1, r + 1)
            if not all(k in delays and len(delays[k]) for k in chain):
                continue
            phase = sum(float(np.median(delays[k])) for k in chain)
            out.append((float(s), float(r), round(phase % tick_s, 4)))
    return tuple(out)


def _replayed_losses(
    log: Log,
    ids: list[int],
    delays: dict[int, np.ndarray],
    links: tuple[tuple[float, ...], ...],
    source: str,
) -> tuple[list[tuple[float, ...]], list[float]]:
    """Each link's recorded losses as ``LossConfig.lost_s`` entries, and the senders' half
    broadcast periods: every follower's link from its predecessor (``recorded_losses``)
    and, for a receiver that hears one vehicle besides its predecessor, that link too
    (``other_sender_losses``; with more vehicles a drop's sender is ambiguous: drawn)."""
    replay: list[tuple[float, ...]] = []
    windows: list[float] = []
    composed = {(int(e[0]), int(e[1])): float(np.median(e[2:])) for e in links}
    for vid in delays:
        rec = recorded_losses(log, vid, source)
        if rec is None:
            continue
        replay.append((vid - 1.0, float(vid), *(round(float(x), 3) for x in rec[0])))
        windows.append(rec[1])
        others = [v for v in ids if v not in (vid, vid - 1)]
        if len(others) == 1:
            s = others[0]
            lost = other_sender_losses(
                log,
                receiver=vid,
                sender=s,
                pred_lost_s=rec[0],
                pred_delay_s=float(np.median(delays[vid])),
                sender_delay_s=composed.get((s, vid), 0.0),
            )
            replay.append((float(s), float(vid), *(float(x) for x in lost)))
    return replay, windows


def run_stamp_source(log: Log, ids: list[int]) -> str | None:
    """How the run's vehicles stamped their messages (``stamp_source``), the most links'
    verdict (the deploys of one run share their version and signing); None if no link's
    stamps match."""
    found = [stamp_source(log, v) for v in ids if v > 0 and v - 1 in ids]
    known = [f for f in found if f is not None]
    return max(STAMP_SOURCES, key=known.count) if known else None


def fit_channel(
    log: Log,
    staleness_s: float | dict[int, float] = 0.0,
    quantiles: int = QUANTILES,
) -> ChannelFit:
    """Fit the channel from a run's (merged) log, times from the scenario's start: the
    senders' clock error (``clock_error``), the followers' delivery delays
    (``delivery_delays``; without telemetry ages: the ages at first use less the sender's
    clock error and staleness) as each link's delay distribution (``link_delays``) and,
    pooled, as the common one, the senders' staleness (which the channel stamps), and the
    loss their counters show. ``staleness_s``: each vehicle's (or all vehicles') telemetry
    staleness (s)."""
    ids = sorted(int(v) for v in np.unique(np.asarray(log["vehicle_id"])))
    stale = (
        dict(staleness_s) if isinstance(staleness_s, dict) else {v: float(staleness_s) for v in ids}
    )
    source = run_stamp_source(log, ids)
    if source == "send":
        # Messages stamped when sent (signed) show neither the senders' clocks nor their
        # telemetry's staleness: the simulated ones are not stamped with them either.
        clocks = {v: (0.0, 0.0) for v in ids}
        stale = {v: 0.0 for v in ids}
    else:
        clocks = {v: clock_error(log, v, stale.get(v, 0.0)) for v in ids}
    ages, delays = {}, {}
    errs: list[tuple[float, float]] = []  # each measured link's sender's clock error
    for vid in ids:
        if vid > 0 and vid - 1 in clocks:
            a, when = _ages_and_times(log, vid)
            e_s, d_s = clocks[vid - 1]
            # A logged age is the delay + the sender's staleness and clock error (the
            # receiver's "now" is the system clock, in its log and in its member alike).
            ages[vid] = np.maximum(a - (e_s + d_s * when), 0.0)
            delays[vid] = delivery_delays(
                log, vid, np.maximum(ages[vid] - stale.get(vid - 1, 0.0), 0.0), source
            )
            errs.append((e_s, d_s))
    err0, drift = (
        (float(np.mean([e[0] for e in errs])), float(np.mean([e[1] for e in errs])))
        if errs
        else (0.0, 0.0)
    )
    span = float(np.nanmax(np.asarray(log["t_s"], dtype=float))) if len(log["t_s"]) else 0.0
    offsets: dict[int, float] = {}
    if max(abs(err0), abs(err0 + drift * span)) < CLOCK_ERROR_MIN_S:
        err0, drift = 0.0, 0.0
    elif errs:
        # The common error is the least sender's; each sender's own beyond it is stamped
        # with its staleness (sitl-px4/convoy r2: 55 / 30 ms at the start, leader /
        # follower 1; their drifts agree to 0.1 ms/s).
        err0 = min(clocks[v - 1][0] for v in ages)
        offsets = {v - 1: clocks[v - 1][0] - err0 for v in ages}
    pooled = np.concatenate([d for d in delays.values()] or [np.zeros(0)])
    if len(pooled) < 10:
        raise InputFileError(
            "too few predecessor messages in the log to fit the channel "
            f"({len(pooled)} first-use ages; need >= 10)"
        )
    samples = _quantiles(pooled, quantiles)
    links = link_delays(delays, _tick_s(log), quantiles)
    received = lost = 0
    for vid in ages:
        sel = np.asarray(log["vehicle_id"]) == vid
        rec = np.asarray(log["msgs_received"])[sel]
        los = np.asarray(log["msgs_lost"])[sel]
        rec, los = rec[rec >= 0], los[los >= 0]
        if len(rec) and len(los):
            received += int(rec.max() - rec.min())
            lost += int(los.max() - los.min())
    per = lost / (received + lost) if received + lost else 0.0
    staleness = tuple(
        round(stale.get(v, 0.0) + offsets.get(v, 0.0), 4) for v in range(max(ids) + 1)
    )
    replay, windows = (
        _replayed_losses(log, ids, delays, links, source) if per > 0.0 and source else ([], [])
    )
    window = round(float(np.median(windows)), 4) if windows else 0.05
    return ChannelFit(
        samples, round(per, 4), ages, err0, drift, links, staleness, tuple(replay), window
    )


@dataclass(frozen=True)
class Calibration:
    """What ``calibrate`` fitted and wrote.

    Attributes:
        convoy_path: the convoy file written (``sim --convoy`` it).
        preset_paths: per vehicle, its fitted preset file.
        presets: per vehicle, the fitted preset (delays: the loop's, as its controller saw).
        speed_rms_mps: per vehicle, the chosen model's speed RMS on its log.
        kept_base: per vehicle, whether the base preset's loop was kept (delay fitted).
        staleness_s: per vehicle, the loop delay beyond the base preset's own.
        channel: the channel fit.
        policy: the policy the run drove (from its metadata; "paper" if unknown).
        duration_s: the scenario window used (s from the leader's start).
        speed_scale: per vehicle, its logged speed over its track speed (``speed_scale``);
            the plant models cos(heading bias) of it.
    """

    convoy_path: Path
    preset_paths: dict[int, Path]
    presets: dict[int, VehiclePreset]
    speed_rms_mps: dict[int, float]
    kept_base: dict[int, bool]
    staleness_s: dict[int, float]
    channel: ChannelFit
    policy: str
    duration_s: float
    speed_scale: dict[int, float] = dataclasses.field(default_factory=dict)


def _base_for(
    vid: int, convoy_preset: VehiclePreset, meta: dict[str, Any], base: str | None
) -> VehiclePreset:
    """The preset a vehicle's fit starts from: ``base`` if given, else the shipped preset of
    the run's autopilot, else the convoy's; sized as the convoy's vehicle."""
    name = base or AUTOPILOT_BASES.get(str(meta.get("autopilot")))
    if name is None:
        return convoy_preset
    start = vehicle_preset(name)
    return dataclasses.replace(
        start, length_m=convoy_preset.length_m, width_m=convoy_preset.width_m
    )


def _with_loop_delay(preset: VehiclePreset, delay_s: float, name: str) -> VehiclePreset:
    """``preset`` renamed, its speed delay ``delay_s`` and its heading delay moved by as much."""
    extra = delay_s - preset.actuation_delay_s
    return dataclasses.replace(
        preset,
        name=name,
        actuation_delay_s=round(min(2.0, max(0.0, delay_s)), 3),
        heading_delay_s=round(min(2.0, max(0.0, preset.heading_delay + extra)), 3),
    )


HEADING_BIAS_MIN_STEP_M = 0.02
"""Rows that moved less than this (m) since the previous one say nothing of the track."""


def heading_bias(log: Log, vehicle_id: int) -> float:
    """A vehicle's heading bias (rad): the median of its logged heading (the autopilot's
    estimate) less its track's direction (from its logged positions, between rows that
    moved ``HEADING_BIAS_MIN_STEP_M`` or more); 0 when it hardly moved. Measured: PX4 SIH
    r2 -5.9 / -5.7 / +1.5 degrees, the PX4 demo -1.1 / -9.5 / -5.0, ArduPilot SITL
    +0.5 to +0.6."""
    sel = np.asarray(log["vehicle_id"]) == vehicle_id
    t = np.asarray(log["t_s"], dtype=float)[sel]
    order = np.argsort(t, kind="stable")
    x, y, h = (np.asarray(log[k], dtype=float)[sel][order] for k in ("x_m", "y_m", "heading_rad"))
    dx, dy = np.diff(x), np.diff(y)
    moved = np.hypot(dx, dy) >= HEADING_BIAS_MIN_STEP_M
    moved &= np.isfinite(h[1:])
    if moved.sum() < 20:
        return 0.0
    off = np.angle(np.exp(1j * (h[1:] - np.arctan2(dy, dx))))[moved]
    return float(np.clip(np.median(off), -0.5, 0.5))


SPEED_SCALE_SPAN_S = 3.0
"""Logged speed is set against the track over spans this long (s)."""

SPEED_SCALE_MIN_MPS = 0.5
"""Only spans whose track speed is at least this (m/s) say how speed is reported."""


def speed_scale(log: Log, vehicle_id: int) -> float:
    """How a vehicle reports its speed: the median over its
    ``SPEED_SCALE_SPAN_S`` spans of its mean logged speed over its track speed, on spans
    that moved at least ``SPEED_SCALE_MIN_MPS`` with the two within 0.3 m/s (no outage);
    1 when fewer than 20 spans do. The plant models cos(heading bias) of it
    (``VehiclePreset.heading_bias_rad``), which is all of it on the PX4 demo: 0.9993 /
    0.9855 / 0.9973 where its heading biases (-1.1 / -9.6 / -5.1 degrees) give 0.9998 /
    0.9860 / 0.9960. Not modelled (printed by ``fit-plant``): the firmware's own speed
    errors, PX4 SIH sitl-px4/convoy r1-r3 0.993-1.100 (r2 1.034 / 0.993 / 1.016) and
    ArduPilot SITL sitl/convoy 0.978-0.986 (modelled, they moved vx-fixed-2's string
    stability to the other side of 1 on one seed). Spans of 1 s read up to 1 % lower (the positions' noise adds
    to a short track; ArduPilot vx-fixed-1's last vehicle 0.968)."""
    sel = np.asarray(log["vehicle_id"]) == vehicle_id
    t = np.asarray(log["t_s"], dtype=float)[sel]
    order = np.argsort(t, kind="stable")
    t = t[order]
    x, y, v = (np.asarray(log[k], dtype=float)[sel][order] for k in ("x_m", "y_m", "speed_mps"))
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(v)
    if "telemetry_valid" in log:  # rows after the telemetry was lost say nothing
        ok &= np.asarray(log["telemetry_valid"], dtype=float)[sel][order] != 0
    t, x, y, v = t[ok], x[ok], y[ok], v[ok]
    j = np.searchsorted(t, t + SPEED_SCALE_SPAN_S)
    i = np.flatnonzero(j < len(t))
    j = j[i]
    if len(i) == 0:
        return 1.0
    track = np.hypot(x[j] - x[i], y[j] - y[i]) / np.maximum(t[j] - t[i], 1e-9)
    sums = np.concatenate([[0.0], np.cumsum(v)])
    logged = (sums[j] - sums[i]) / (j - i)
    keep = (track >= SPEED_SCALE_MIN_MPS) & (np.abs(logged - track) < 0.3)
    if keep.sum() < 20:
        return 1.0
    return float(np.clip(np.median(logged[keep] / track[keep]), 0.5, 1.5))


LOOP_DELAYS_S = np.round(np.arange(0.0, 0.62, 0.02), 2)
"""The loop delays (s) tried with the base preset's loop (the pi replay's 20 ms grid)."""


def fit_vehicle(
    run: Path,
    vid: int,
    start: VehiclePreset,
    name: str,
    rounds: int,
    population: int,
) -> tuple[VehiclePreset, float, bool]:
    """One vehicle's preset from its log, replayed as its controller saw it: the base's loop
    at its best delay, or a free pi fit when that explains the log clearly better (see the
    module doc). Returns (preset, speed RMS m/s, base kept)."""
    from openconvoy.experiments.fitplant import _series_from, fit_pi_plant, pi_speed_rms

    series, _ = _series_from(run, vid, "telemetry", telemetry_age=False)
    free = fit_pi_plant(
        [run], base=start, name=name, vehicle_id=vid, rounds=rounds, population=population,
        telemetry_age=False,
    )  # fmt: skip
    if start.speed_loop != "pi":
        return free.preset, free.speed_rms_mps, False
    tried = [dataclasses.replace(start, actuation_delay_s=float(d)) for d in LOOP_DELAYS_S]
    rms = pi_speed_rms(series, tried)
    k = int(np.argmin(rms))
    if rms[k] <= KEEP_BASE_RATIO * free.speed_rms_mps + KEEP_BASE_SLACK_MPS:
        delay = float(LOOP_DELAYS_S[k])
        if 0 < k < len(rms) - 1:  # the squared error's parabola through the best three
            y0, y1, y2 = (float(v) ** 2 for v in rms[k - 1 : k + 2])
            curve = y0 - 2.0 * y1 + y2
            if curve > 0.0:
                step = float(LOOP_DELAYS_S[1] - LOOP_DELAYS_S[0])
                delay += step * (y0 - y2) / (2.0 * curve)
        return _with_loop_delay(start, delay, name), float(rms[k]), True
    return free.preset, free.speed_rms_mps, False


def calibrate(
    run_dir: str | Path,
    convoy_path: str | Path,
    out_path: str | Path,
    base: str | None = None,
    rounds: int = 14,
    population: int = 160,
) -> Calibration:
    """Fit every vehicle of the run at ``run_dir`` and its channel; write the fitted presets
    beside ``out_path`` (``<stem>.vehicle_N.toml``) and the convoy file ``out_path``
    (``convoy_path``'s scenario and origin, the fitted vehicles, a ``[channel]`` table)."""
    from openconvoy.convoy import load_convoy

    run = Path(run_dir)
    if not run.is_dir():
        raise InputFileError(f"{run}: not a run directory (vehicle_N.csv and vehicle_N.json)")
    convoy = load_convoy(convoy_path)
    meta = run_metadata(run)
    whole = read_log(run)
    t0 = scenario_start(run)
    log = whole if t0 is None else window(whole, t0, math.inf)
    ids = sorted(int(v) for v in np.unique(np.asarray(log["vehicle_id"])))
    if len(ids) != convoy.n_vehicles:
        raise InputFileError(
            f"{run} holds vehicles {ids}, but {convoy_path} describes {convoy.n_vehicles}"
        )
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    presets: dict[int, VehiclePreset] = {}
    paths: dict[int, Path] = {}
    rms: dict[int, float] = {}
    kept: dict[int, bool] = {}
    stale: dict[int, float] = {}
    scales: dict[int, float] = {}
    for vid in ids:
        start = _base_for(vid, vehicle_preset(convoy.vehicles[vid]), meta.get(vid, {}), base)
        name = f"{convoy.name}-vehicle-{vid}"
        scales[vid] = round(speed_scale(log, vid), 4)
        presets[vid], rms[vid], kept[vid] = fit_vehicle(run, vid, start, name, rounds, population)
        presets[vid] = dataclasses.replace(
            presets[vid], heading_bias_rad=round(heading_bias(log, vid), 4)
        )
        # The loop's dead time beyond the autopilot's own: the telemetry's real staleness.
        stale[vid] = (
            round(min(max(presets[vid].actuation_delay_s - start.actuation_delay_s, 0.0),
                      median_telemetry_age(log, vid)), 3)
            if kept[vid] else 0.0
        )  # fmt: skip
        paths[vid] = out.with_name(f"{out.stem}.vehicle_{vid}.toml")
        how = "the base loop, delay fitted" if kept[vid] else "a free pi fit"
        paths[vid].write_text(
            f"# fitted by openconvoy fit-plant from {run / f'vehicle_{vid}.csv'} ({how}; "
            "delays: the loop's as the controller saw it)\n" + preset_to_toml(presets[vid]),
            encoding="utf-8",
        )
    channel = fit_channel(log, stale)
    policy = str(meta.get(0, {}).get("policy_spec") or meta.get(0, {}).get("policy") or "paper")
    duration = _drive_duration(meta, t0)
    out.write_text(_convoy_toml(convoy, paths, channel, run), encoding="utf-8")
    return Calibration(out, paths, presets, rms, kept, stale, channel, policy, duration, scales)


def _drive_duration(meta: dict[int, dict[str, Any]], t0: float | None) -> float:
    lead = meta.get(0, {})
    end = lead.get("t_end_s")
    if t0 is None or not isinstance(end, (int, float)):
        return math.nan
    return float(end) - t0


def _convoy_toml(convoy: Any, paths: dict[int, Path], channel: ChannelFit, run: Path) -> str:
    declared = ", ".join(f'"{v}"' for v in convoy.vehicles)
    plants = ", ".join(f'"{paths[v].name}"' for v in sorted(paths))
    samples = ", ".join(f"{s:g}" for s in channel.latency_samples_s)
    links = ", ".join(
        "[" + ", ".join([str(int(e[0])), str(int(e[1]))] + [f"{v:g}" for v in e[2:]]) + "]"
        for e in channel.link_latency_s
    )
    lat, lon, alt = convoy.origin
    return (
        f"# fitted by openconvoy fit-plant from the vehicle run {run}\n"
        "# (docs/calibration.md): sim --convoy this file, then compare RUN SIM\n"
        "[convoy]\n"
        f'name = "{convoy.name}-fitted"\n'
        f'scenario = "{convoy.scenario}"\n'
        "# deployed with (what members, safety rules and the leader's profile know)\n"
        f"vehicles = [{declared}]\n"
        "# how they drive (fitted)\n"
        f"plants = [{plants}]\n"
        f"origin = [{lat!r}, {lon!r}, {alt!r}]\n"
        "\n[channel]\n"
        f"per = {channel.per!r}\n"
        f"latency_samples_s = [{samples}]\n"
        f"stamp_error_s = {channel.stamp_error_s!r}\n"
        f"stamp_drift = {channel.stamp_drift!r}\n"
        "# per link: sender, receiver, its delay quantiles (s)\n"
        f"link_latency_s = [{links}]\n"
        "# per vehicle: its telemetry staleness, its messages stamped that much older (s)\n"
        f"staleness_s = [{', '.join(f'{v:g}' for v in channel.staleness_s)}]\n"
        + (
            "# per link: sender, receiver, the send times (s) of the broadcasts it dropped on\n"
            "# the run, replayed by sim (sim --per P draws losses at P instead)\n"
            f"lost_window_s = {channel.lost_window_s!r}\n"
            "lost_s = ["
            + ", ".join(
                "[" + ", ".join([str(int(e[0])), str(int(e[1]))] + [f"{v:g}" for v in e[2:]]) + "]"
                for e in channel.lost_s
            )
            + "]\n"
            if channel.lost_s
            else ""
        )
    )


def format_calibration(c: Calibration) -> str:
    """What was fitted, and the next two commands of the workflow."""
    lines = []
    for vid, p in sorted(c.presets.items()):
        how = "base loop kept" if c.kept_base[vid] else "free pi fit"
        lines.append(
            f"vehicle {vid}: {c.preset_paths[vid]}  {how}, loop delay "
            f"{p.actuation_delay_s:.2f} s, speed RMS {c.speed_rms_mps[vid]:.4f} m/s, "
            f"heading bias {math.degrees(p.heading_bias_rad):+.1f} deg; speed logged "
            f"x{c.speed_scale.get(vid, math.nan):.4f} of its track's "
            f"(cos of the bias: {math.cos(p.heading_bias_rad):.4f})"
        )
    lines.append(c.channel.summary())
    lines.append(f"wrote {c.convoy_path}")
    lines.append(
        f"next: openconvoy sim --convoy {c.convoy_path} --policy {c.policy} --out SIM_DIR; "
        "then openconvoy compare RUN_DIR SIM_DIR"
    )
    return "\n".join(lines)


# --- the verdict -----------------------------------------------------------------------


VERDICT_KEYS = ("p95_platooning_error_m", "string_stability", "mean_speed_difference_mps")


def ratios(a: dict[str, Any], b: dict[str, Any]) -> dict[str, float]:
    """B / A of the verdict's metrics (NaN where A is 0 or either is missing)."""
    out = {}
    for k in VERDICT_KEYS:
        x, y = _finite(a.get(k)), _finite(b.get(k))
        out[k] = y / x if x != 0.0 else math.nan
    return out


def _finite(v: Any) -> float:
    """``v`` as a float; NaN for None or a value that is not finite."""
    return float(v) if v is not None and math.isfinite(float(v)) else math.nan


def verdict(a: dict[str, Any], b: dict[str, Any], tolerance: float = TOLERANCE) -> dict[str, Any]:
    """Does B reproduce A? ``p95`` ratio within ``tolerance`` of 1 and string stability on
    the same side of 1; the speed-difference ratio is reported, not judged."""
    r = ratios(a, b)
    p95_ok = math.isfinite(r["p95_platooning_error_m"]) and (
        abs(r["p95_platooning_error_m"] - 1.0) <= tolerance
    )
    sa, sb = a.get("string_stability"), b.get("string_stability")
    side_ok = (
        sa is not None
        and sb is not None
        and math.isfinite(sa)
        and math.isfinite(sb)
        and (sa < 1.0) == (sb < 1.0)
    )
    return {"ratios": r, "p95_within": p95_ok, "string_same_side": side_ok,
            "match": p95_ok and side_ok, "tolerance": tolerance}  # fmt: skip


def format_verdict(v: dict[str, Any]) -> str:
    """The one verdict line."""
    r = v["ratios"]

    def f(x: float) -> str:
        return "nan" if not math.isfinite(x) else f"{x:.3f}"

    tol = f"{100 * v['tolerance']:.0f} %"
    return (
        f"verdict: {'MATCH' if v['match'] else 'NO MATCH'}: B/A p95 "
        f"{f(r['p95_platooning_error_m'])} ({'within' if v['p95_within'] else 'outside'} {tol}), "
        f"string stability {f(r['string_stability'])} "
        f"({'same side of 1' if v['string_same_side'] else 'other side of 1'}), "
        f"speed difference {f(r['mean_speed_difference_mps'])}"
    )


def windowed_metrics(
    path: str | Path, duration_s: float | None, lengths: dict[int, float] | None = None
) -> tuple[dict[str, Any], str]:
    """A run's metrics on the scenario's window: a vehicle run (deploy metadata) from the
    leader's start for ``duration_s`` (None: to its end), a sim run as it is; with a note
    saying which window was used."""
    log = read_log(path)
    t0 = scenario_start(path)
    if t0 is None:
        return mt.compute_metrics(log, lengths), "whole run"
    t1 = t0 + (duration_s if duration_s is not None else math.inf)
    cut = window(log, t0, t1)
    if len(cut["t_s"]) == 0:
        raise InputFileError(f"{path}: no rows in the scenario window")
    span = float(cut["t_s"].max())
    return mt.compute_metrics(cut, lengths), f"the leader's drive, {span:.1f} s from its start"
