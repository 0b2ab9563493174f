"""One DDS participant in a ROS 2 domain, with ROS 2's names and QoS, that ROS 2 sees as a node.

A ROS 2 topic ``/a/b`` is the DDS topic ``rt/a/b`` (under the node's namespace, ``rt/<ns>/a/b``); ROS 2's
default QoS is reliable, volatile, keep-last 10; "latched" is transient-local (with Cyclone's durability
service keeping the same depth, as rmw_cyclonedds sets it); only XCDR1 is offered, like both ROS 2
middlewares. Each endpoint carries its type's hash in its user data and the participant its enclave, and the
node's readers and writers are published on ``ros_discovery_info`` as rmw implementations do, so node lists,
``ros2 node info`` and graph views show the node with its topics. The domain is created with ROS 2's discovery
settings (``domain.py``) and then ``CYCLONEDDS_URI``.
"""

from __future__ import annotations

import contextlib
import threading
from typing import TypeVar

from cyclonedds.core import DDSException, Listener, ReadCondition
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.internal import InvalidSample
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.domain import Discovery, cyclone_config, discovery, domain_id, in_namespace
from humanoid_prime.dds.typehash import user_data
from humanoid_prime.errors import PrimeError

ROS_TOPIC_PREFIX = "rt"
DEFAULT_DEPTH = 10
T = TypeVar("T", bound=IdlStruct)
DISCOVERY_TOPIC = "ros_discovery_info"  # a DDS topic of the rmw layer, outside ROS 2's names
ENCLAVE = b"enclave=/;"  # the participant user data rmw implementations read (no security enclave)


def dds_topic_name(topic: str) -> str:
    """``/prime/joint_states`` -> ``rt/prime/joint_states``."""
    if not topic.startswith("/"):
        raise PrimeError(f"ROS 2 topic names given here are absolute: {topic!r} does not start with '/'")
    return ROS_TOPIC_PREFIX + topic


def ros_qos(*, latched: bool = False, depth: int = DEFAULT_DEPTH, reliable: bool = True,
            data_type: type[IdlStruct] | None = None) -> Qos:
    """ROS 2's QoS profile as rmw_cyclonedds maps it: reliable, volatile, keep-last ``depth`` (the default
    profile), or transient-local for a latched topic; with ``data_type``, its type hash in the user data."""
    policies: list[object] = [
        Policy.Reliability.Reliable(duration(milliseconds=100)) if reliable else Policy.Reliability.BestEffort,
        Policy.History.KeepLast(depth),
        Policy.DataRepresentation(use_cdrv0_representation=True),  # XCDR1 only, as both ROS 2 middlewares
        Policy.WriterDataLifecycle(autodispose=False),  # rmw_cyclonedds: no dispose when a writer goes away
    ]
    if latched:
        policies += [Policy.Durability.TransientLocal,
                     # Cyclone keeps history for late joiners by the durability service's depth (rmw_cyclonedds).
                     Policy.DurabilityService(cleanup_delay=0, history=Policy.History.KeepLast(depth),
                                              max_samples=-1, max_instances=-1, max_samples_per_instance=-1)]
    else:
        policies.append(Policy.Durability.Volatile)
    if data_type is not None:
        policies.append(Policy.Userdata(user_data(data_type)))
    return Qos(*policies)


def take(reader: DataReader[T], n: int = 64, condition: ReadCondition | None = None) -> list[T]:
    """Up to ``n`` samples from ``reader`` (those ``condition`` selects), without the data-less ones (a writer gone
    away, an instance disposed) that DDS also delivers."""
    samples = reader.take(N=n) if condition is None else reader.take(N=n, condition=condition)
    return [s for s in samples if not isinstance(s, InvalidSample)]


class _Domains:
    """The DDS domains this process created, each with the configuration of the first node to join it, kept
    while a node uses it (deleting a domain deletes every participant in it)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._held: dict[int, tuple[Domain | None, int]] = {}

    def join(self, domain: int, settings: Discovery) -> None:
        with self._lock:
            held, users = self._held.get(domain, (None, 0))
            if not users:
                try:
                    held = Domain(domain, cyclone_config(settings))
                except DDSException as exc:
                    raise PrimeError(f"cannot join DDS domain {domain}: {exc} (check CYCLONEDDS_URI, "
                                     "ROS_STATIC_PEERS and the network interfaces)") from None
            self._held[domain] = (held, users + 1)

    def leave(self, domain: int) -> None:
        with self._lock:
            held, users = self._held.pop(domain, (None, 0))
            if users > 1:
                self._held[domain] = (held, users - 1)
            elif held is not None:
                held.__del__()  # dds_delete now, not whenever the collector gets to it


_domains = _Domains()


def _gid(entity: DomainParticipant | DataWriter[IdlStruct] | DataReader[IdlStruct]) -> msg.Gid:
    """An entity's ROS 2 GID: its DDS GUID, as every rmw implementation takes it (wire order)."""
    return msg.Gid(data=list(entity.guid.bytes))


