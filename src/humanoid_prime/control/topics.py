"""In-process topics with the ROS 2 names and message shapes, so a ROS 2 bridge is a mapping.

Publishing calls subscribers synchronously in the publisher's thread and keeps the latest message.
Subscribers must be quick and must copy a message they keep: hot-path publishers reuse one message.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar, cast

import numpy as np
import numpy.typing as npt

from humanoid_prime.control._tick import Copy
from humanoid_prime.control.flags import Level

JOINT_STATES = "/prime/joint_states"
CONTROL_MODE = "/control_mode"
SAFETY_STATUS = "/safety_status"
REMOTE_COMMAND = "/remote_policy_controller/command"
_M = TypeVar("_M")


@dataclass
class JointState:
    """sensor_msgs/JointState."""

    stamp: float
    name: tuple[str, ...]
    position: npt.NDArray[np.float64]
    velocity: npt.NDArray[np.float64]
    effort: npt.NDArray[np.float64]


@dataclass
class MitCommand:
    """The MIT command message: one value per joint, in ``joint_names`` order."""

    joint_names: tuple[str, ...]
    position: npt.NDArray[np.float64]
    velocity: npt.NDArray[np.float64]
    effort: npt.NDArray[np.float64]
    stiffness: npt.NDArray[np.float64]
    damping: npt.NDArray[np.float64]
    stamp: float = 0.0


@dataclass(frozen=True)
class ControlMode:
    mode: str
    controller: str
    stamp: float = 0.0


@dataclass(frozen=True)
class SafetyStatus:
    """Latched: published on change. ``flags`` maps a source key to a human-readable problem, ``levels`` the
    same key to how bad it is (``Level.WARN`` or ``Level.ERROR``)."""

    ok: bool
    flags: dict[str, str] = field(default_factory=dict)
    stamp: float = 0.0
    levels: dict[str, Level] = field(default_factory=dict)

    @property
    def faulted(self) -> bool:
        """Some flag is an error (a warning alone is not a fault)."""
        return any(level is Level.ERROR for level in self.levels.values())


class TopicBus:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        # A topic is a name: what it carries is agreed between its publishers and subscribers (a DDS message
        # may stand in for ours, with the same fields), so the bus stores callbacks of any one argument.
        self._subscribers: dict[str, list[Callable[..., None]]] = {}  # type: ignore[explicit-any]  # see above
        self._latest: dict[str, object] = {}

    def publish(self, topic: str, message: object) -> None:
        self._latest[topic] = message
        for callback in self._subscribers.get(topic, ()):
            callback(message)

    def subscribe(self, topic: str, callback: Callable[[_M], None], *, latched: bool = False) -> None:
        """Call ``callback`` for every message; with ``latched``, also once now with the latest one."""
        with self._lock:
            self._subscribers.setdefault(topic, []).append(callback)
        if latched and topic in self._latest:
            callback(cast(_M, self._latest[topic]))  # what the topic carries, as agreed (see __init__)

    def unsubscribe(self, topic: str, callback: Callable[[_M], None]) -> None:
        with self._lock:
            subs = self._subscribers.get(topic, [])
            if callback in subs:
                subs.remove(callback)

    def latest(self, topic: str) -> object:
        return self._latest.get(topic)


class Snapshot:
    """The latest joint positions, mode and safety flags on a topic bus, for views and the control socket's
    ``state`` request. Per tick it costs one copy of 14 positions; ``as_dict`` may be called from any thread."""

    def __init__(self, topics: TopicBus, names: tuple[str, ...], joint_states_topic: str = JOINT_STATES) -> None:
        self.topics = topics
        self.names = names
        self.joint_states_topic = joint_states_topic
        self.position = np.full(len(names), np.nan)
        self._copy = Copy()
        self.stamp = float("nan")
        self.mode: str | None = None
        self.status: SafetyStatus | None = None
        topics.subscribe(joint_states_topic, self._on_joint_states)
        topics.subscribe(CONTROL_MODE, self._on_mode, latched=True)
        topics.subscribe(SAFETY_STATUS, self._on_safety, latched=True)

    def _on_joint_states(self, message: JointState) -> None:
        self._copy.run(self.position, message.position)
        self.stamp = message.stamp

    def _on_mode(self, message: ControlMode) -> None:
        self.mode = message.mode

    def _on_safety(self, message: SafetyStatus) -> None:
        self.status = message

    def as_dict(self) -> dict[str, object]:
        status = self.status
        return {"names": list(self.names), "position": [None if v != v else float(v) for v in self.position],
                "stamp": self.stamp, "mode": self.mode,
                "flags": dict(status.flags) if status is not None else {},
                "levels": {k: v.name for k, v in status.levels.items()} if status is not None else {}}

    def detach(self) -> None:
        self.topics.unsubscribe(self.joint_states_topic, self._on_joint_states)
        self.topics.unsubscribe(CONTROL_MODE, self._on_mode)
        self.topics.unsubscribe(SAFETY_STATUS, self._on_safety)
