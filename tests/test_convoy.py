import pytest

from openconvoy.convoy import ConvoyConfig, load_convoy
from openconvoy.envs.vehicles import vehicle_preset


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


@pytest.mark.parametrize(
    "value, ok",
    [
        ("0.5", True),
        ("0", True),
        ("-0.1", False),
        ("nan", False),
        ("inf", False),
        ('"1"', False),
        ("101.0", False),
    ],
)
def test_gap_margin_is_checked_and_reaches_the_envelope(tmp_path, value, ok):
    from openconvoy.bridge.runner import envelope_from

    p = tmp_path / "c.toml"
    p.write_text(f'[convoy]\nvehicles = ["1/10", "1/6"]\n[safety]\ngap_margin_m = {value}\n')
    if not ok:
        with pytest.raises(ValueError, match="gap_margin_m"):
            load_convoy(p)
        return
    env = envelope_from(load_convoy(p), vehicle_id=1)
    assert env.braking.margin_m == float(value)
    # reaction: the actuation delay and a 20 Hz control period
    assert env.braking.decel_mps2 == 1.0 and env.braking.reaction_s == pytest.approx(0.12 + 0.05)
    assert env.braking.lag_s == pytest.approx(0.35)
    assert (env.ego_length_m, env.pred_length_m) == (0.97, 0.779)
    assert envelope_from(ConvoyConfig(), vehicle_id=1).braking.margin_m == pytest.approx(
        0.25 * 0.97
    )
    # The leader's rule is to the convoy's tail, which it meets lapping a closed track (D49).
    lead = envelope_from(ConvoyConfig(), vehicle_id=0)
    assert (
        lead.braking is not None
        and lead.pred_length_m == vehicle_preset(ConvoyConfig().vehicles[-1]).length_m
    )


def test_v2v_transport_is_multicast_unless_ros2_is_written(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('[convoy]\nvehicles = ["1/10", "1/10"]\n')
    assert load_convoy(p).v2v.transport == "multicast"
    p.write_text(
        '[convoy]\nvehicles = ["1/10", "1/10"]\n'
        '[v2v]\ntransport = "ros2"\nros2_topic = "/lab/v2v"\nros2_domain = 7\n'
    )
    v = load_convoy(p).v2v
    assert (v.transport, v.ros2_topic, v.ros2_domain) == ("ros2", "/lab/v2v", 7)
    for bad, named in (
        ('transport = "dds"', "v2v.transport: 'dds' is not one of multicast, ros2"),
        ("ros2_domain = 233", "ros2_domain"),
    ):
        p.write_text(f'[convoy]\nvehicles = ["1/10", "1/10"]\n[v2v]\n{bad}\n')
        with pytest.raises(ValueError, match=named):
            load_convoy(p)


VEHICLE_TABLES = (
    '[convoy]\nvehicles = ["1/10", "1/6", "1/10"]\n'
    '[[vehicle]]\nlink = "mavlink"\n'
    '[[vehicle]]\nlink = "mavros"\nros = 2\nnamespace = "/v1/mavros"\n'
    '[[vehicle]]\nlink = "px4-dds"\ndds_domain = 7\n'
)


def test_vehicle_tables_give_each_vehicle_its_link(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text(VEHICLE_TABLES)
    c = load_convoy(p)
    links = [c.vehicle_link(i) for i in range(3)]
    assert [v.link for v in links] == ["mavlink", "mavros", "px4-dds"]
    assert (links[1].ros, links[1].ns) == (2, "/v1/mavros")
    assert (links[2].ns, links[2].dds_domain) == ("", 7)  # px4-dds: no namespace by default
    p.write_text('[convoy]\nvehicles = ["1/10", "1/6"]\n[[vehicle]]\nlink = "ap-dds"\n'
                 '[[vehicle]]\nlink = "mavros"\n')  # fmt: skip
    c = load_convoy(p)
    assert (c.vehicle_link(0).ns, c.vehicle_link(1).ns, c.vehicle_link(1).ros) == (
        "/ap",
        "/mavros",
        1,
    )
    # No tables: MAVLink for every vehicle.
    p.write_text('[convoy]\nvehicles = ["1/10", "1/6"]\n')
    assert load_convoy(p).vehicle_link(1).link == "mavlink"


@pytest.mark.parametrize(
    "change, named",
    [
        (('"px4-dds"', '"zenoh"'), r"vehicle\[2\]\.link.*'zenoh'"),
        (("ros = 2", "ros = 3"), r"vehicle\[1\]\.ros.*3"),
        (("dds_domain = 7", "dds_domain = 300"), r"vehicle\[2\]\.dds_domain"),
        (
            ('link = "mavlink"\n', 'link = "mavlink"\nnamespace = "/x"\n'),
            r"vehicle\[0\]\.namespace",
        ),
        (
            ('[[vehicle]]\nlink = "px4-dds"\ndds_domain = 7\n', ""),
            r"2 \[\[vehicle\]\] tables for 3",
        ),
        (('link = "mavlink"', 'linc = "mavlink"'), "linc"),
    ],
)
def test_a_bad_vehicle_table_is_named(tmp_path, change, named):
    p = tmp_path / "c.toml"
    text = VEHICLE_TABLES.replace(*change)
    assert text != VEHICLE_TABLES
    p.write_text(text)
    with pytest.raises(ValueError, match=named):
        load_convoy(p)
