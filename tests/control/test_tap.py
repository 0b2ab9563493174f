"""The tick tap: each tick handed to another thread at the end of the tick, never waiting on it."""

from __future__ import annotations

import threading

import numpy as np

from humanoid_prime.control.tap import TickTap
from humanoid_prime.modes import Mode


class Consumer:
    def __init__(self, stuck: bool = False) -> None:
        self.ticks: list[tuple[float, np.ndarray]] = []
        self.modes: list[str] = []
        self.statuses = 0
        self.remote = []
        self.release = threading.Event()
        self.entered = threading.Event()
        self.stuck = stuck
        if not stuck:
            self.release.set()

    def on_tick(self, sample) -> None:
        self.entered.set()
        self.release.wait()
        self.ticks.append((sample.stamp, sample.data.copy()))

    def on_mode(self, message) -> None:
        self.modes.append(message.mode)

    def on_safety(self, message) -> None:
        self.statuses += 1

    def on_remote(self, message) -> None:
        self.remote.append(message)


def test_each_tick_brings_its_state_and_the_command_written(manager, plant):
    consumer = Consumer()
    tap = TickTap(manager, consumer, name="test", commands=True, remote=True)
    manager.request_mode(Mode.DAMPING)
    plant.position[:] = np.arange(14) * 0.01
    for k in range(5):
        manager.tick(k * 0.01)
    tap.close()
    assert [stamp for stamp, _ in consumer.ticks] == [k * 0.01 for k in range(5)]
    stamp, data = consumer.ticks[-1]
    np.testing.assert_array_equal(data[0], np.arange(14) * 0.01)
    np.testing.assert_array_equal(data[3:], plant.written[-1])  # the command of that very tick
    assert consumer.modes == ["ZERO_TORQUE", "DAMPING"] and consumer.statuses >= 1


def test_a_stuck_consumer_never_holds_the_tick_and_the_drops_are_counted(manager):
    consumer = Consumer(stuck=True)
    drops = []
    tap = TickTap(manager, consumer, name="test", on_drop=drops.append, slots=8)
    manager.tick(0.0)
    assert consumer.entered.wait(30)
    for k in range(1, 20):
        manager.tick(k * 0.01)  # returns: nothing here waits on the consumer
    assert tap.dropped == 20 - 8 and drops[-1] == 12
    consumer.release.set()
    tap.close()
    assert len(consumer.ticks) == 8


def test_a_tick_cut_short_is_not_handed_over(manager):
    consumer = Consumer()
    tap = TickTap(manager, consumer, name="test", commands=True)
    manager.tick(0.0)
    manager.topics.publish(manager.config.joint_states_topic, manager.controllers["joint_state_broadcaster"].message)
    tap.close()  # the second "tick" published its state but never wrote: it is not recorded as a tick
    assert len(consumer.ticks) == 1


def test_a_consumer_error_is_counted_and_the_tap_goes_on(manager):
    consumer = Consumer()
    calls = []

    def failing(sample):
        calls.append(sample.stamp)
        if len(calls) == 1:
            raise OSError("disk full")

    consumer.on_tick = failing
    tap = TickTap(manager, consumer, name="test")
    manager.tick(0.0)
    manager.tick(0.01)
    tap.close()
    assert calls == [0.0, 0.01] and tap.errors == 1 and tap.last_error == "OSError: disk full"
