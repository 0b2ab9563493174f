"""A tap on the control loop: what every tick produced, handed to another thread without ever waiting.

The DDS bridge and the recorder both need each tick's joint state (and the recorder the MIT command that was
written), the mode and the safety status as they change, and the remote commands as they arrive, and neither
may delay the tick. The tap copies each tick's joint state into a slot of a fixed ring (and, at the end of the
tick, after ``write()``, the command), then hands the slot to its consumer's thread, which runs while the loop
waits for its next period. When every slot is taken (the consumer fell behind) the tick's sample is dropped and
counted; the tick goes on. A tap made with ``wait`` (a run with no real-time deadline, such as a simulation as
fast as it goes) waits for a free slot instead, so nothing is dropped.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import CONTROL_MODE, SAFETY_STATUS, ControlMode, JointState, MitCommand, SafetyStatus

SLOTS = 64  # ticks in flight to the consumer thread before one is dropped


@dataclass(frozen=True)
class TickSample:
    """One tick as the consumer sees it: ``data`` rows 0-2 the measured position, velocity, effort; rows 3-7
    (when the tap takes commands) the position, velocity, effort, stiffness, damping written. The arrays stay
    valid only during the consumer's call."""

    stamp: float
    data: npt.NDArray[np.float64]
    queued_at: float


class Consumer(Protocol):
    def on_tick(self, sample: TickSample) -> None: ...
    def on_mode(self, message: ControlMode) -> None: ...
    def on_safety(self, message: SafetyStatus) -> None: ...
    def on_remote(self, message: MitCommand) -> None: ...


class TickTap:
    """Attach ``consumer`` to ``manager`` (see the module docstring); ``close`` detaches and drains."""

    def __init__(self, manager: ControllerManager, consumer: Consumer, *, name: str, commands: bool = False,
                 remote: bool = False, on_drop: Callable[[int], None] | None = None, slots: int = SLOTS,
                 clock: Callable[[], float] = time.perf_counter, wait: bool = False) -> None:
        self.manager = manager
        self.wait = wait
        self._freed = threading.Event()  # the consumer took a slot's sample (for ``wait``)
        self.consumer = consumer
        self.commands = commands
        self.clock = clock
        self.on_drop = on_drop  # called in the tick thread with the count, after each drop
        self.slots = slots
        self.dropped = 0
        self.errors = 0
        self.last_error = ""
        n = manager.robot.n
        self._ring = np.zeros((slots, 8 if commands else 3, n))
        self._stamps = np.zeros(slots)
        self._queued_at = np.zeros(slots)
        self._head = 0  # written by the tick thread only
        self._tail = 0  # written by the consumer thread only
        self._slot: int | None = None  # this tick's slot, handed over at its end
        self._pending: list[ControlMode | SafetyStatus] = []
        # a tick's slot, a latched message, a REMOTE command, or None: the end
        self._work: queue.SimpleQueue[int | ControlMode | SafetyStatus | MitCommand | None] = queue.SimpleQueue()
        self._joint_states = manager.config.joint_states_topic
        self._remote_topic = manager.config.remote.topic if remote else None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        topics = manager.topics
        topics.subscribe(self._joint_states, self._on_joint_states)
        topics.subscribe(CONTROL_MODE, self._on_latched, latched=True)
        topics.subscribe(SAFETY_STATUS, self._on_latched, latched=True)
        if self._remote_topic is not None:
            topics.subscribe(self._remote_topic, self._on_remote)
        manager.add_end_of_tick(self._end_of_tick)
        self._closed = False
        self._end_of_tick()  # the latched mode and status it was given on subscribing

    # ---- the tick thread -------------------------------------------------------------------------

    def _on_joint_states(self, message: JointState) -> None:
        head = self._head
        while self.wait and head - self._tail >= self.slots and self._thread.is_alive():
            self._freed.wait(0.1)
            self._freed.clear()
        if head - self._tail >= self.slots:
            self.dropped += 1
            self._slot = None
            if self.on_drop is not None:
                self.on_drop(self.dropped)
            return
        k = head % self.slots
        row = self._ring[k]
        row[0] = message.position
        row[1] = message.velocity
        row[2] = message.effort
        self._stamps[k] = message.stamp
        self._head = head + 1
        self._slot = k

    def _on_latched(self, message: ControlMode | SafetyStatus) -> None:  # published by the tick thread
        self._pending.append(message)

    def _end_of_tick(self) -> None:
        k = self._slot
        if k is not None:
            self._slot = None
            if self.commands:
                self._ring[k, 3:] = self.manager.resources.command.data
            self._queued_at[k] = self.clock()
            self._work.put(k)
        if self._pending:
            pending, self._pending = self._pending, []
            for item in pending:
                self._work.put(item)

    def _on_remote(self, message: MitCommand) -> None:  # any thread; the message may be reused: copy it
        self._work.put(MitCommand(tuple(message.joint_names), _copy(message.position), _copy(message.velocity),
                                  _copy(message.effort), _copy(message.stiffness), _copy(message.damping),
                                  stamp=message.stamp))

    # ---- the consumer thread ---------------------------------------------------------------------

    def _run(self) -> None:
        consumer = self.consumer
        while True:
            item = self._work.get()
            if item is None:
                return
            try:
                if isinstance(item, int):
                    consumer.on_tick(TickSample(float(self._stamps[item]), self._ring[item],
                                                float(self._queued_at[item])))
                    self._tail += 1
                    self._freed.set()
                elif isinstance(item, ControlMode):
                    consumer.on_mode(item)
                elif isinstance(item, SafetyStatus):
                    consumer.on_safety(item)
                elif isinstance(item, MitCommand):
                    consumer.on_remote(item)
            except Exception as exc:  # counted and kept; the loop and the tap go on
                if isinstance(item, int):
                    self._tail += 1
                    self._freed.set()
                self.errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}"

    def close(self, timeout: float = 10.0) -> None:
        """Detach from the loop, let the consumer finish what is queued, stop its thread."""
        if self._closed:
            return
        self._closed = True
        topics = self.manager.topics
        self.manager.remove_end_of_tick(self._end_of_tick)
        topics.unsubscribe(self._joint_states, self._on_joint_states)
        topics.unsubscribe(CONTROL_MODE, self._on_latched)
        topics.unsubscribe(SAFETY_STATUS, self._on_latched)
        if self._remote_topic is not None:
            topics.unsubscribe(self._remote_topic, self._on_remote)
        if self._slot is not None:  # a tick cut short (an exception, Ctrl-C) before its write: not handed over
            self._slot = None
            self._head -= 1
        self._end_of_tick()
        self._work.put(None)
        self._thread.join(timeout)


def _copy(values: npt.ArrayLike) -> npt.NDArray[np.float64]:
    return np.array(values, dtype=np.float64)
