"""The controller manager: staged start, switching between ticks, exclusive claims, one-tick fallback,
safety status and the paced loop."""

import itertools
import threading
import time

import numpy as np
import pytest

from doubles.control import Clock, Plant, constant_policy, with_policy
from humanoid_prime.control.flags import SafetyFlags
from humanoid_prime.control.hardware import Lifecycle
from humanoid_prime.control.manager import ControllerManager, LoopStats
from humanoid_prime.control.topics import CONTROL_MODE, JOINT_STATES, SAFETY_STATUS, ControlMode, MitCommand
from humanoid_prime.errors import LifecycleError
from humanoid_prime.modes import Mode


def remote_command(robot, **rows):
    values = {name: np.zeros(robot.n) for name in ("position", "velocity", "effort", "stiffness", "damping")}
    values.update({k: np.asarray(v) for k, v in rows.items()})
    return MitCommand(joint_names=robot.names, **values)


def enter_remote(manager, robot, t=0.0):
    manager.request_mode(Mode.REMOTE)
    manager.tick(t)
    return t


# ---- staged start --------------------------------------------------------------------------------

def test_start_is_staged_hardware_configured_then_every_controller_then_activation(manager):
    assert [name for name, _ in manager.stages] == [
        "hardware configure", "joint_state_broadcaster", "zero_torque_controller", "damping_controller",
        "standby_controller", "locomotion_controller", "remote_policy_controller", "hardware activate",
        "controllers activated"]


def test_every_controller_is_configured_before_the_hardware_goes_cyclic(robot, config, clock, monkeypatch):
    # from activation on the drives must be fed every period: loading a policy then would starve them
    events: list[str] = []
    plant = Plant("plant", robot.names, events)
    manager = ControllerManager(robot, [plant], config, clock=clock)
    for name, controller in manager.controllers.items():
        configure = controller.on_configure
        monkeypatch.setattr(controller, "on_configure",
                            lambda *args, name=name, configure=configure: (events.append(name), configure(*args)))
    manager.start()
    assert events == ["plant.configure", *manager.controllers, "plant.activate"]


def test_after_start_broadcaster_and_zero_torque_are_active_and_the_others_loaded_inactive(manager):
    states = {name: c.lifecycle for name, c in manager.controllers.items()}
    assert states == {
        "joint_state_broadcaster": Lifecycle.ACTIVE, "zero_torque_controller": Lifecycle.ACTIVE,
        "damping_controller": Lifecycle.INACTIVE, "standby_controller": Lifecycle.INACTIVE,
        "locomotion_controller": Lifecycle.INACTIVE, "remote_policy_controller": Lifecycle.INACTIVE}
    assert manager.active_mode is Mode.ZERO_TORQUE


def test_hardware_is_active_before_any_controller_starts(robot, config, clock):
    events: list[str] = []
    plant = Plant("plant", robot.names, events)
    manager = ControllerManager(robot, [plant], config, clock=clock)
    manager.topics.subscribe(CONTROL_MODE, lambda msg: events.append(f"mode {msg.mode}"))
    manager.start()
    assert events == ["plant.configure", "plant.activate", "mode ZERO_TORQUE"]


def test_start_publishes_zero_torque_on_control_mode(manager):
    latest = manager.topics.latest(CONTROL_MODE)
    assert (latest.mode, latest.controller) == ("ZERO_TORQUE", "zero_torque_controller")


def test_tick_before_start_is_refused(robot, config, plant):
    with pytest.raises(LifecycleError, match="started"):
        ControllerManager(robot, [plant], config).tick(0.0)


# ---- switching and claims ------------------------------------------------------------------------

def test_a_request_changes_nothing_until_the_next_tick(manager):
    manager.tick(0.0)
    manager.request_mode(Mode.DAMPING)
    assert manager.active_mode is Mode.ZERO_TORQUE
    assert manager.command_owner == "zero_torque_controller"
    manager.tick(0.01)
    assert manager.active_mode is Mode.DAMPING
    assert manager.command_owner == "damping_controller"


def test_every_switch_publishes_the_new_mode(manager):
    seen: list[ControlMode] = []
    manager.topics.subscribe(CONTROL_MODE, seen.append)
    manager.request_mode(Mode.STANDBY)
    manager.tick(0.0)
    assert [(m.mode, m.controller) for m in seen] == [("STANDBY", "standby_controller")]


