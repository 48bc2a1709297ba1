import numpy as np
import pytest

from openconvoy.core.member import ConvoyMember
from openconvoy.core.state import VehicleState
from openconvoy.policies import PRESETS, ClassicalPolicy, load_policy
from openconvoy.policies.spec import classical_config, classical_from_toml, classical_to_toml


def test_paper_preset_has_the_published_defaults():
    c = PRESETS["paper"]
    m = c.member
    assert (m.topology, m.trigger.kind, m.trigger.period_s) == ("all-predecessors", "periodic", 0.1)
    assert (m.spacing.kind, m.spacing.distance_m) == ("constant-distance", 15.0)
    assert (c.speed.kind, c.speed.kp, c.speed.kd) == ("pd", 0.3, 1.1)
    assert (c.heading.kind, c.heading.gain) == ("stanley", 0.2)
    assert (c.speed_limit_mps, c.control_rate_hz) == (5.0, 20.0)


def test_table_one_presets_cover_topologies_and_triggers():
    combos = {
        (p.member.topology, p.member.trigger.kind, p.member.spacing.kind) for p in PRESETS.values()
    }
    for topo in ("all-predecessors", "leader"):
        for trig in ("periodic", "event"):
            assert (topo, trig, "constant-distance") in combos
    for topo in ("all-predecessors", "lookahead:1", "lookahead:N"):
        for trig in ("periodic", "event"):
            assert (topo, trig, "constant-time-headway") in combos
    assert ("bidirectional", "periodic", "quadratic") in combos
    assert all(p.description for p in PRESETS.values())


def test_ladder_suffix_and_unknown_spec():
    assert classical_config("paper+ladder").member.ladder.enabled
    assert not classical_config("paper").member.ladder.enabled
    with pytest.raises(ValueError, match="unknown policy 'papr'"):
        load_policy("papr")
    with pytest.raises(FileNotFoundError):
        load_policy("missing.npz")


def test_toml_roundtrip_and_base_override(tmp_path):
    c = classical_config("cacc-lookahead1-event+ladder")
    p = tmp_path / "p.toml"
    p.write_text(classical_to_toml(c))
    assert classical_from_toml(p) == c
    p.write_text('[policy]\nbase = "paper"\n[policy.speed]\nkp = 0.5\n')
    tuned = classical_from_toml(p)
    assert tuned.speed.kp == 0.5 and tuned.speed.kd == 1.1 and tuned.name == "p"
    p.write_text('[policy]\nbase = "paper"\n[policy.speed]\nkpp = 0.5\n')
    with pytest.raises(ValueError, match="kpp"):
        classical_from_toml(p)


def test_policy_acts_on_member_observations():
    pol = load_policy("paper")
    assert isinstance(pol, ClassicalPolicy)
    m = ConvoyMember(1, 2, pol.member_config, [0.8, 0.8])
    m.observe_own(VehicleState(1, 0.0, 0.0, 0.0, 1.0, 0.0))
    # Nothing heard: stand still.
    assert load_policy("paper").act(m.observation(0.0)).tolist() == [0.0, 0.0]
    # Predecessor 2 m farther than 15 m, same speed: speed up by kp * 2.
    m.receive(VehicleState(0, 0.0, 17.0, 0.0, 1.0, 0.0), 0.0)
    a = pol.act(m.observation(0.0))
    assert a[0] == pytest.approx(1.0 + 0.3 * 2.0, abs=1e-5) and a[1] == pytest.approx(0.0, abs=1e-6)
    assert a.dtype == np.float32


def test_the_spec_grammar_is_parsed_in_one_place() -> None:
    from openconvoy.policies.spec import PolicySpec

    p = PolicySpec.parse("dir/fast.toml+ladder")
    assert (p.base, p.ladder, p.toml, p.learned, p.suffix) == (
        "dir/fast.toml",
        True,
        True,
        False,
        "+ladder",
    )
    assert str(p.with_base("fast")) == "fast+ladder" and str(p) == "dir/fast.toml+ladder"
    assert PolicySpec.parse("run/model.zip").learned and PolicySpec.parse("p.npz").learned
    # A learned policy takes no ladder suffix: that spec is a (bad) classical one.
    assert not PolicySpec.parse("model.zip+ladder").learned
    assert PolicySpec.parse("paper") == PolicySpec("paper", False)
