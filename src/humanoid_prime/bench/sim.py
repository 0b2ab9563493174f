"""Simulation speed (DESIGN §6): ``MujocoSystem`` with the controllers, headless, as fast as possible.

The demonstration schedule is compressed into the requested simulated time so every mode, the
ONNX policy and the remote stream included, contributes to the figures.

The x-real-time figure follows the host: on a shared machine MuJoCo's own step rate moves by half within
minutes. So the floor is MuJoCo's own stepping in this very run: ``MujocoSystem`` times its physics (``mj_step``
looping the tick's steps in C) as the tick's plant time, and the run's fraction of that floor is reported beside
the target: that fraction is ours, the rest is the machine and the model. Timed in the run, the floor steps the
states the run visited (arms moving against stiff gains cost MuJoCo more than arms hanging limp), and the tick
splits into MuJoCo's time and our own CPU. The default of 60 s simulated runs for about a second, long enough
to average over the host's swings.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from humanoid_prime.bench import TARGET_FLOOR_FRACTION
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.robot import load_robot
from humanoid_prime.sim.demo import DEMO_SECONDS, SCHEDULE, START_POSE, Simulation, Step, build_simulation, demo_stream

ROBOT_UPDATE_RATE = 50.0  # Hz, the control rate of the robot (the physics stays at the file's physics_rate)


def bench_sim(seconds: float = 60.0, *, hardware_file: str | Path | None = None,
              controllers_file: str | Path | None = None) -> dict[str, object]:
    """Run ``seconds`` of simulated time headless and report the real-time factor and the tick cost."""
    robot = load_robot(hardware_file, use_sim=True)
    config = load_controllers(robot.names, controllers_file)
    config = dataclasses.replace(config, sim_update_rate=ROBOT_UPDATE_RATE)  # the robot's rates (DESIGN §6)
    system, manager = build_simulation(robot, config, initial_pose=START_POSE)
    scale = seconds / DEMO_SECONDS
    schedule = tuple(Step(step.at * scale, step.mode) for step in SCHEDULE)
    sim = Simulation(system, manager, schedule=schedule, stream=demo_stream(robot, config, manager), realtime=False)
    with manager:
        manager.start()
        sim.run(seconds)
        summary = sim.summary()
        stats = manager.stats
        kept = min(stats.ticks, stats.capacity)
        physics_s = float(stats.ios[:kept].mean()) * stats.ticks
        split = stats.split_us()
    rtf = summary["realtime_factor"]
    floor_rtf = summary["sim_seconds"] / physics_s
    return {
        "sim_seconds": summary["sim_seconds"],
        "wall_seconds": summary["wall_seconds"],
        "realtime_factor": rtf,
        "floors": {"mj_step_us": round(physics_s / (summary["ticks"] * system.substeps) * 1e6, 2),
                   "realtime_factor": round(floor_rtf, 1)},
        "floor_fraction": None if rtf is None else round(rtf / floor_rtf, 3),
        "target_floor_fraction": TARGET_FLOOR_FRACTION,
        "meets_target": rtf is not None and rtf / floor_rtf >= TARGET_FLOOR_FRACTION,
        "ticks": summary["ticks"],
        "tick_us": {"median": summary["tick_us"]["median"], "p99": summary["tick_us"]["p99"]},
        "tick_cpu_us": {"median": split["cpu"]["median"], "p99": split["cpu"]["p99"]},
        "update_rate": summary["update_rate"],
        "physics_rate": summary["physics_rate"],
        "modes_visited": summary["modes_visited"],
        "fallbacks": len(summary["fallbacks"]),
    }
