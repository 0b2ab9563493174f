"""The command gate with collision on the control loop (DESIGN §6): the simulated Prime's 14 joints at 50 Hz in
REMOTE, following the demonstration's wave, paced on the wall clock as on the robot (so every tick starts with the
caches the wait left it). Two simulations run in the same process, one whose gate checks the body and one whose gate
does not, in turns of half a second; each turn's first tick aside, the median tick (read + update + write, our CPU:
the physics is the plant's time) of each, and what the body check adds (target <= 50 us). Then the left hand is
driven into the torso and held there by the gate: the median tick while the gate refuses, beside the same tick of
the run without the body check (the arm driven through the torso).
"""

from __future__ import annotations

import math
import time

import numpy as np

from humanoid_prime.bench import TARGET_GATE_ADDED_TICK_US
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.control.controller import pose_array
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.rate import Rate
from humanoid_prime.control.topics import REMOTE_COMMAND
from humanoid_prime.modes import Mode
from humanoid_prime.sim.demo import RemoteStream, build_simulation, demo_stream

RATE_HZ = 50.0
TURN_S = 0.5
# The left hand driven into the torso from behind (the scenario of tests/sim/test_collision.py).
INTO_TORSO = {"left_shoulder_pitch": 0.43, "left_shoulder_roll": 0.33, "left_shoulder_yaw": -1.17,
              "left_elbow_pitch": -2.01}


class _Run:
    """One simulated Prime in REMOTE at ``RATE_HZ``, its gate checking the body or not."""

    def __init__(self, robot: Robot, check_body: bool) -> None:
        config = load_controllers(robot.names)
        ready = config.standby.poses["ready"]
        self.system, built = build_simulation(robot, config, initial_pose=ready, update_rate=RATE_HZ,
                                              clock=time.monotonic)
        self.manager = ControllerManager(robot, list(built.resources.components), config, update_rate=RATE_HZ,
                                         check_body=check_body)
        self.manager.start(now=self.system.sim_time)
        self.manager.request_mode(Mode.REMOTE)
        self.wave = demo_stream(robot, config, self.manager)
        into = pose_array(robot, {**ready, **INTO_TORSO})
        self.push = RemoteStream(robot, self.manager.topics, config.remote.topic, into,
                                 (config.remote.erob_kp, config.remote.erob_kd))
        self.push.amplitude[:] = 0.0  # holds still at the pose: the gate refuses it every tick
        self.cpu_us: dict[str, list[float]] = {"wave": [], "push": []}

    def tick(self, stream: str, record: bool) -> None:
        manager, stats = self.manager, self.manager.stats
        (self.wave if stream == "wave" else self.push).publish(self.system.sim_time)
        manager.tick(now=self.system.sim_time)
        k = (stats.ticks - 1) % stats.capacity
        if record:
            self.cpu_us[stream].append((stats.costs[k] - stats.ios[k]) * 1e6)

    def close(self) -> None:
        self.manager.shutdown()


def _turns(runs: dict[bool, _Run], stream: str, seconds: float) -> None:
    rate = Rate(RATE_HZ)
    per_turn = max(2, round(TURN_S * RATE_HZ))
    for turn in range(max(2, round(seconds / TURN_S))):
        run = runs[turn % 2 == 0]
        for k in range(per_turn):
            rate.wait()
            run.tick(stream, record=k > 0)


def _figures(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "p99": None}
    median, p99 = np.percentile(values, (50, 99))
    return {"median": round(float(median), 1), "p99": round(float(p99), 1)}


def bench_gate(seconds: float = 20.0) -> dict[str, object]:
    robot = load_robot(use_sim=True)
    runs = {True: _Run(robot, check_body=True), False: _Run(robot, check_body=False)}
    try:
        _turns(runs, "wave", seconds)
        for run in runs.values():  # REMOTE's first message after the wave: the hand on its way to the torso
            run.manager.topics.publish(REMOTE_COMMAND, run.push.message)
        _turns(runs, "push", seconds / 2)
        refused = runs[True].manager.gate.refused.count
    finally:
        for run in runs.values():
            run.close()
    on, off = (_figures(runs[state].cpu_us["wave"]) for state in (True, False))
    push_on, push_off = (_figures(runs[state].cpu_us["push"]) for state in (True, False))
    added = None if on["median"] is None or off["median"] is None else round(on["median"] - off["median"], 1)
    refusing = None if push_on["median"] is None or push_off["median"] is None else \
        round(push_on["median"] - push_off["median"], 1)
    return {
        "rate_hz": RATE_HZ,
        "seconds": seconds,
        "tick_cpu_us": {"with_body_check": on, "without": off},
        "added_tick_us_median": added,
        "refusing": {"tick_cpu_us": {"with_body_check": push_on, "without": push_off},
                     "added_tick_us_median": refusing, "refused": refused},
        "target_added_tick_us": TARGET_GATE_ADDED_TICK_US,
        "meets_target": added is not None and added <= TARGET_GATE_ADDED_TICK_US,
        "floors": {"tick_cpu_us_median": off["median"] if off["median"] is not None else math.nan},
    }