def test_any_mode_switches_to_any_mode_leaving_one_active_controller_owning_the_commands(manager):
    t = 0.0
    for source, target in itertools.permutations(Mode, 2):
        for mode in (source, target):
            manager.request_mode(mode)
            manager.tick(t)
            t += 0.01
            assert manager.active_mode is mode
            assert manager.command_owner == mode.controller
            active = [c.name for c in manager.controllers.values()
                      if c.lifecycle is Lifecycle.ACTIVE and c.claims_commands]
            assert active == [mode.controller]
    assert manager.fallbacks == []


def test_the_new_controller_activates_on_the_state_measured_in_the_switching_tick(manager, plant):
    manager.tick(0.0)
    plant.position[:] = np.linspace(-0.5, 0.0, 14)
    manager.request_mode(Mode.DAMPING)
    manager.tick(0.01)
    np.testing.assert_array_equal(plant.last[0], np.linspace(-0.5, 0.0, 14))


def test_a_reset_clears_latched_faults_and_enters_the_active_mode_again_from_the_measured_state(
        manager, plant, robot):
    manager.request_mode(Mode.STANDBY)
    manager.tick(0.0)
    plant.faults.append("left_elbow_pitch (ring 3): fault")
    rest = (robot.lower + robot.upper) / 2
    plant.position[:] = rest  # where the limp joints came to rest
    assert manager.request_reset() == ["left_elbow_pitch (ring 3): fault"]
    assert "plant.reset_faults" not in plant.events  # nothing until the next tick
    seen: list[ControlMode] = []
    manager.topics.subscribe(CONTROL_MODE, seen.append)
    manager.tick(0.01)
    assert plant.events.count("plant.reset_faults") == 1 and plant.faults == []
    assert [m.mode for m in seen] == ["STANDBY"]  # entered again ...
    np.testing.assert_allclose(plant.last[0], rest, atol=1e-9)  # ... from the measured pose: no jump
    assert manager.resets == 1


def test_a_mode_requested_with_a_reset_is_the_mode_entered(manager, plant):
    manager.request_reset()
    manager.request_mode(Mode.DAMPING)
    manager.tick(0.0)
    assert manager.active_mode is Mode.DAMPING and "plant.reset_faults" in plant.events


def test_requests_from_other_threads_land_between_ticks(manager):
    def press_keys(modes):
        for mode in modes * 100:
            manager.request_mode(mode)
            time.sleep(0.0002)

    threads = [threading.Thread(target=press_keys, args=(m,)) for m in ([Mode.DAMPING, Mode.STANDBY],
                                                                      [Mode.REMOTE, Mode.ZERO_TORQUE])]
    for thread in threads:
        thread.start()
    k = 0
    while any(thread.is_alive() for thread in threads):
        manager.tick(k * 0.01)
        k += 1
        assert manager.command_owner == manager.active_mode.controller
        time.sleep(0.0002)
    assert manager.fallbacks == []
    assert len(set(manager.modes_visited)) > 1


def test_a_mode_may_be_requested_by_name(manager):
    manager.request_mode("standby_controller")
    manager.tick(0.0)
    assert manager.active_mode is Mode.STANDBY


def test_modes_visited_lists_every_activation_in_order(manager):
    for k, mode in enumerate((Mode.STANDBY, Mode.DAMPING)):
        manager.request_mode(mode)
        manager.tick(k * 0.01)
    assert manager.modes_visited == ["ZERO_TORQUE", "STANDBY", "DAMPING"]


# ---- fallback within one tick --------------------------------------------------------------------

def test_a_nan_from_a_controller_reaches_damping_within_one_tick(robot, config, clock, tmp_path):
    plant = Plant("plant", robot.names)
    plant.position[:] = 0.1 * np.sin(np.arange(14)) - 0.15  # within every joint's limits
    nan_policy = constant_policy(tmp_path / "nan.onnx", robot, np.nan)
    with ControllerManager(robot, [plant], with_policy(config, nan_policy), clock=clock) as manager:
        manager.start()
        manager.request_mode(Mode.LOCOMOTION)
        manager.tick(0.0)
        assert manager.active_mode is Mode.DAMPING
        assert [(f["tick"], f["from"], f["to"]) for f in manager.fallbacks] == [(0, "LOCOMOTION", "DAMPING")]
        assert "non-finite action" in manager.fallbacks[0]["reason"]
        position, velocity, effort, stiffness, damping = plant.last  # the write of that same tick
        np.testing.assert_array_equal(position, plant.position)
        assert stiffness.tolist() == [0.0] * 14 and damping.tolist() == [6.0] * 14
        assert manager.command_owner == "damping_controller"


