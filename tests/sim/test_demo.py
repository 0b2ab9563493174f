"""The scripted demonstration: its schedule, its remote command stream, and the run loop."""

import threading

import numpy as np
import pytest

from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.controller import pose_array
from humanoid_prime.control.topics import REMOTE_COMMAND
from humanoid_prime.modes import Mode
from humanoid_prime.sim.demo import (
    DEMO_SECONDS,
    SCHEDULE,
    Simulation,
    Step,
    build_simulation,
    demo_stream,
)


@pytest.fixture(scope="module")
def config(sim_robot):
    return load_controllers(sim_robot.names)


def test_schedule_visits_every_mode_within_20_seconds():
    assert {step.mode for step in SCHEDULE} == set(Mode)
    assert all(0.0 <= step.at < DEMO_SECONDS for step in SCHEDULE)
    assert [step.at for step in SCHEDULE] == sorted(step.at for step in SCHEDULE)


def test_schedule_starts_limp_and_ends_damped():
    assert SCHEDULE[0] == Step(0.0, Mode.ZERO_TORQUE)
    assert SCHEDULE[-1].mode is Mode.DAMPING


def test_schedule_gives_standby_its_whole_entry_trajectory(config):
    standby = next(i for i, step in enumerate(SCHEDULE) if step.mode is Mode.STANDBY)
    assert SCHEDULE[standby + 1].at - SCHEDULE[standby].at > config.standby.duration


def test_remote_stream_stays_inside_the_joint_limits(sim_robot, config):
    system, manager = build_simulation(sim_robot, config)
    stream = demo_stream(sim_robot, config, manager)
    for now in np.linspace(0.0, 6.0, 601):
        stream.publish(now)
        assert (stream.message.position >= sim_robot.lower).all()
        assert (stream.message.position <= sim_robot.upper).all()
    assert stream.message.joint_names == sim_robot.names


def test_remote_stream_waves_around_the_locomotion_default_pose(sim_robot, config):
    _, manager = build_simulation(sim_robot, config)
    stream = demo_stream(sim_robot, config, manager)
    center = pose_array(sim_robot, config.standby.poses[config.locomotion.default_pose])
    np.testing.assert_array_equal(stream.center, center)
    stream.publish(0.0)
    np.testing.assert_array_equal(stream.message.position, center)
    assert stream.message.velocity[sim_robot.index("left_elbow_pitch")] > 0
    assert stream.message.velocity[sim_robot.index("right_elbow_pitch")] < 0  # arms in opposite phase


def test_remote_mode_follows_the_stream(sim_robot, config):
    system, manager = build_simulation(sim_robot, config)
    stream = demo_stream(sim_robot, config, manager)
    sim = Simulation(system, manager, schedule=(Step(0.5, Mode.REMOTE),), stream=stream, realtime=False)
    with manager:
        manager.start()
        sim.run(1.0)
        remote = manager.controllers[Mode.REMOTE.controller]
        assert manager.active_mode is Mode.REMOTE
        assert remote.accepted == stream.published
        assert "stale" not in remote.flags
        np.testing.assert_array_equal(manager.resources.command.position, stream.message.position)
        assert manager.topics.latest(REMOTE_COMMAND) is stream.message


def test_simulation_advances_one_control_period_per_tick(sim_robot, config):
    system, manager = build_simulation(sim_robot, config)
    sim = Simulation(system, manager, realtime=False)
    with manager:
        manager.start()
        sim.run(0.25)
    assert manager.stats.ticks == 50
    assert system.sim_time == pytest.approx(0.25)
    assert sim.stopped_by == "duration"


def test_an_operator_takeover_stops_the_schedule(sim_robot, config):
    system, manager = build_simulation(sim_robot, config)
    sim = Simulation(system, manager, schedule=(Step(0.1, Mode.DAMPING), Step(0.2, Mode.STANDBY)), realtime=False)
    with manager:
        manager.start()
        sim.run(0.15)
        sim.take_over()
        manager.request_mode(Mode.ZERO_TORQUE)
        sim.run(0.2)
        assert manager.modes_visited == ["ZERO_TORQUE", "DAMPING", "ZERO_TORQUE"]


def test_a_set_stop_event_ends_the_run(sim_robot, config):
    system, manager = build_simulation(sim_robot, config)
    stop = threading.Event()
    sim = Simulation(system, manager, realtime=False)
    with manager:
        manager.start()
        sim.run(None, stop=stop, on_tick=lambda: stop.set() if manager.stats.ticks >= 7 else None)
    assert manager.stats.ticks == 7
    assert sim.stopped_by == "operator"
