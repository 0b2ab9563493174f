"""Reading a Prime recording back: the per-tick series of a run (measured state and the MIT command written),
and its modes, for plots and replays."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt
from mcap.reader import make_reader

from humanoid_prime.control.interfaces import COMMAND_NAMES, STATE_NAMES
from humanoid_prime.control.topics import CONTROL_MODE, JOINT_STATES
from humanoid_prime.dds import messages as msg
from humanoid_prime.errors import PrimeError
from humanoid_prime.record.topics import COMMAND as COMMAND_TOPIC

Floats = npt.NDArray[np.float64]


@dataclass
class Recording:
    """Per-tick arrays (ticks x joints) in the recording's joint order; times in seconds from the first joint
    state, by the time each message was recorded (one clock for every topic)."""

    path: Path
    names: tuple[str, ...]
    time: Floats
    position: Floats
    velocity: Floats
    effort: Floats
    command_time: Floats
    command: Floats  # ticks x 5 x joints: position, velocity, effort, stiffness, damping
    modes: list[tuple[float, str]] = field(default_factory=list)  # (time, mode) as the mode changed

    def index(self, joint: str) -> int:
        if joint not in self.names:
            raise PrimeError(f"{self.path}: no joint {joint!r} in the recording (joints: {', '.join(self.names)})")
        return self.names.index(joint)

    def commanded_torque(self) -> Floats:
        """The MIT law's torque at each commanded tick, on the measured state of the same tick:
        effort + stiffness (position - q) + damping (velocity - dq); NaN where no command was written."""
        n = min(len(self.command_time), len(self.time))
        c = self.command[:n]
        with np.errstate(invalid="ignore"):
            return c[:, 2] + c[:, 3] * (c[:, 0] - self.position[:n]) + c[:, 4] * (c[:, 1] - self.velocity[:n])


def read_recording(path: str | Path, joints: tuple[str, ...] | None = None) -> Recording:
    """The joint states, commands and modes of a Prime recording; one clear error when it is not one, when a
    message's arrays do not match its joints or the first message's, or (with ``joints``, the robot's) when it
    records other joints."""
    path = Path(path)
    states: list[msg.JointState] = []
    commands: list[msg.MitCommand] = []
    state_times: list[int] = []
    command_times: list[int] = []
    modes: list[tuple[float, str]] = []
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for _, channel, message in reader.iter_messages(topics=[JOINT_STATES, COMMAND_TOPIC, CONTROL_MODE]):
                if channel.topic == JOINT_STATES:
                    states.append(msg.JointState.deserialize(message.data))
                    state_times.append(message.log_time)
                elif channel.topic == COMMAND_TOPIC:
                    commands.append(msg.MitCommand.deserialize(message.data))
                    command_times.append(message.log_time)
                else:
                    modes.append((message.log_time, msg.String.deserialize(message.data).data))
    except OSError as exc:
        raise PrimeError(f"cannot read {path}: {exc.strerror}") from None
    except Exception as exc:  # the MCAP reader's and the decoder's errors alike: one line
        raise PrimeError(f"{path} is not a readable MCAP recording: {type(exc).__name__}: {exc}") from None
    if not states:
        raise PrimeError(f"{path}: no {JOINT_STATES} messages in it (is it a Prime recording?)")
    names = tuple(states[0].name)
    if not names:
        raise PrimeError(f"{path}: its joint states name no joints (is it a Prime recording?)")
    if joints is not None and names != joints:
        raise PrimeError(f"{path}: it records the joints {', '.join(names)}, not this robot's "
                         f"({', '.join(joints)}); give the recording of a Prime, or its --hardware file")
    t0 = state_times[0]
    series: tuple[tuple[str, Sequence[msg.JointState | msg.MitCommand], list[int], tuple[str, ...]], ...] = (
        (JOINT_STATES, states, state_times, STATE_NAMES), (COMMAND_TOPIC, commands, command_times, COMMAND_NAMES))
    for what, samples, times, fields in series:
        for k, sample in enumerate(samples):
            sizes = {len(getattr(sample, f)) for f in fields}
            if tuple(sample.name) != names or sizes != {len(names)}:
                raise PrimeError(f"{path}: {what} message {k} (at {(times[k] - t0) * 1e-9:.3f} s) has "
                                 f"{len(sample.name)} joint names and arrays of {sorted(sizes)} values, where the "
                                 f"recording's joints are {len(names)}: not a recording prime can read")

    def rows(samples: Sequence[msg.JointState | msg.MitCommand], fields: tuple[str, ...]) -> Floats:
        return np.array([[getattr(s, f) for f in fields] for s in samples], dtype=np.float64)

    def seconds(times: list[int]) -> Floats:
        """Log times (ns) in seconds from the first joint state, the difference taken exactly, in integers."""
        return (np.array(times, dtype=np.int64) - t0).astype(np.float64) * 1e-9

    state = rows(states, STATE_NAMES)
    command = rows(commands, COMMAND_NAMES) if commands else np.zeros((0, len(COMMAND_NAMES), len(names)))
    return Recording(path, names, seconds(state_times), state[:, 0], state[:, 1], state[:, 2],
                     seconds(command_times), command, [((t - t0) * 1e-9, mode) for t, mode in modes])
