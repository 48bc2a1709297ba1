import pytest

from openconvoy.core.gates import RxGate, TriggerConfig, TxGate
from openconvoy.core.state import VehicleState

KEPT = {
    # topology: senders vehicle 3 of 6 keeps
    "predecessor": {2},
    "all-predecessors": {0, 1, 2},
    "lookahead:1": {2},
    "lookahead:2": {1, 2},
    "lookahead:N": {0, 1, 2},
    "leader": {0},
    "leader-predecessor": {0, 2},
    "bidirectional": {2, 4},
    "all": {0, 1, 2, 4, 5},
}


@pytest.mark.parametrize("topology", sorted(KEPT))
def test_each_topology_keeps_exactly_its_senders(topology):
    gate = RxGate(topology, ego=3, n_vehicles=6)
    assert {j for j in range(6) if gate.keeps(j)} == KEPT[topology]


def test_needed_vehicles_for_the_ladder_are_every_kept_predecessor():
    # Issue 10: the ladder once watched only the nearest one, so a dead leader that the
    # policy still followed (dead-reckoned) went unnoticed.
    assert RxGate("leader", 3, 6).needed() == [0]
    assert RxGate("all-predecessors", 3, 6).needed() == [2, 1, 0]
    assert RxGate("leader-predecessor", 3, 6).needed() == [2, 0]
    assert RxGate("lookahead:2", 4, 6).needed() == [3, 2]
    assert RxGate("bidirectional", 1, 3).needed() == [0]
    assert RxGate("all", 2, 4).needed() == [1, 0]
    assert RxGate("all", 0, 3).needed() == []


@pytest.mark.parametrize("bad", ["ring", "lookahead:0", "lookahead:x"])
def test_bad_topology_names_are_errors(bad):
    with pytest.raises(ValueError, match="topology"):
        RxGate(bad, 1, 3)


def _state(t, x, v=1.0):
    return VehicleState(0, t, x, 0.0, v, 0.0)


def test_periodic_sends_on_a_fixed_grid_despite_tick_jitter():
    gate = TxGate(TriggerConfig("periodic", period_s=0.1))
    ticks = [0.0, 0.05, 0.101, 0.149, 0.2, 0.26, 0.31, 0.39, 0.4]
    sent = [t for t in ticks if gate.should_send(_state(t, t), t)]
    assert sent == [0.0, 0.101, 0.2, 0.31, 0.4]


def test_event_trigger_sends_on_deviation_and_after_max_silence():
    cfg = TriggerConfig(
        "event", period_s=0.1, threshold_m=0.5, speed_threshold_mps=10, max_silence_s=1.0
    )
    gate = TxGate(cfg)
    # Constant speed: others extrapolate perfectly, so only the first message and the
    # max-silence refreshes go out.
    sent = [k for k in range(31) if gate.should_send(_state(k * 0.1, k * 0.1), k * 0.1)]
    assert sent == [0, 10, 20, 30]
    # A jump of 1 m away from the extrapolation goes out at the next check.
    gate = TxGate(cfg)
    assert gate.should_send(_state(0.0, 0.0), 0.0)
    assert not gate.should_send(_state(0.1, 0.1), 0.1)
    assert gate.should_send(_state(0.2, 1.2), 0.2)


def test_event_trigger_on_speed_change():
    gate = TxGate(TriggerConfig("event", threshold_m=100, speed_threshold_mps=0.2))
    assert gate.should_send(_state(0.0, 0.0, v=1.0), 0.0)
    assert not gate.should_send(_state(0.1, 0.1, v=1.1), 0.1)
    assert gate.should_send(_state(0.2, 0.2, v=1.3), 0.2)


@pytest.mark.parametrize("topology", [*sorted(KEPT), "lookahead:7"])
@pytest.mark.parametrize("n", [1, 2, 6])
def test_kept_row_is_keeps_for_every_sender(topology, n):
    # The bulk answer the batched simulator builds its links from, against ρ per pair.
    for ego in range(n):
        gate = RxGate(topology, ego, n)
        assert gate.kept_row().tolist() == [gate.keeps(j) for j in range(n)]


def test_kept_row_of_a_plugin_asks_its_keeps():
    gate = RxGate("tests/data/plugins/equal.py:AllPredecessors", 3, 6)
    assert gate.kept_row().tolist() == [True, True, True, False, False, False]