def test_zero_torque_takes_over_in_the_same_tick_when_damping_fails_too(robot, config, clock):
    plant = Plant("plant", robot.names)
    with ControllerManager(robot, [plant], config, update_rate=100.0, clock=clock) as manager:
        manager.start()
        manager.request_mode(Mode.LOCOMOTION)
        manager.tick(0.0)
        plant.position[3] = np.nan  # the elbow encoder reads garbage: the policy and Damping both fail
        manager.tick(0.01)
        assert manager.active_mode is Mode.ZERO_TORQUE
        assert [(f["tick"], f["from"], f["to"]) for f in manager.fallbacks] == [
            (1, "LOCOMOTION", "DAMPING"), (1, "DAMPING", "ZERO_TORQUE")]
        assert "left_elbow_pitch" in manager.fallbacks[1]["reason"]
        assert np.all(np.isfinite(plant.last))
        assert plant.last[1:].tolist() == [[0.0] * 14] * 4


def test_when_zero_torque_itself_fails_the_last_resort_is_limp_on_the_last_valid_targets(manager, plant):
    manager.tick(0.0)
    plant.velocity[:] = 0.3
    manager.tick(0.01)
    last_valid = plant.last[0].copy()

    def broken(now, dt, state, command):
        raise RuntimeError("zero torque broke")

    manager.controllers["zero_torque_controller"].update = broken
    plant.position[:] += 0.2  # the arm moved since: the limp command keeps the last valid target
    manager.tick(0.02)
    assert manager.fallbacks[-1]["from"] == manager.fallbacks[-1]["to"] == "ZERO_TORQUE"
    assert "writing a limp command" in manager.fallbacks[-1]["reason"]
    position, velocity, effort, stiffness, damping = plant.last
    np.testing.assert_array_equal(position, last_valid)
    assert [velocity.tolist(), effort.tolist(), stiffness.tolist(), damping.tolist()] == [[0.0] * 14] * 4
    assert "zero torque broke" in manager.topics.latest(SAFETY_STATUS).flags["controller_manager/fallback"]


def test_a_fallback_is_flagged_on_safety_status(robot, config, clock, tmp_path):
    plant = Plant("plant", robot.names)
    nan_policy = constant_policy(tmp_path / "nan.onnx", robot, np.nan)
    with ControllerManager(robot, [plant], with_policy(config, nan_policy), clock=clock) as manager:
        manager.start()
        manager.request_mode(Mode.LOCOMOTION)
        manager.tick(0.0)
        status = manager.topics.latest(SAFETY_STATUS)
        assert not status.ok
        assert status.flags["controller_manager/fallback"].startswith("locomotion_controller: policy produced a "
                                                                      "non-finite action")


def test_the_next_requested_mode_clears_the_fallback_flag(robot, config, clock, tmp_path):
    nan_policy = constant_policy(tmp_path / "nan.onnx", robot, np.nan)
    with ControllerManager(robot, [Plant("plant", robot.names)], with_policy(config, nan_policy),
                           clock=clock) as manager:
        manager.start()
        manager.request_mode(Mode.LOCOMOTION)
        manager.tick(0.0)
        manager.request_mode(Mode.STANDBY)
        manager.tick(0.01)
        assert manager.topics.latest(SAFETY_STATUS).ok


def test_a_controller_that_raises_is_replaced_in_the_same_tick(manager, plant):
    def wrong_size(now, dt, state, command):
        np.copyto(command.position, np.zeros(13))

    manager.controllers["standby_controller"].update = wrong_size
    manager.request_mode(Mode.STANDBY)
    manager.tick(0.0)
    assert manager.active_mode is Mode.DAMPING
    assert manager.fallbacks[-1]["reason"].startswith("standby_controller: ValueError: could not broadcast")
    assert plant.last[4].tolist() == [6.0] * 14


def standby_producing(manager, **rows):
    """STANDBY active, its controller patched to propose ``rows`` (zeros elsewhere): the output check's input."""
    def produce(now, dt, state, command):
        command.data[:] = 0.0
        for row, values in rows.items():
            np.copyto(getattr(command, row), values)

    manager.controllers["standby_controller"].update = produce
    manager.request_mode(Mode.STANDBY)


def test_a_non_finite_command_falls_back_to_damping(manager, robot, plant):
    standby_producing(manager, position=np.full(14, np.nan))
    manager.tick(0.01)
    assert manager.active_mode is Mode.DAMPING
    assert "standby_controller: position of left_shoulder_pitch is nan" in manager.fallbacks[-1]["reason"]
    assert np.all(np.isfinite(plant.last))


