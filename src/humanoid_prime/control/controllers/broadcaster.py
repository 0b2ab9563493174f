"""Publishes the measured joint state on ``/prime/joint_states`` every tick; claims no command."""

from __future__ import annotations

import numpy as np

from humanoid_prime.config.robot import Robot
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
        # One message, rewritten in place every tick (subscribers copy what they keep).
        self.message = JointState(stamp=0.0, name=robot.names, position=np.zeros(robot.n),
                                  velocity=np.zeros(robot.n), effort=np.zeros(robot.n))

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        message = self.message
        np.copyto(message.position, state.position)
        np.copyto(message.velocity, state.velocity)
        np.copyto(message.effort, state.effort)
        message.stamp = now
        self.topics.publish(self.topic, message)
