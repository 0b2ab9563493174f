"""Publishes the measured joint state on ``/prime/joint_states`` every tick; claims no command."""

from __future__ import annotations

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import Copy
from humanoid_prime.control.controller import Controller
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.topics import JOINT_STATES, JointState, TopicBus
from humanoid_prime.modes import JOINT_STATE_BROADCASTER


class JointStateBroadcaster(Controller):
    claims_commands = False

    def __init__(self, topic: str = JOINT_STATES) -> None:
        super().__init__(JOINT_STATE_BROADCASTER, None)
        self.topic = topic

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        self.topics = topics
        # One message, rewritten in place every tick (subscribers copy what they keep); its three arrays are
        # the rows of one, so the tick copies the state in one call.
        self._data = np.zeros((3, robot.n))
        position, velocity, effort = self._data
        self.message = JointState(stamp=0.0, name=robot.names, position=position, velocity=velocity, effort=effort)
        self._copy = Copy()

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        message = self.message
        self._copy.run(self._data, state.data)
        message.stamp = now
        self.topics.publish(self.topic, message)