# ---- the output check ----------------------------------------------------------------------------

@pytest.mark.parametrize(("row", "value", "reason"), [
    ("damping", -0.1, "damping of left_wrist_roll is negative (-0.1)"),
    ("stiffness", -1.0, "stiffness of left_wrist_roll is negative (-1)"),
    ("effort", 4.9, "effort of left_wrist_roll is 4.9 Nm, beyond its limit of 4.8 Nm"),
    ("effort", -4.9, "effort of left_wrist_roll is -4.9 Nm, beyond its limit of 4.8 Nm"),
    ("velocity", -3.2, "velocity of left_wrist_roll is -3.2 rad/s, beyond its limit of 3.14 rad/s (the Sito maximum, "
                       "command_limits.sito.velocity in prime_hardware.yaml)"),
    ("stiffness", 100.5, "stiffness of left_wrist_roll is 100.5 Nm/rad, beyond its limit of 100 Nm/rad (the Sito "
                         "maximum, command_limits.sito.stiffness in prime_hardware.yaml)"),
    ("damping", 1e9, "damping of left_wrist_roll is 1e+09 Nm*s/rad, beyond its limit of 10 Nm*s/rad"),
])
def test_an_unsafe_command_is_rejected(manager, robot, row, value, reason):
    standby_producing(manager, **{row: np.where(np.arange(14) == robot.index("left_wrist_roll"), value, 0.0)})
    manager.tick(0.01)
    assert manager.active_mode is Mode.DAMPING
    assert manager.fallbacks[-1]["reason"].startswith(f"standby_controller: {reason}")


def test_a_gain_is_held_to_the_maximum_of_its_joints_family(manager, robot):
    stiffness = np.zeros(14)
    stiffness[robot.index("left_elbow_pitch")] = 400.0  # within the eRob maximum (500), beyond the Sito one (100)
    standby_producing(manager, stiffness=stiffness)
    manager.tick(0.01)
    assert manager.active_mode is Mode.STANDBY, manager.fallbacks


@pytest.mark.parametrize("stiffness", [5.0, 0.0])
def test_a_target_beyond_a_limit_by_more_than_the_margin_is_rejected_with_or_without_stiffness(manager, robot,
                                                                                                stiffness):
    position = np.zeros(14)
    position[robot.index("left_wrist_pitch")] = 0.785 + 0.006
    standby_producing(manager, position=position, stiffness=np.full(14, stiffness))
    manager.tick(0.01)
    assert manager.active_mode is Mode.DAMPING
    assert "position target of left_wrist_pitch is 0.791 rad, outside its limits [-0.785, 0.785]" in \
        manager.fallbacks[-1]["reason"]


@pytest.mark.parametrize("stiffness", [5.0, 0.0])
def test_a_target_within_the_margin_is_clipped_onto_the_limit(manager, robot, plant, stiffness):
    enter_remote(manager, robot)
    position = np.zeros(14)
    position[robot.index("left_wrist_pitch")] = 0.785 + 0.004
    manager.topics.publish("/remote_policy_controller/command",
                           remote_command(robot, position=position, stiffness=np.full(14, stiffness)))
    manager.tick(0.01)
    assert manager.active_mode is Mode.REMOTE
    assert plant.last[0][robot.index("left_wrist_pitch")] == 0.785


def test_a_limp_arm_beyond_its_limits_stays_in_zero_torque_and_damping_with_targets_on_the_limits(manager, robot,
                                                                                                 plant):
    elbow = robot.index("left_elbow_pitch")
    plant.position[elbow] = 0.3  # measured beyond its upper limit (0): a calibration that is off, a hard stop
    manager.tick(0.0)
    assert manager.active_mode is Mode.ZERO_TORQUE and plant.last[0][elbow] == 0.0
    manager.request_mode(Mode.DAMPING)
    manager.tick(0.01)
    assert manager.active_mode is Mode.DAMPING and plant.last[0][elbow] == 0.0
    assert manager.fallbacks == []


def test_a_limp_wrist_beyond_its_limit_keeps_remote_damping_with_its_target_on_the_limit(manager, robot, plant):
    wrist = robot.index("left_wrist_roll")
    plant.position[wrist] = 0.9  # beyond 0.698: REMOTE's stale damping targets the live position of every joint
    enter_remote(manager, robot)
    manager.tick(0.01)
    assert manager.active_mode is Mode.REMOTE and manager.fallbacks == []
    assert plant.last[0][wrist] == 0.698 and plant.last[3][wrist] == 0.0


