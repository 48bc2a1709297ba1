"""DDS plumbing shared by the ``px4-dds`` link and its PX4 stand-in: topic names, QoS and
a Cyclone DDS participant that can be kept on the loopback interface.

Topic names and QoS follow PX4's ``src/modules/uxrce_dds_client/utilities.hpp`` (PX4 main,
as the px4_msgs in ``msgs.py``): ``generate_topic_name`` makes ``rt/<ns>/fmu/<in|out>/<name>``
(``rt/`` is ROS 2's DDS prefix for topics; ``<ns>`` is PX4's ``UXRCE_DDS_NS``, one per
vehicle), PX4's data writers (``/fmu/out``) are BEST_EFFORT, TRANSIENT_LOCAL, KEEP_LAST,
its data readers (``/fmu/in``) BEST_EFFORT, VOLATILE, KEEP_LAST.
"""

from __future__ import annotations

from typing import Any

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from openconvoy.bridge.px4dds.msgs import topic_base
from openconvoy.comms.dds import Waiter, interface_config
from openconvoy.core.errors import ConfigError

OUT_QOS = Qos(
    Policy.Reliability.BestEffort,
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1),
)
"""PX4's data writers (``create_data_writer``)."""

OUT_READER_QOS = Qos(
    Policy.Reliability.BestEffort,
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(32),
)
"""Our readers of ``/fmu/out``: PX4's writer QoS with a deeper history, so that every sample
between two polls (50 Hz topics, a 20 Hz runner) is seen and a bad one can be counted."""

IN_QOS = Qos(
    Policy.Reliability.BestEffort,
    Policy.Durability.Volatile,
    Policy.History.KeepLast(8),
)
"""PX4's data readers (``create_data_reader``); our writers of ``/fmu/in`` match them."""

LOCALHOST_CONFIG = (
    "<CycloneDDS><Domain id='any'><General>"
    "<Interfaces><NetworkInterface name='lo'/></Interfaces>"
    "<AllowMulticast>false</AllowMulticast></General>"
    "<Discovery><ParticipantIndex>auto</ParticipantIndex>"
    "<MaxAutoParticipantIndex>60</MaxAutoParticipantIndex>"
    "<Peers><Peer address='127.0.0.1'/></Peers></Discovery>"
    "</Domain></CycloneDDS>"
)
"""Cyclone on the loopback interface only, discovery by unicast to 127.0.0.1: nothing leaves
the machine (tests and demos)."""


_DOMAINS: dict[int, Domain] = {}


def _configured_domain(domain_id: int, config: str) -> None:
    """Create domain ``domain_id`` with Cyclone XML ``config`` once per process (Cyclone
    refuses a second Domain object for an id in use; a stand-in and a link may share a
    process). Kept for the process's life: the Domain object carries the configuration."""
    if domain_id not in _DOMAINS:
        _DOMAINS[domain_id] = Domain(domain_id, config)


def topic_name(ns: str, direction: str, data_type: type) -> str:
    """PX4's ``generate_topic_name`` for a px4_msgs type: ``rt/<ns>/fmu/<direction>/<name>``
    (no ns: ``rt/fmu/...``), the name with its version suffix (``msgs.topic_base``)."""
    ns, name = ns.strip("/"), topic_base(data_type)
    return f"rt/{ns}/fmu/{direction}/{name}" if ns else f"rt/fmu/{direction}/{name}"


class Participant:
    """One DDS participant on ``domain_id``; ``localhost`` keeps it on ``lo`` without
    multicast (``LOCALHOST_CONFIG``), ``iface`` on that network interface
    (``comms.dds.interface_config``, as the V2V over DDS and the ap-dds link's Cyclone node),
    else Cyclone's own configuration (CYCLONEDDS_URI)."""

    def __init__(
        self, domain_id: int = 0, localhost: bool = False, iface: str | None = None
    ) -> None:
        if localhost and iface:
            raise ConfigError("--dds-localhost and --dds-iface: choose one")
        if localhost:
            _configured_domain(domain_id, LOCALHOST_CONFIG)
        elif iface:
            _configured_domain(domain_id, interface_config(iface))
        self.dp: DomainParticipant | None = DomainParticipant(domain_id)
        self._topics: dict[str, Topic] = {}

    def _open_dp(self) -> DomainParticipant:
        if self.dp is None:
            raise RuntimeError("DDS participant closed")
        return self.dp

    def _topic(self, name: str, data_type: Any) -> Topic:
        if name not in self._topics:
            self._topics[name] = Topic(self._open_dp(), name, data_type)
        return self._topics[name]

    def writer(self, name: str, data_type: Any, qos: Qos) -> DataWriter:
        """A data writer of ``data_type`` on topic ``name``."""
        return DataWriter(self._open_dp(), self._topic(name, data_type), qos=qos)

    def reader(self, name: str, data_type: Any, qos: Qos) -> DataReader:
        """A data reader of ``data_type`` on topic ``name``."""
        return DataReader(self._open_dp(), self._topic(name, data_type), qos=qos)

    def waiter(self, readers: list[DataReader]) -> Waiter:
        """A ``Waiter`` that wakes when any of ``readers`` has data."""
        return Waiter(self._open_dp(), readers)

    def close(self) -> None:
        """Delete the participant and with it its readers, writers and topics now (the
        Python objects may live on in their owners; Cyclone no longer matches them)."""
        if self.dp is not None:
            self.dp.__del__()  # cyclonedds has no public delete; this one is idempotent
        self._topics.clear()
        self.dp = None


def take_all(reader: DataReader, counter: dict[str, int], key: str, data_type: type) -> list[Any]:
    """Every sample of ``data_type`` pending on ``reader`` (non-blocking). Cyclone's
    ``InvalidSample`` (a writer went away: no data) is skipped; a sample Cyclone cannot
    deserialize is bad network input: counted in ``counter[key]`` and dropped."""
    try:
        samples = reader.take(N=64)
    except Exception:  # noqa: BLE001 (cyclonedds raises plain Exceptions on bad CDR)
        counter[key] = counter.get(key, 0) + 1
        return []
    return [s for s in samples if isinstance(s, data_type)]
