"""The gate keeps Prime's arms off each other and off the torso in the simulation, with the full physics: REMOTE
streams that drive the left hand into the right hand and each hand into the torso are stopped short, the minimum
distance over the run measured by MuJoCo itself (every physics step, every pair of bodies the arms can meet), and
each refusal is counted and named. Without the body check the same streams end in contact: the simulation collides.

The pairs measured here are written from the robot's shape, not from the gate's tables: every geom of the left
arm against every geom of the right arm, and each arm against the torso, its base and the pedestal, the shoulder
that sits on the torso excepted."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pytest

from humanoid_prime.calibration.gravity import GravityModel
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.controller import pose_array
from humanoid_prime.control.topics import REMOTE_COMMAND, SAFETY_STATUS, MitCommand
from humanoid_prime.modes import Mode
from humanoid_prime.sim.demo import build_simulation

RAMP_S = 6.0  # the stream goes from the ready pose to its target in this long, then insists for as long again
SITO_GAINS = (8.0, 0.5)
BODY = {"world", "base_link", "torso_link"}
ADJACENT = {("left_shoulder_pitch_link", "torso_link"), ("right_shoulder_pitch_link", "torso_link")}


def side(body: str) -> str:
    return "left" if body.startswith("left_") else "right" if body.startswith("right_") else "body"


def measured_pairs(model) -> list[tuple[int, int]]:
    """Every pair of geoms of different sides of the robot (the floor aside), adjacent bodies excepted."""
    bodies = [model.body(int(model.geom_bodyid[g])).name for g in range(model.ngeom)]
    geoms = [g for g in range(model.ngeom) if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE]
    return [(a, b) for a in geoms for b in geoms if a < b and side(bodies[a]) != side(bodies[b])
            and (bodies[a], bodies[b]) not in ADJACENT and (bodies[b], bodies[a]) not in ADJACENT]


@dataclass
class Run:
    min_distance: float
    closest: tuple[str, str]
    contacts: int  # MuJoCo contacts between different sides, summed over the physics steps
    refused: int
    by_pair: dict[str, int]
    flags: list[str]


def drive(sim_robot, target: np.ndarray, *, check_body: bool = True) -> Run:
    """REMOTE from the ready pose toward ``target`` (joint space, straight), gravity fed forward, for 2 x RAMP_S."""
    config = load_controllers(sim_robot.names)
    ready = pose_array(sim_robot, config.standby.poses["ready"])
    system, manager = build_simulation(sim_robot, config, initial_pose=dict(zip(sim_robot.names, ready, strict=True)))
    if not check_body:
        manager = type(manager)(sim_robot, list(manager.resources.components), config,
                                update_rate=manager.update_rate, check_body=False)
    model, data = system.model, system.data
    pairs = measured_pairs(model)
    bodies = [model.body(int(model.geom_bodyid[g])).name for g in range(model.ngeom)]
    low = [np.inf, ("", "")]
    contacts = [0]

    def step(dt: float) -> None:
        mujoco.mj_step(model, data)
        for a, b in pairs:
            distance = mujoco.mj_geomDistance(model, data, a, b, 1.0, None)
            if distance < low[0]:
                low[0], low[1] = distance, (bodies[a], bodies[b])
        contacts[0] += sum(1 for c in data.contact[:data.ncon]
                           if side(bodies[c.geom1]) != side(bodies[c.geom2]))

    system.advance = step
    gravity = GravityModel(sim_robot)
    flags: list[str] = []
    manager.topics.subscribe(SAFETY_STATUS, lambda s: flags.extend(s.flags.values()), latched=True)
    n = sim_robot.n
    stiffness = np.where([j.family == "sito" for j in sim_robot.joints], SITO_GAINS[0], 0.0)
    damping = np.where([j.family == "sito" for j in sim_robot.joints], SITO_GAINS[1], 0.0)
    message = MitCommand(joint_names=sim_robot.names, position=np.zeros(n), velocity=np.zeros(n),
                         effort=np.zeros(n), stiffness=stiffness, damping=damping)
    with manager:
        manager.start(now=system.sim_time)
        manager.request_mode(Mode.REMOTE)
        manager.tick(now=system.sim_time)
        for _ in range(round(2 * RAMP_S * manager.update_rate)):
            share = min(1.0, system.sim_time / RAMP_S)
            message.position[:] = ready + share * (target - ready)
            message.velocity[:] = (target - ready) / RAMP_S if share < 1.0 else 0.0
            message.effort[:] = gravity.torques(message.position)
            message.stamp = system.sim_time
            manager.topics.publish(REMOTE_COMMAND, message)
            manager.tick(now=system.sim_time)
        assert manager.active_mode is Mode.REMOTE
        refused = manager.gate.refused
        return Run(low[0], low[1], contacts[0], refused.count, dict(refused.by_pair), flags)


def mirrored(robot, left: dict[str, float]) -> dict[str, float]:
    """The right arm's pose that mirrors ``left`` (rolls and yaws change sign)."""
    return {"right_" + name.removeprefix("left_"): -value if name.endswith(("roll", "yaw")) else value
            for name, value in left.items()}