# ---- REMOTE refuses a bad command at the door ----------------------------------------------------

@pytest.mark.parametrize(("rows", "reason"), [
    ({"position": np.full(14, np.nan)}, "position of left_shoulder_pitch is nan"),
    ({"damping": np.full(14, np.inf)}, "damping of left_shoulder_pitch is inf"),
    ({"stiffness": -np.ones(14)}, "stiffness of left_shoulder_pitch is negative (-1)"),
    ({"effort": np.full(14, 500.0)}, "effort of left_shoulder_pitch is 500 Nm, beyond its limit of"),
    ({"position": np.full(14, 9.0), "stiffness": np.ones(14)}, "position target of left_shoulder_pitch is 9 rad"),
    ({"position": np.full(14, 1e308)}, "position target of left_shoulder_pitch is 1e+308 rad"),
    ({"velocity": np.full(14, 1e6)}, "velocity of left_shoulder_pitch is 1e+06 rad/s, beyond its limit of 6.28"),
    ({"stiffness": np.full(14, 1e9)}, "stiffness of left_shoulder_pitch is 1e+09 Nm/rad, beyond its limit of 500"),
    ({"velocity": np.zeros(13)}, "velocity has shape (13,), expected (14,)"),
    ({"effort": ["a"] * 14}, "effort is not a list of numbers"),
])
def test_remote_refuses_a_bad_command_counts_it_flags_it_and_keeps_the_last_good_one(manager, robot, plant, rows,
                                                                                       reason):
    enter_remote(manager, robot)
    good = (robot.lower + robot.upper) / 2
    manager.topics.publish("/remote_policy_controller/command", remote_command(robot, position=good))
    manager.tick(0.01)
    manager.topics.publish("/remote_policy_controller/command", remote_command(robot, **rows))
    manager.tick(0.02)
    remote = manager.controllers["remote_policy_controller"]
    assert manager.active_mode is Mode.REMOTE, manager.fallbacks
    assert remote.rejected == 1 and reason in remote.last_rejection
    assert reason in manager.topics.latest(SAFETY_STATUS).flags["remote_policy_controller/rejected"]
    np.testing.assert_array_equal(plant.last[0], good)


# ---- topics --------------------------------------------------------------------------------------

def test_joint_states_are_published_every_tick_with_the_measured_state(manager, plant, robot):
    seen = []
    manager.topics.subscribe(JOINT_STATES, lambda msg: seen.append((msg.stamp, msg.position.copy())))
    plant.position[:] = np.arange(14) * 0.01
    for k in range(3):
        manager.tick(k * 0.01)
    assert [stamp for stamp, _ in seen] == [0.0, 0.01, 0.02]
    np.testing.assert_array_equal(seen[-1][1], np.arange(14) * 0.01)
    assert manager.topics.latest(JOINT_STATES).name == robot.names


def test_a_failing_joint_state_subscriber_does_not_stop_the_loop(manager):
    def broken(_msg):
        raise ValueError("display closed")

    manager.topics.subscribe(JOINT_STATES, broken)
    manager.tick(0.0)
    manager.tick(0.01)
    assert manager.tick_count == 2
    assert "display closed" in manager.topics.latest(SAFETY_STATUS).flags["controller_manager/broadcast"]


def test_safety_status_is_published_at_start_and_then_only_on_change(manager, plant):
    seen = []
    manager.topics.subscribe(SAFETY_STATUS, seen.append, latched=True)
    for k in range(5):
        manager.tick(k * 0.01)
    assert [s.ok for s in seen] == [True]
    plant.set_flag("rx", "can2: rx timeout id 22")
    for k in range(5, 10):
        manager.tick(k * 0.01)
    plant.clear_flag("rx")
    manager.tick(0.1)
    assert [(s.ok, s.flags) for s in seen] == [(True, {}), (False, {"plant/rx": "can2: rx timeout id 22"}),
                                                (True, {})]


# ---- shutdown ------------------------------------------------------------------------------------

def test_shutdown_releases_the_controller_then_deactivates_and_shuts_down_the_hardware(manager, plant):
    manager.request_mode(Mode.STANDBY)
    manager.tick(0.0)
    manager.shutdown()
    assert manager.command_owner is None
    assert manager.controllers["standby_controller"].lifecycle is Lifecycle.INACTIVE
    assert plant.events == ["plant.configure", "plant.activate", "plant.deactivate", "plant.shutdown"]


