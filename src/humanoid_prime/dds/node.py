"""One DDS participant in a ROS 2 domain, with ROS 2's names and QoS.

A ROS 2 topic ``/a/b`` is the DDS topic ``rt/a/b``; ROS 2's default QoS is reliable, volatile, keep-last 10;
"latched" is transient-local (with Cyclone's durability service keeping the same depth, as rmw_cyclonedds
sets it); only XCDR1 is offered, like both ROS 2 middlewares. ``ROS_DOMAIN_ID`` picks the domain unless one
is given. Cyclone's own configuration (``CYCLONEDDS_URI``: interfaces, peers) applies as usual.
"""

from __future__ import annotations

from typing import Any

from cyclonedds.core import DDSException
from cyclonedds.domain import DomainParticipant
from cyclonedds.internal import InvalidSample
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from humanoid_prime.dds.domain import domain_id
from humanoid_prime.errors import PrimeError

ROS_TOPIC_PREFIX = "rt"
DEFAULT_DEPTH = 10


def dds_topic_name(topic: str) -> str:
    """``/prime/joint_states`` -> ``rt/prime/joint_states``."""
    if not topic.startswith("/"):
        raise PrimeError(f"ROS 2 topic names given here are absolute: {topic!r} does not start with '/'")
    return ROS_TOPIC_PREFIX + topic


def ros_qos(*, latched: bool = False, depth: int = DEFAULT_DEPTH, reliable: bool = True) -> Qos:
    """ROS 2's QoS profile as rmw_cyclonedds maps it: reliable, volatile, keep-last ``depth`` (the default
    profile), or transient-local for a latched topic."""
    policies: list[Any] = [
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
    return Qos(*policies)


def take(reader: DataReader, n: int = 64, **conditions: Any) -> list[Any]:
    """Up to ``n`` samples from ``reader``, without the data-less ones (a writer gone away, an instance
    disposed) that DDS also delivers."""
    return [s for s in reader.take(N=n, **conditions) if not isinstance(s, InvalidSample)]


class DdsNode:
    """A DDS participant with ROS 2 conventions; ``close`` deletes it and everything it created."""

    def __init__(self, domain: int | None = None) -> None:
        self.domain = domain_id(domain)
        try:
            self.participant = DomainParticipant(self.domain)
        except DDSException as exc:
            raise PrimeError(f"cannot join DDS domain {self.domain}: {exc} (check CYCLONEDDS_URI and the network "
                             "interfaces)") from None
        self._topics: dict[str, Topic] = {}
        self._entities: list[Any] = []

    def _topic(self, topic: str, data_type: type) -> Topic:
        name = dds_topic_name(topic)
        if name not in self._topics:
            self._topics[name] = Topic(self.participant, name, data_type)
        return self._topics[name]

    def writer(self, topic: str, data_type: type, *, latched: bool = False, depth: int = DEFAULT_DEPTH) -> DataWriter:
        writer = DataWriter(self.participant, self._topic(topic, data_type), qos=ros_qos(latched=latched, depth=depth))
        self._entities.append(writer)
        return writer

    def reader(self, topic: str, data_type: type, *, latched: bool = False, depth: int = DEFAULT_DEPTH) -> DataReader:
        reader = DataReader(self.participant, self._topic(topic, data_type), qos=ros_qos(latched=latched, depth=depth))
        self._entities.append(reader)
        return reader

    def close(self) -> None:
        """Delete the participant (and with it every reader, writer and topic: peers see them go at once)."""
        participant = getattr(self, "participant", None)
        if participant is None:
            return
        self._entities.clear()
        self._topics.clear()
        self.participant = None
        participant.__del__()  # dds_delete now, not whenever the collector gets to it

    def __enter__(self) -> DdsNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
