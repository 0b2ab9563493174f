"""A policy sender for Prime's REMOTE mode over DDS: the reference client behind ``prime remote``, and the
example to copy for your own.

It is an ordinary DDS participant with ROS 2's conventions, node ``prime_remote`` on the graph, in the
namespace of the Prime it drives: it publishes
``prime_msgs/MitCommand`` on ``/remote_policy_controller/command`` (all 14 joints, canonical order, every
period) and ``std_msgs/String`` on ``/prime/mode_request``, and reads ``/prime/joint_states``,
``/control_mode`` and ``/safety_status``. The same works from rclpy with ``prime_msgs`` built in a colcon
workspace; this module needs only Python and Cyclone DDS.

The motion starts where the robot is: the first command targets the measured position, and the target
moves to the chosen pose over ``ramp`` seconds before the wave starts, so no joint is ever asked to jump.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.topics import CONTROL_MODE, JOINT_STATES, REMOTE_COMMAND, SAFETY_STATUS
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.graph import MODE_REQUEST
from humanoid_prime.dds.node import DdsNode, take

Array = npt.NDArray[np.float64]

NODE_NAME = "prime_remote"


@dataclass
class Motion:
    """Targets over time: from ``start`` to ``pose`` in ``ramp`` seconds (smoothstep), then ``pose`` plus a
    sine of ``amplitude`` rad at ``frequency`` Hz on the ``wave`` joints (clipped into the joint limits)."""

    start: Array
    pose: Array
    lower: Array
    upper: Array
    wave: Array  # bool per joint
    amplitude: float = 0.0
    frequency: float = 0.5
    ramp: float = 2.0

    def target(self, t: float) -> tuple[Array, Array]:
        """Position and velocity targets ``t`` seconds after the start."""
        if t < self.ramp:
            s = t / self.ramp
            blend, rate = s * s * (3 - 2 * s), 6 * s * (1 - s) / self.ramp
            return self.start + blend * (self.pose - self.start), rate * (self.pose - self.start)
        phase = 2 * math.pi * self.frequency * (t - self.ramp)
        position = self.pose + np.where(self.wave, self.amplitude * math.sin(phase), 0.0)
        velocity = np.where(self.wave, self.amplitude * 2 * math.pi * self.frequency * math.cos(phase), 0.0)
        clipped = np.clip(position, self.lower, self.upper)
        return clipped, np.where(clipped == position, velocity, 0.0)


@dataclass
class Seen:
    """What the client has received from Prime."""

    joint_states: int = 0
    first_joint_state_s: float | None = None  # monotonic time of the first and the latest joint state
    last_joint_state_s: float | None = None
    position: Array | None = None
    stamp: float | None = None
    modes: list[str] = field(default_factory=list)
    safety: list[tuple[str, str, str]] = field(default_factory=list)  # (status name, level, message), latest

    @property
    def mode(self) -> str | None:
        return self.modes[-1] if self.modes else None

    def joint_state_rate(self) -> float | None:
        first, last = self.first_joint_state_s, self.last_joint_state_s
        if self.joint_states < 2 or first is None or last is None or first == last:
            return None
        return (self.joint_states - 1) / (last - first)


class RemoteClient:
    """Talks to a running Prime over DDS. ``poll()`` takes what arrived; ``send()`` streams one command."""

    def __init__(self, robot: Robot, *, domain: int | None = None, namespace: str = "/",
                 command_topic: str = REMOTE_COMMAND, clock: Callable[[], float] = time.monotonic) -> None:
        self.names = list(robot.names)
        self.clock = clock
        self.node = DdsNode(domain, name=NODE_NAME, namespace=namespace)  # the Prime's topics are under it too
        try:
            self.commands = self.node.writer(command_topic, msg.MitCommand)
            self.mode_requests = self.node.writer(MODE_REQUEST, msg.String)
            self.joint_states = self.node.reader(JOINT_STATES, msg.JointState)
            self.control_mode = self.node.reader(CONTROL_MODE, msg.String, latched=True, depth=1)
            self.safety_status = self.node.reader(SAFETY_STATUS, msg.DiagnosticArray, latched=True, depth=1)
        except BaseException:
            self.node.close()
            raise
        self.seen = Seen()
        self.sent = 0
        self.on_joint_state: Callable[[float, Array], None] | None = None  # (arrival, positions)

    def poll(self) -> None:
        for sample in take(self.joint_states):
            if list(sample.name) != self.names:
                continue  # not Prime's joint order: not ours to compare
            now = self.clock()
            seen = self.seen
            seen.joint_states += 1
            seen.first_joint_state_s = seen.first_joint_state_s if seen.first_joint_state_s is not None else now
            seen.last_joint_state_s = now
            seen.position = np.asarray(sample.position, dtype=np.float64)
            seen.stamp = msg.seconds(sample.header.stamp)
            if self.on_joint_state is not None:
                self.on_joint_state(now, seen.position)
        for mode in take(self.control_mode):
            self.seen.modes.append(mode.data)
        for status in take(self.safety_status):
            self.seen.safety = [(s.name, msg.LEVEL_NAMES.get(s.level, str(s.level)), s.message) for s in status.status]

    def wait_for_joint_states(self, timeout: float, sleep: Callable[[float], None] = time.sleep) -> bool:
        """Poll until a joint state of Prime arrived or ``timeout`` seconds passed."""
        deadline = self.clock() + timeout
        while self.seen.position is None and self.clock() < deadline:
            self.poll()
            sleep(0.01)
        return self.seen.position is not None

    def send(self, position: Array, velocity: Array, effort: Array, stiffness: Array,
             damping: Array, stamp: float | None = None) -> None:
        self.commands.write(msg.MitCommand(
            header=msg.Header(stamp=msg.stamp(time.time() if stamp is None else stamp)), name=self.names,
            position=[float(v) for v in position], velocity=[float(v) for v in velocity],
            effort=[float(v) for v in effort], stiffness=[float(v) for v in stiffness],
            damping=[float(v) for v in damping]))
        self.sent += 1

    def request_mode(self, mode: str) -> None:
        self.mode_requests.write(msg.String(data=mode))

    def close(self) -> None:
        self.node.close()

    def __enter__(self) -> RemoteClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Tracking:
    """How the measured positions of the ``joints`` follow the targets, from ``since`` on, judged at arrival.

    A joint held by a finite stiffness against gravity sits a steady distance from its target (``offset``,
    about 0.15 rad for a shoulder at kp 20); what is left once that is taken out (``residual_rms``) is how well
    the motion is followed, and ``range_ratio`` is the measured swing over the commanded swing."""

    def __init__(self, joints: Array, target: Callable[[float], Array], since: float) -> None:
        self.joints = joints
        self.target = target
        self.since = since
        self.samples = 0
        self.max_error = 0.0
        n = int(joints.sum())
        self._sum = np.zeros(n)
        self._square_sum = np.zeros(n)
        self._measured = np.array([np.inf, -np.inf])[:, None] * np.ones(n)  # rows: min, max
        self._commanded = self._measured.copy()

    def __call__(self, arrival: float, position: Array) -> None:
        if arrival < self.since or not self.joints.any():
            return
        target = self.target(arrival)[self.joints]
        measured = position[self.joints]
        error = measured - target
        self.samples += 1
        self.max_error = max(self.max_error, float(np.abs(error).max()))
        self._sum += error
        self._square_sum += error * error
        for values, bounds in ((measured, self._measured), (target, self._commanded)):
            np.minimum(bounds[0], values, out=bounds[0])
            np.maximum(bounds[1], values, out=bounds[1])

    def as_dict(self) -> dict[str, float | int | None]:
        if not self.samples:
            return {"samples": 0, "max_rad": None, "offset_rad": None, "residual_rms_rad": None, "range_ratio": None}
        mean = self._sum / self.samples
        residual = np.sqrt(np.maximum(self._square_sum / self.samples - mean * mean, 0.0))
        commanded = self._commanded[1] - self._commanded[0]
        measured = self._measured[1] - self._measured[0]
        moving = commanded > 1e-6
        ratio = float(np.min(measured[moving] / commanded[moving])) if moving.any() else None
        return {"samples": self.samples, "max_rad": self.max_error, "offset_rad": float(np.abs(mean).max()),
                "residual_rms_rad": float(residual.max()), "range_ratio": ratio}
