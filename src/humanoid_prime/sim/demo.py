"""The simulated Prime at work: the loop that runs the controllers on ``MujocoSystem``, and the
scripted demonstration that visits every mode in 20 simulated seconds.

Controllers see simulated time (``tick(now=sim_time)``); the loop is paced against the wall clock
(real time) or runs as fast as the machine allows. Tick cost is measured on the wall clock.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from humanoid_prime.config.calibration import identity_calibration
from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.description import MUJOCO_BLOCK
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.controller import gain_rows, pose_array
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.rate import Rate
from humanoid_prime.control.topics import MitCommand, TopicBus
from humanoid_prime.drivers.mujoco.system import MujocoSystem
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.registry import ComponentSettings
from humanoid_prime.runtime.session import assemble


@dataclass(frozen=True)
class Step:
    at: float  # simulated seconds
    mode: Mode


DEMO_SECONDS = 20.0
# ZERO_TORQUE is active from the staged start: the raised arms fall, DAMPING catches them, STANDBY
# lifts them to the ready pose, the policy runs, the remote stream waves, DAMPING ends the show.
SCHEDULE: tuple[Step, ...] = (
    Step(0.0, Mode.ZERO_TORQUE),
    Step(2.0, Mode.DAMPING),
    Step(4.0, Mode.STANDBY),
    Step(8.0, Mode.LOCOMOTION),
    Step(12.0, Mode.REMOTE),
    Step(17.0, Mode.DAMPING),
)
# Where the arms are when the simulated robot powers up: raised forward, elbows bent. Raised high enough that each
# joint alone can sweep its whole range with the arm clear of the torso by more than the collision margin (the
# hands-free calibration starts here): lower, shoulder_roll's inner stop would put the upper arm into the torso.
START_POSE: dict[str, float] = {
    "left_shoulder_pitch": -1.0, "left_shoulder_roll": 0.15, "left_elbow_pitch": -0.9,
    "right_shoulder_pitch": -1.0, "right_shoulder_roll": -0.15, "right_elbow_pitch": -0.9,
}

# The remote stream: a slow wave around the locomotion default pose, the arms in opposite phase.
WAVE_AMPLITUDE_RAD: dict[str, float] = {
    "shoulder_pitch": 0.35, "shoulder_roll": 0.15, "shoulder_yaw": 0.3, "elbow_pitch": 0.4,
    "wrist_roll": 0.3, "wrist_pitch": 0.3, "wrist_yaw": 0.5,
}
WAVE_PERIOD_S = 3.0
WAVE_SITO_GAINS = (8.0, 0.5)  # kp, kd the stream asks of the Sito wrists (eRob take the mode gains)


class RemoteStream:
    """A scripted remote sender: one ``MitCommand`` per tick on the remote topic, stamped with ``now``.

    One message is rewritten in place every tick (subscribers copy what they keep).
    """

    def __init__(self, robot: Robot, topics: TopicBus, topic: str, center: np.ndarray, erob_gains: tuple[float, float],
                 *, period_s: float = WAVE_PERIOD_S) -> None:
        self.topics = topics
        self.topic = topic
        self.center = np.asarray(center, dtype=np.float64)
        self.omega = 2.0 * math.pi / period_s
        amplitude = np.array([WAVE_AMPLITUDE_RAD[j.name.split("_", 1)[1]] for j in robot.joints])
        room = np.minimum(self.center - robot.lower, robot.upper - self.center)
        sign = np.array([1.0 if j.name.startswith("left_") else -1.0 for j in robot.joints])
        self.amplitude = sign * np.minimum(amplitude, 0.9 * np.maximum(room, 0.0))
        stiffness, damping = gain_rows(robot, erob_gains, WAVE_SITO_GAINS)
        n = robot.n
        self.message = MitCommand(joint_names=robot.names, position=np.zeros(n), velocity=np.zeros(n),
                                  effort=np.zeros(n), stiffness=stiffness, damping=damping)
        self.published = 0

    def publish(self, now: float) -> None:
        message = self.message
        phase = self.omega * now
        np.multiply(self.amplitude, math.sin(phase), out=message.position)
        message.position += self.center
        np.multiply(self.amplitude, self.omega * math.cos(phase), out=message.velocity)
        message.stamp = now
        self.topics.publish(self.topic, message)
        self.published += 1


def build_simulation(robot: Robot, config: ControllersConfig, *, initial_pose: Mapping[str, float] | None = None,
                     model_path: str | Path | None = None, update_rate: float | None = None,
                     broadcaster_only: bool = False, clock: Callable[[], float] = time.perf_counter
                     ) -> tuple[MujocoSystem, ControllerManager]:
    """The description's ``MujocoSystem`` block and a controller manager over it (not started), at the simulation
    rate of ``config`` unless ``update_rate`` is given; the physics never steps slower than the loop."""
    rate = config.sim_update_rate if update_rate is None else update_rate
    settings = ComponentSettings(robot, identity_calibration(robot.hardware), update_rate=rate,
                                 physics_rate=max(rate, config.physics_rate), model_path=model_path,
                                 initial_pose=initial_pose)
    manager = assemble(settings, config, (MUJOCO_BLOCK,), broadcaster_only=broadcaster_only, clock=clock)
    (system,) = manager.resources.components
    return system, manager


def demo_stream(robot: Robot, config: ControllersConfig, manager: ControllerManager) -> RemoteStream:
    """The remote stream of the demonstration, centred on the locomotion default pose."""
    center = pose_array(robot, config.standby.poses[config.locomotion.default_pose])
    erob_gains = (config.remote.erob_kp, config.remote.erob_kd)
    return RemoteStream(robot, manager.topics, config.remote.topic, center, erob_gains)


class Simulation:
    """Runs a started controller manager on a ``MujocoSystem``, following a schedule of modes.

    ``lock`` (a context-manager factory, e.g. a viewer's lock) is held around each tick.
    """

    def __init__(self, system: MujocoSystem, manager: ControllerManager, *, schedule: Sequence[Step] = (),
                 stream: RemoteStream | None = None, realtime: bool = True,
                 lock: Callable[[], contextlib.AbstractContextManager[Any]] | None = None) -> None:
        self.system = system
        self.manager = manager
        self.schedule = tuple(sorted(schedule, key=lambda step: step.at))
        self.stream = stream
        self.realtime = realtime
        self.lock = lock
        self.following_schedule = True
        self.wall_seconds = 0.0
        self.stopped_by = ""
        self.now = system.sim_time  # the time of the latest tick
        self._next = 0
        self._running_since: float | None = None

    def wall_elapsed(self) -> float:
        """Wall seconds spent running so far."""
        if self._running_since is None:
            return self.wall_seconds
        return self.wall_seconds + time.perf_counter() - self._running_since

    def take_over(self) -> None:
        """An operator switched modes: stop following the schedule."""
        self.following_schedule = False

    def _follow_schedule(self, now: float) -> None:
        half_period = 0.5 * self.system.period
        while self._next < len(self.schedule) and self.schedule[self._next].at <= now + half_period:
            mode = self.schedule[self._next].mode
            self._next += 1
            if self.following_schedule and mode is not self.manager.active_mode:
                self.manager.request_mode(mode)

    def run(self, duration: float | None, *, stop: threading.Event | None = None,
            on_tick: Callable[[], None] | None = None) -> None:
        """Tick for ``duration`` simulated seconds (None: until ``stop`` is set or Ctrl-C)."""
        system, manager, stream, lock = self.system, self.manager, self.stream, self.lock
        total = None if duration is None else max(1, round(duration / system.period))
        began = self._running_since = time.perf_counter()
        rate = Rate(system.update_rate, clock=time.perf_counter) if self.realtime else None
        k = 0
        self.stopped_by = "duration"
        try:
            while total is None or k < total:
                if stop is not None and stop.is_set():
                    self.stopped_by = "operator"
                    break
                if rate is not None and not rate.wait():
                    manager.stats.overruns += 1
                now = self.now = system.sim_time
                self._follow_schedule(now)
                if stream is not None:
                    stream.publish(now)
                if lock is None:
                    manager.tick(now)
                else:
                    with lock():
                        manager.tick(now)
                if on_tick is not None:
                    on_tick()
                k += 1
        except KeyboardInterrupt:
            self.stopped_by = "interrupt"
        finally:
            self.wall_seconds += time.perf_counter() - began
            self._running_since = None

    def summary(self) -> dict[str, Any]:
        manager, system = self.manager, self.system
        stats = manager.stats.summary()
        sim_seconds = system.sim_time
        return {
            "modes_visited": list(manager.modes_visited),
            "final_mode": manager.active_mode.value if manager.active_mode is not None else None,
            "ticks": stats["ticks"],
            "sim_seconds": round(sim_seconds, 6),
            "wall_seconds": round(self.wall_seconds, 6),
            "realtime_factor": round(sim_seconds / self.wall_seconds, 3) if self.wall_seconds > 0 else None,
            "tick_us": stats["tick_us"],
            "overruns": stats["overruns"],
            "fallbacks": list(manager.fallbacks),
            "refused": manager.gate.refused.as_dict(),
            "update_rate": system.update_rate,
            "physics_rate": system.physics_rate,
            "stages": [{"stage": name, "seconds": round(seconds, 6)} for name, seconds in manager.stages],
            "stopped_by": self.stopped_by,
            "config": manager.configuration,
        }