HANDS = {"left_shoulder_pitch": -1.3, "left_shoulder_roll": -0.6, "left_elbow_pitch": -0.4}
LEFT_INTO_TORSO = {"left_shoulder_pitch": 0.43, "left_shoulder_roll": 0.33, "left_shoulder_yaw": -1.17,
                   "left_elbow_pitch": -2.01}


def target(sim_robot, pose: dict[str, float]) -> np.ndarray:
    ready = load_controllers(sim_robot.names).standby.poses["ready"]
    return pose_array(sim_robot, {**ready, **pose})


SCENARIOS = {
    "left hand into the right hand": (lambda r: {**HANDS, **mirrored(r, HANDS)}, {"left arm", "right arm"}),
    "left hand into the torso": (lambda r: LEFT_INTO_TORSO, {"left arm", "body"}),
    "right hand into the torso": (lambda r: mirrored(r, LEFT_INTO_TORSO), {"right arm", "body"}),
}


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_gate_stops_the_stream_short_of_the_margin(sim_robot, name):
    pose, _ = SCENARIOS[name]
    margin = sim_robot.hardware.collision_margin
    run = drive(sim_robot, target(sim_robot, pose(sim_robot)))
    print(f"{name}: minimum distance {run.min_distance:.4f} m ({' / '.join(run.closest)}), "
          f"{run.refused} commands refused: {run.by_pair}")
    assert run.min_distance >= margin, run
    assert run.contacts == 0
    assert run.refused > 0
    assert any("command refused" in flag and " m apart (margin 0.030 m)" in flag for flag in run.flags), run.flags


@pytest.mark.parametrize("name", SCENARIOS)
def test_without_the_body_check_the_same_stream_collides(sim_robot, name):
    pose, _ = SCENARIOS[name]
    run = drive(sim_robot, target(sim_robot, pose(sim_robot)), check_body=False)
    assert run.min_distance < 0.005 and run.refused == 0, run


POSES = 1000