# ---- the paced loop and its statistics -----------------------------------------------------------

@pytest.fixture
def paced(robot, config):
    clock = Clock(step=1e-6)
    manager = ControllerManager(robot, [Plant("plant", robot.names)], config, update_rate=50.0, clock=clock,
                                sleep=clock.sleep)
    manager.start()
    yield manager, clock
    manager.shutdown()


def test_run_ticks_once_per_period_for_the_duration(paced):
    manager, _ = paced
    manager.run(duration=1.0)
    summary = manager.stats.summary()
    assert summary["ticks"] == 50
    assert summary["overruns"] == 0
    assert summary["period_ms"]["mean"] == pytest.approx(20.0, abs=1e-3)


def test_a_tick_that_ends_after_the_next_deadline_is_an_overrun_and_the_schedule_restarts(paced):
    manager, clock = paced

    def slow_third_tick(m):
        if m.tick_count == 3:
            clock.now += 0.030

    manager.run(duration=0.2, on_tick=slow_third_tick)
    assert manager.stats.overruns == 1
    assert manager.stats.ticks == 10
    periods_ms = manager.stats.periods[1:10] * 1e3
    assert periods_ms[2] == pytest.approx(30.0, abs=0.01)  # late once, then back on a 20 ms grid
    assert periods_ms[3:] == pytest.approx([20.0] * 6, abs=0.01)


def test_run_stops_when_the_stop_event_is_set(paced):
    manager, _ = paced
    stop = threading.Event()
    manager.run(stop=stop, on_tick=lambda m: stop.set() if m.tick_count == 7 else None)
    assert manager.tick_count == 7


def test_loop_stats_summary_reports_cost_period_jitter_and_overruns():
    stats = LoopStats(period=0.02, capacity=8)
    for k in range(10):  # wraps: keeps the last 8
        stats.record(cost=(k + 1) * 1e-5, period=float("nan") if k == 0 else 0.02 + 1e-4)
    stats.overruns = 2
    summary = stats.summary()
    assert summary["ticks"] == 10 and summary["overruns"] == 2
    assert summary["tick_us"]["median"] == pytest.approx(65.0)
    assert summary["tick_us"]["max"] == pytest.approx(100.0)
    assert summary["period_ms"]["mean"] == pytest.approx(20.1)
    assert summary["jitter_us"]["p99"] == pytest.approx(100.0)


def test_safety_flags_version_grows_on_every_change_only():
    flags = SafetyFlags("x")
    flags.set_flag("a", "one")
    flags.set_flag("a", "one")
    flags.set_flag("a", "two")
    flags.clear_flag("a")
    flags.clear_flag("a")
    assert flags.flags_version == 3


def test_loop_stats_split_the_tick_into_our_cpu_and_bus_io():
    stats = LoopStats(period=0.02, capacity=8)
    for k in range(4):
        stats.record(cost=100e-6 + k * 10e-6, period=0.02, io=40e-6)
    split = stats.split_us()
    assert split["io"]["median"] == pytest.approx(40.0)
    assert split["cpu"]["median"] == pytest.approx(75.0)
    assert split["cpu"]["max"] == pytest.approx(90.0)
    assert stats.summary()["tick_cpu_us"] == split["cpu"]


def test_the_tick_records_the_bus_io_every_component_reported(paced):
    manager, _ = paced
    (plant,) = manager.resources.components
    plant.io_s = 0.25e-3
    manager.tick()
    assert manager.stats.ios[manager.stats.ticks - 1] == pytest.approx(0.25e-3)


def test_a_run_measures_no_period_across_the_gap_before_its_schedule_starts(paced):
    manager, clock = paced
    manager.tick()  # a tick before the loop (the session's first), then a long pause
    clock.now += 0.5
    manager.run(duration=0.1, between_ticks=lambda: None)
    periods = manager.stats.periods[1:manager.stats.ticks]
    assert np.isnan(periods[0])  # the pause is not a period of the loop
    assert periods[1:] * 1e3 == pytest.approx([20.0] * (len(periods) - 1), abs=0.01)


def test_between_ticks_runs_after_each_tick_outside_its_measured_cost(paced):
    manager, clock = paced
    calls = []

    def housekeeping():
        calls.append(manager.tick_count)
        clock.now += 0.005  # 5 ms of collection: not the tick's cost

    manager.run(duration=0.1, between_ticks=housekeeping)
    assert calls == [1, 2, 3, 4, 5]
    assert manager.stats.costs[:5].max() < 0.005
