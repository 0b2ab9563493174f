"""Where a run meets the ROS 2 graph: the domain (``--domain`` over ``ROS_DOMAIN_ID`` over 0), the node's
namespace, and ROS 2's discovery conventions, turned into Cyclone DDS configuration. Nothing here imports DDS:
the CLI checks all of it before anything starts.

Discovery follows ROS 2 (Iron and later) as rmw_cyclonedds applies it: ``ROS_AUTOMATIC_DISCOVERY_RANGE``
SUBNET (the default: multicast, plus any ``ROS_STATIC_PEERS``), LOCALHOST (no multicast; this machine and the
static peers), OFF (nobody) or SYSTEM_DEFAULT (Cyclone's own configuration untouched); ``ROS_LOCALHOST_ONLY=1``
(deprecated in Jazzy) means LOCALHOST. ``CYCLONEDDS_URI`` is applied after, so a user's file has the last word.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass

from humanoid_prime.errors import PrimeError

DOMAIN_ENV = "ROS_DOMAIN_ID"
RANGE_ENV = "ROS_AUTOMATIC_DISCOVERY_RANGE"
PEERS_ENV = "ROS_STATIC_PEERS"
LOCALHOST_ONLY_ENV = "ROS_LOCALHOST_ONLY"
MAX_DOMAIN_ID = 232  # the largest ROS 2 domain id whose ports stay below 65535 (ROS 2 "The ROS_DOMAIN_ID")
RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
MAX_AUTO_PARTICIPANT_INDEX = 32  # participants found per machine without multicast (rmw_cyclonedds' choice)
FAST_DDS_VENDOR = "1.15"  # eProsima's RTPS vendor id
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def domain_id(given: int | None = None) -> int:
    """``given``, else ``ROS_DOMAIN_ID``, else 0; refused with the reason when outside ROS 2's range."""
    source = "--domain"
    if given is None:
        text = os.environ.get(DOMAIN_ENV, "").strip()
        if not text:
            return 0
        source = DOMAIN_ENV
        try:
            given = int(text)
        except ValueError:
            raise PrimeError(f"{DOMAIN_ENV}={text!r} is not a domain id (an integer 0-{MAX_DOMAIN_ID})") from None
    if not 0 <= given <= MAX_DOMAIN_ID:
        raise PrimeError(f"{source} {given} is outside the ROS 2 domain ids 0-{MAX_DOMAIN_ID}")
    return given


def node_namespace(text: str | None) -> str:
    """``--namespace`` as ROS 2 writes a node's namespace: ``''``/``'/'`` -> ``'/'``, ``left`` -> ``'/left'``,
    ``a/b`` -> ``'/a/b'``; each part a ROS 2 name (letters, digits, underscores, not starting with a digit)."""
    stripped = (text or "").strip().strip("/")
    parts = stripped.split("/") if stripped else []
    for part in parts:
        if not _NAME.fullmatch(part):
            raise PrimeError(f"--namespace {text!r}: {part!r} is not a ROS 2 name (letters, digits and underscores, "
                             "not starting with a digit)")
    return "/" + "/".join(parts)


def in_namespace(namespace: str, topic: str) -> str:
    """``topic`` (absolute) under ``namespace``: ``/left`` and ``/prime/joint_states`` give
    ``/left/prime/joint_states``."""
    if not topic.startswith("/"):
        raise PrimeError(f"ROS 2 topic names given here are absolute: {topic!r} does not start with '/'")
    return topic if namespace == "/" else namespace + topic


@dataclass(frozen=True)
class Discovery:
    """ROS 2's discovery settings of this process's environment."""

    range: str = "SUBNET"
    static_peers: tuple[str, ...] = ()

    def cyclone_xml(self) -> str:
        """Cyclone DDS configuration for these settings (rmw_cyclonedds' mapping), with the compatibility setting
        every Prime participant needs: Fast DDS 3 advertises XTypes type information whose sequence members
        Cyclone rejects, after which it never matches; ignoring Fast DDS's type information reduces matching
        to the type names, as ROS 2 itself matches."""
        general = discovery = ""
        if self.range in ("LOCALHOST", "OFF"):
            general = "<General><AllowMulticast>false</AllowMulticast></General>"
        if self.range == "OFF":
            discovery = (f"<Discovery><ParticipantIndex>none</ParticipantIndex><Tag>ros_discovery_off_{os.getpid()}"
                         "</Tag></Discovery>")
        elif self.range != "SYSTEM_DEFAULT":
            from xml.sax.saxutils import quoteattr  # imports urllib.request: 0.1 s the CLI's options need not pay

            peers = (["localhost"] if self.range == "LOCALHOST" else []) + list(self.static_peers)
            listed = "".join(f"<Peer address={quoteattr(peer)}/>" for peer in peers)
            discovery = ("<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>"
                         f"{MAX_AUTO_PARTICIPANT_INDEX}</MaxAutoParticipantIndex>"
                         + (f"<Peers>{listed}</Peers>" if listed else "") + "</Discovery>")
        compatibility = (f"<Compatibility><IgnoreTypeInformation>{FAST_DDS_VENDOR}</IgnoreTypeInformation>"
                         "</Compatibility>")
        return f'<CycloneDDS><Domain Id="any">{general}{compatibility}{discovery}</Domain></CycloneDDS>'

    def describe(self) -> str:
        peers = f", static peers {', '.join(self.static_peers)}" if self.static_peers else ""
        return f"discovery {self.range.lower()}{peers}"


def discovery(env: Mapping[str, str] | None = None) -> Discovery:
    """The discovery settings in ``env`` (default: this process's environment), as rcl reads them."""
    env = os.environ if env is None else env
    text = env.get(RANGE_ENV, "").strip()
    peers = tuple(peer.strip() for peer in env.get(PEERS_ENV, "").split(";") if peer.strip())
    if env.get(LOCALHOST_ONLY_ENV, "").strip() == "1":
        return Discovery("LOCALHOST")  # as rcl (Jazzy): the deprecated variable wins, static peers are ignored
    if not text:
        return Discovery("SUBNET", peers)
    if text.upper() not in RANGES:
        raise PrimeError(f"{RANGE_ENV}={text!r} is not one of {', '.join(RANGES)}")
    return Discovery(text.upper(), peers if text.upper() in ("SUBNET", "LOCALHOST") else ())


def cyclone_config(settings: Discovery) -> str:
    """The configuration a Prime participant's domain is created with: ``settings`` first, then
    ``CYCLONEDDS_URI`` (a file or XML; later fragments override earlier ones)."""
    user = os.environ.get("CYCLONEDDS_URI", "").strip()
    return settings.cyclone_xml() + (f",{user}" if user else "")