def test_a_thousand_random_remote_poses_are_refused_exactly_where_mujoco_finds_the_bodies_within_the_margin(robot):
    """Each tick REMOTE gets a pose drawn within the joint limits, the robot standing at the ready pose: the gate
    refuses it exactly when MuJoCo's own distance between some pair of bodies is under the margin."""
    from doubles.control import Plant
    from humanoid_prime.config.model import load_model
    from humanoid_prime.control.manager import ControllerManager

    config = load_controllers(robot.names)
    ready = pose_array(robot, config.standby.poses["ready"])
    plant = Plant("plant", robot.names)
    plant.position[:] = ready
    model = load_model(robot)
    data = mujoco.MjData(model)
    pairs = measured_pairs(model)
    qpos = [model.joint(name).qposadr[0] for name in robot.names]
    margin = robot.hardware.collision_margin

    def within_margin(pose: np.ndarray) -> bool:
        data.qpos[qpos] = pose
        mujoco.mj_kinematics(model, data)
        return min(mujoco.mj_geomDistance(model, data, a, b, 1.0, None) for a, b in pairs) < margin

    assert not within_margin(ready)
    rng = np.random.default_rng(40)
    sito = np.array([j.family == "sito" for j in robot.joints])
    n = robot.n
    message = MitCommand(joint_names=robot.names, position=np.zeros(n), velocity=np.zeros(n), effort=np.zeros(n),
                         stiffness=np.where(sito, 8.0, 0.0), damping=np.where(sito, 0.5, 0.0))
    disagreements, refused_poses = [], 0
    with ControllerManager(robot, [plant], config, update_rate=100.0) as manager:
        manager.start(now=0.0)
        manager.request_mode(Mode.REMOTE)
        manager.tick(0.01)
        for k in range(POSES):
            now = 0.02 + 0.01 * k
            message.position[:] = rng.uniform(robot.lower, robot.upper)
            message.stamp = now
            manager.topics.publish(REMOTE_COMMAND, message)
            before = manager.gate.refused.count
            manager.tick(now)
            refused = manager.gate.refused.count > before
            refused_poses += refused
            if refused != within_margin(message.position):
                disagreements.append((k, refused))
        assert manager.active_mode is Mode.REMOTE and not manager.fallbacks
    print(f"{POSES} random REMOTE poses: {refused_poses} refused, {POSES - refused_poses} accepted, "
          f"{len(disagreements)} disagreements with MuJoCo")
    assert disagreements == []
    assert 0.1 * POSES < refused_poses < 0.9 * POSES  # both kinds are well represented


def test_every_bundled_pose_keeps_the_bodies_beyond_the_margin(robot):
    """The standby poses and the pose the simulated robot powers up in: MuJoCo's distances, every pair."""
    from humanoid_prime.config.model import load_model
    from humanoid_prime.sim.demo import START_POSE

    model = load_model(robot)
    data = mujoco.MjData(model)
    pairs = measured_pairs(model)
    qpos = [model.joint(name).qposadr[0] for name in robot.names]
    poses = {**load_controllers(robot.names).standby.poses, "START_POSE": START_POSE}
    for name, pose in poses.items():
        data.qpos[qpos] = pose_array(robot, pose)
        mujoco.mj_kinematics(model, data)
        nearest = min(mujoco.mj_geomDistance(model, data, a, b, 1.0, None) for a, b in pairs)
        assert nearest >= robot.hardware.collision_margin, (name, nearest)


def test_the_demonstration_visits_every_mode_without_a_refusal_or_a_touch(sim_robot):
    """STANDBY's poses, the policy and the remote wave of ``prime sim``: the gate never has to hold an arm, and
    the arms never touch each other or the torso."""
    from humanoid_prime.sim.demo import DEMO_SECONDS, SCHEDULE, START_POSE, Simulation, demo_stream

    config = load_controllers(sim_robot.names)
    system, manager = build_simulation(sim_robot, config, initial_pose=START_POSE)
    model, data = system.model, system.data
    bodies = [model.body(int(model.geom_bodyid[g])).name for g in range(model.ngeom)]
    touches = []

    def step(dt: float) -> None:
        mujoco.mj_step(model, data)
        touches.extend((bodies[c.geom1], bodies[c.geom2]) for c in data.contact[:data.ncon]
                       if side(bodies[c.geom1]) != side(bodies[c.geom2]))

    system.advance = step
    with manager:
        manager.start(now=system.sim_time)
        sim = Simulation(system, manager, schedule=SCHEDULE, stream=demo_stream(sim_robot, config, manager),
                         realtime=False)
        sim.run(DEMO_SECONDS)
        summary = sim.summary()
    assert {Mode(mode) for mode in summary["modes_visited"]} == set(Mode)
    assert summary["refused"]["count"] == 0 and not summary["fallbacks"]
    assert touches == []
