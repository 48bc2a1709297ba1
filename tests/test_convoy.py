import pytest

from openconvoy.convoy import ConvoyConfig, load_convoy


def test_load_full_convoy_file(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text(
        '[convoy]\nname = "lab"\nvehicles = ["1/10", "1/6"]\norigin = [1.0, 2.0, 3.0]\n'
        '[v2v]\nport = 5000\ntemp_ids = ["00000001", "00000002"]\n[safety]\nmin_gap_m = 0.5\n'
    )
    c = load_convoy(p)
    assert c.name == "lab" and c.n_vehicles == 2 and c.origin == (1.0, 2.0, 3.0)
    assert c.v2v.port == 5000 and c.v2v.temp_ids == ("00000001", "00000002")
    assert c.safety.min_gap_m == 0.5 and c.safety.speed_cap_mps == 5.0


def test_unknown_key_is_named(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('[convoy]\nvehicels = ["1/10"]\n')
    with pytest.raises(ValueError, match="vehicels"):
        load_convoy(p)
    p.write_text("[convoi]\n")
    with pytest.raises(ValueError, match="convoi"):
        load_convoy(p)


def test_needs_a_follower():
    with pytest.raises(ValueError, match="follower"):
        ConvoyConfig(vehicles=("1/10",))