class DdsNode:
    """A DDS participant with ROS 2 conventions, seen on the graph as node ``name`` in ``namespace`` (no name:
    a plain participant, as before ROS 2 knew of nodes). ``close`` deletes it and everything it created."""

    def __init__(self, domain: int | None = None, *, name: str | None = None, namespace: str = "/",
                 settings: Discovery | None = None) -> None:
        self.domain = domain_id(domain)
        self.name = name
        self.namespace = namespace
        self.settings = settings if settings is not None else discovery()
        _domains.join(self.domain, self.settings)
        try:
            self.participant = DomainParticipant(self.domain, qos=Qos(Policy.Userdata(ENCLAVE)))
        except DDSException as exc:
            _domains.leave(self.domain)
            raise PrimeError(f"cannot join DDS domain {self.domain}: {exc} (check CYCLONEDDS_URI and the network "
                             "interfaces)") from None
        self._topics: dict[str, Topic[IdlStruct]] = {}
        self._readers: list[DataReader[IdlStruct]] = []
        self._writers: list[DataWriter[IdlStruct]] = []
        self._discovery: DataWriter[msg.ParticipantEntitiesInfo] | None = None
        if name is not None:
            qos = ros_qos(latched=True, depth=1, data_type=msg.ParticipantEntitiesInfo)
            self._discovery = DataWriter(self.participant, Topic(self.participant, DISCOVERY_TOPIC,
                                                                 msg.ParticipantEntitiesInfo), qos=qos)

    def topic_name(self, topic: str) -> str:
        """The ROS 2 name of ``topic`` (absolute) for this node: under its namespace."""
        return in_namespace(self.namespace, topic)

    def _topic(self, topic: str, data_type: type[T]) -> Topic[T]:
        name = dds_topic_name(self.topic_name(topic))
        if name not in self._topics:
            self._topics[name] = Topic(self.participant, name, data_type)
        return self._topics[name]  # type: ignore[return-value]  # one topic name, one type

    def writer(self, topic: str, data_type: type[T], *, latched: bool = False, depth: int = DEFAULT_DEPTH,
               reliable: bool = True, listener: Listener | None = None) -> DataWriter[T]:
        writer = DataWriter(self.participant, self._topic(topic, data_type),
                            qos=ros_qos(latched=latched, depth=depth, reliable=reliable, data_type=data_type),
                            listener=listener)
        self._writers.append(writer)  # type: ignore[arg-type]  # kept for their GUIDs only
        self.announce()
        return writer

    def reader(self, topic: str, data_type: type[T], *, latched: bool = False, depth: int = DEFAULT_DEPTH,
               reliable: bool = True, listener: Listener | None = None) -> DataReader[T]:
        reader = DataReader(self.participant, self._topic(topic, data_type),
                            qos=ros_qos(latched=latched, depth=depth, reliable=reliable, data_type=data_type),
                            listener=listener)
        self._readers.append(reader)  # type: ignore[arg-type]  # kept for their GUIDs only
        self.announce()
        return reader

    def entities_info(self) -> msg.ParticipantEntitiesInfo:
        """What this participant publishes on ``ros_discovery_info``: its node with its readers and writers."""
        nodes = [] if self.name is None else [msg.NodeEntitiesInfo(
            node_namespace=self.namespace, node_name=self.name, reader_gid_seq=[_gid(r) for r in self._readers],
            writer_gid_seq=[_gid(w) for w in self._writers])]
        return msg.ParticipantEntitiesInfo(gid=_gid(self.participant), node_entities_info_seq=nodes)

    def announce(self) -> None:
        """Publish the node's endpoints on ``ros_discovery_info`` (latched: late joiners get the latest)."""
        if self._discovery is not None:
            self._discovery.write(self.entities_info())

    def close(self) -> None:
        """Leave the graph: first the node (``ros_discovery_info`` without it, then that instance disposed and
        unregistered, as rmw does when a node is destroyed, so a peer's node list drops it at once), then the
        participant (with every reader, writer and topic: peers see them go at once)."""
        participant: DomainParticipant | None = getattr(self, "participant", None)
        if participant is None:
            return
        if self._discovery is not None:
            gone = msg.ParticipantEntitiesInfo(gid=_gid(participant), node_entities_info_seq=[])
            with contextlib.suppress(DDSException):
                self._discovery.write(gone)
                self._discovery.dispose(gone)
                self._discovery.unregister_instance(gone)
        self._readers.clear()
        self._writers.clear()
        self._topics.clear()
        self._discovery = None
        del self.participant
        participant.__del__()  # dds_delete now, not whenever the collector gets to it
        _domains.leave(self.domain)

    def __enter__(self) -> DdsNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
