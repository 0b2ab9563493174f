"""``SitoSystem`` against the emulated wrists on a virtual bus (lockstep: see conftest)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from doubles.sito import PERIOD, SITO_IDS
from humanoid_prime.config.calibration import JointCalibration, identity_calibration
from humanoid_prime.config.hardware import CommandLimits
from humanoid_prime.control.hardware import Lifecycle
from humanoid_prime.drivers.sito.protocol import COUNTS_PER_RAD, FrameType, position_to_counts
from humanoid_prime.drivers.sito.system import SitoSystem
from humanoid_prime.errors import ConfigError, PrimeError
from humanoid_prime.virtual.plant import InertiaPlant

ONE_COUNT = 1.0 / COUNTS_PER_RAD
GAINS, ENABLE, COMMAND, DISABLE = 0x45, 0x01, 0x09, 0x00


def types_by_id(frames: list[tuple[int, bytes]], frame_type: int) -> list[int]:
    return [(ident >> 8) & 0xFF for ident, _ in frames if ident & 0xFF == frame_type]


def standby(rig, position: float = 0.0) -> None:
    rig.command.position[rig.idx] = position
    rig.command.stiffness[rig.idx] = 20.0
    rig.command.damping[rig.idx] = 2.0


# --- lifecycle and order ------------------------------------------------------------------------------------

def test_joints_are_the_sito_joints_in_canonical_order(robot, make_rig):
    system = make_rig().system
    assert system.joints == ("left_wrist_roll", "left_wrist_pitch", "right_wrist_roll", "right_wrist_pitch")
    assert list(system.indices) == [4, 5, 11, 12]
    assert system.can_ids == SITO_IDS


def test_activation_sends_zero_gains_to_every_motor_then_enable(make_rig):
    rig = make_rig()
    rig.activate()
    frames = rig.host_frames()
    assert [(ident, data.hex()) for ident, data in frames] == (
        [(0x05060045 | can_id << 8, "0000000000000000") for can_id in SITO_IDS]
        + [(0x05060001 | can_id << 8, "0914140000000000") for can_id in SITO_IDS])


def test_activation_waits_for_feedback_from_every_motor(rig):
    assert all(rig.motor(i).enabled and rig.motor(i).feedback_sent >= 2 for i in SITO_IDS)


def test_activation_fails_naming_a_silent_motor_and_leaves_all_disabled(make_rig):
    rig = make_rig()
    rig.motor(38).silent = True
    with pytest.raises(PrimeError, match=r"right_wrist_roll \(CAN id 38\)"):
        rig.activate()
    rig.emulator.step(0.001)
    assert rig.system.lifecycle is Lifecycle.INACTIVE
    assert all(not rig.motor(i).enabled and rig.motor(i).disables == 1 for i in SITO_IDS)


def test_deactivate_disables_every_motor(rig):
    rig.system.deactivate()
    rig.emulator.step(0.001)
    assert types_by_id(rig.host_frames(), DISABLE) == list(SITO_IDS)
    assert all(not rig.motor(i).enabled for i in SITO_IDS)


def test_disable_is_eight_0x55(rig):
    rig.system.deactivate()
    assert {data for ident, data in rig.host_frames() if ident & 0xFF == DISABLE} == {b"\x55" * 8}


def test_shutdown_from_active_disables_every_motor(rig):
    rig.system.shutdown()
    rig.emulator.step(0.001)
    assert [rig.motor(i).disables for i in SITO_IDS] == [1, 1, 1, 1]


def test_an_exception_in_a_with_block_disables_every_motor(rig):
    with pytest.raises(RuntimeError), rig.system:
        rig.tick()
        raise RuntimeError("controller crashed")
    rig.emulator.step(0.001)
    assert all(not rig.motor(i).enabled for i in SITO_IDS)


def test_reactivation_enables_again(rig):
    rig.system.deactivate()
    rig.activate()
    assert all(rig.motor(i).enabled for i in SITO_IDS)


# --- what goes on the wire -----------------------------------------------------------------------------------

def test_command_frame_bytes_for_known_values(rig):
    rig.command.position[rig.idx] = 1.0
    rig.command.velocity[rig.idx] = 0.5
    rig.command.effort[rig.idx] = 0.459
    rig.command.stiffness[rig.idx] = 688.58
    rig.command.damping[rig.idx] = 2.25
    rig.tick()
    frames = dict(rig.host_frames())
    assert frames[0x05061609] == bytes.fromhex("0064145f000028be")
    assert frames[0x05061645] == bytes.fromhex("3f80000040000000")


def test_calibration_is_applied_to_commands(robot, make_rig):
    calibration = identity_calibration(robot.hardware).with_joint("left_wrist_roll", JointCalibration(-1, 0.1))
    rig = make_rig(calibration=calibration)
    rig.activate()
    rig.host_frames()
    rig.command.position[4], rig.command.velocity[4], rig.command.effort[4] = 0.2, 0.5, 0.459
    rig.tick()
    # raw = -1 * 0.2 + 0.1 = -0.1 rad -> -1043 counts; velocity -5215 counts/s; effort -100 mA
    assert dict(rig.host_frames())[0x05061609] == bytes.fromhex("ff9ceba1fffffbed")


def test_calibration_is_applied_to_state(robot, make_rig):
    calibration = identity_calibration(robot.hardware).with_joint("right_wrist_pitch", JointCalibration(-1, 0.1))
    rig = make_rig(calibration=calibration)
    rig.plant.q[rig.slot("right_wrist_pitch")] = 0.35
    rig.activate()
    rig.tick()
    assert rig.state.position[12] == pytest.approx(-(0.35 - 0.1), abs=ONE_COUNT)


def test_one_command_frame_per_motor_per_tick(rig):
    standby(rig)
    rig.tick(10)
    assert sorted(types_by_id(rig.host_frames(), COMMAND)) == sorted(SITO_IDS * 10)


def test_gains_are_sent_only_when_they_change(rig):
    standby(rig)
    rig.tick(10)
    assert types_by_id(rig.host_frames(), GAINS) == list(SITO_IDS)


def test_a_gain_change_on_one_joint_sends_one_gains_frame(rig):
    standby(rig)
    rig.tick(2)
    rig.host_frames()
    rig.command.stiffness[5] = 30.0
    rig.tick(5)
    assert types_by_id(rig.host_frames(), GAINS) == [23]


def test_unchanged_gains_are_refreshed_once_a_second(rig):
    standby(rig)
    rig.tick()
    rig.host_frames()
    rig.tick(51)  # a little over one second
    assert sorted(types_by_id(rig.host_frames(), GAINS)) == list(SITO_IDS)


def test_host_frames_at_50_hz_load_the_bus_under_5_percent(rig):
    from humanoid_prime.drivers.sito.bus import frame_bits

    standby(rig)
    rig.tick(50)  # one second
    host = [m for m in rig.sniffed() if m.arbitration_id & 0xFF in (GAINS, COMMAND)]
    assert sum(frame_bits(m) for m in host) / 1e6 < 0.05


# --- behaviour at the joint ----------------------------------------------------------------------------------

def test_commanded_position_is_reached_with_standby_gains(robot, make_rig):
    plant = InertiaPlant.wrists(4)
    plant.gravity[robot.hardware.sito_joints.index("left_wrist_pitch")] = 0.3
    rig = make_rig(plant=plant)
    rig.activate()
    standby(rig, position=0.3)
    rig.tick(50)
    target = position_to_counts(0.3) / COUNTS_PER_RAD
    expected = target
    for _ in range(50):  # kp (q_cmd - q) = gravity sin(q) with kp = 20 Nm/rad exactly
        expected = target - 0.3 * math.sin(expected) / 20.0
    assert rig.state.position[5] == pytest.approx(expected, abs=1.5 * ONE_COUNT)


def test_state_reports_position_velocity_and_effort(rig):
    rig.plant.q[rig.slot("left_wrist_roll")] = 0.2
    rig.command.effort[4] = 0.459
    rig.tick(2)
    assert rig.state.position[4] == pytest.approx(rig.plant.q[rig.slot("left_wrist_roll")], abs=0.02)
    assert rig.state.effort[4] == pytest.approx(0.459, abs=1e-9)


def test_wrists_are_limp_by_default(rig):
    rig.plant.external[rig.slot("left_wrist_roll")] = 0.2
    rig.tick(5)
    assert rig.motor(22).torque == 0.0
    assert rig.state.position[4] > 0.1


def test_a_non_finite_command_goes_limp_and_is_flagged(rig):
    standby(rig, position=0.2)
    rig.tick()
    rig.command.position[5] = math.nan
    rig.tick(2)
    assert (rig.motor(23).kp, rig.motor(23).kd, rig.motor(23).current_mA) == (0.0, 0.0, 0)
    assert rig.motor(22).kp == pytest.approx(20.0, rel=1e-6)
    assert "can2/invalid_command/23" in rig.system.flags


def test_velocity_beyond_int16_is_sent_clamped_and_flagged(rig):
    rig.command.velocity[11] = 5.0
    rig.tick()
    assert dict(rig.host_frames())[0x05062609][2:4] == bytes.fromhex("7fff")
    assert "3.14 rad/s" in rig.system.flags["can2/velocity_clamped/38"]


def test_effort_beyond_int16_is_sent_clamped_at_either_end_and_flagged(rig):
    sent = set()
    for effort in (1e6, -1e6):
        rig.command.effort[11] = effort
        rig.tick()
        sent.add(dict(rig.host_frames())[0x05062609][0:2])  # current, whichever way the joint is wired
        assert "can2/effort_clamped/38" in rig.system.flags
    assert sent == {bytes.fromhex("7fff"), bytes.fromhex("8000")}


def test_velocity_clamp_flag_clears_when_back_in_range(rig):
    rig.command.velocity[11] = 5.0
    rig.tick()
    rig.command.velocity[11] = 1.0
    rig.tick()
    assert "can2/velocity_clamped/38" not in rig.system.flags


# --- transport health flags ----------------------------------------------------------------------------------

def test_healthy_bus_raises_no_flag(rig):
    standby(rig)
    rig.tick(20)
    assert rig.system.flags == {}


def test_rx_timeout_is_raised_for_the_silent_motor_only(rig):
    rig.motor(39).silent = True
    rig.tick(12)  # silence counts from the first read (at 20 ms): 240 - 20 = 220 ms > 200 ms
    assert list(rig.system.flags) == ["can2/rx_timeout/39"]
    assert "right_wrist_pitch (CAN id 39)" in rig.system.flags["can2/rx_timeout/39"]


def test_an_emulated_wrist_that_falls_silent_blames_the_emulator_not_a_cable(make_rig):
    rig = make_rig(emulated=True)
    rig.activate()
    rig.motor(39).silent = True
    rig.tick(12)
    text = rig.system.flags["can2/rx_timeout/39"]
    assert "the emulated wrist fell behind (a loaded machine) or the virtual Prime stopped" in text
    assert "cable" not in text


def test_rx_timeout_is_not_raised_before_200_ms(rig):
    rig.motor(39).silent = True
    rig.tick(9)  # 180 ms
    assert rig.system.flags == {}


def test_rx_timeout_clears_when_feedback_returns(rig):
    rig.motor(39).silent = True
    rig.tick(12)
    rig.motor(39).silent = False
    rig.tick()
    assert rig.system.flags == {}


def test_frames_not_yet_stored_at_the_first_read_after_a_slow_start_are_no_timeout(make_rig):
    """Start-up held the interpreter for 300 ms after activation: the wrists sent their feedback, but the
    receive thread has not stored it when the first tick reads. That is no silence; a wrist that stays silent
    is flagged once the timeout has run from that first read."""
    rig = make_rig()
    rig.activate()
    rig.host_bus.hold()  # the receive thread gets no chance to store anything
    received = rig.system.frames_received
    for _ in range(15):
        rig.emulator.step(PERIOD)
    rig.system.read(rig.emulator.time, rig.state)  # the first tick, 300 ms after the last stored feedback
    assert rig.system.flags == {} and rig.system.frames_received == received
    rig.host_bus.release()  # the thread runs again and stores what waited
    rig.settle()
    rig.motor(39).silent = True
    rig.tick(9)  # 180 ms after the first read
    assert rig.system.flags == {}
    rig.tick(2)
    assert list(rig.system.flags) == ["can2/rx_timeout/39"]


def test_a_few_dropped_frames_do_not_time_out(rig):
    for can_id in SITO_IDS:
        rig.motor(can_id).drop_fraction = 0.3
    rig.tick(50)
    assert not any("rx_timeout" in key for key in rig.system.flags)


def test_tx_overrun_is_raised_when_frames_are_not_acknowledged(rig):
    rig.emulator.acknowledge = False
    rig.tick(3)
    assert "motors' power is off" in rig.system.flags["can2/tx_overrun"]
    assert "ENOBUFS" in rig.system.flags["can2/tx_overrun"]


def test_tx_overrun_clears_when_frames_are_acknowledged_again(rig):
    rig.emulator.acknowledge = False
    rig.tick(3)
    rig.emulator.acknowledge = True
    rig.tick(2)
    assert "can2/tx_overrun" not in rig.system.flags


def test_invalid_frames_are_flagged(rig):
    rig.motor(22).garbage = True
    rig.tick(3)
    assert "wrong length or unknown type" in rig.system.flags["can2/invalid_frame"]


def test_invalid_frame_flag_clears_after_200_ms_without_one(rig):
    rig.motor(22).garbage = True
    rig.tick(3)
    rig.motor(22).garbage = False
    rig.tick(11)
    assert rig.system.flags == {}


def test_undocumented_feedback_is_counted_and_ignored_not_flagged(rig):
    for can_id in SITO_IDS:
        rig.motor(can_id).undocumented_feedback = True  # 0xB0 and 0xB3, as a Sito may send
    standby(rig, position=0.1)
    rig.tick(5)
    sent = sum(rig.motor(can_id).undocumented_sent for can_id in SITO_IDS)
    assert sent >= 2 * len(SITO_IDS)
    assert rig.system.undecoded_frames == sent
    assert rig.system.invalid_frames == 0 and rig.system.flags == {}
    truth = np.array([rig.plant.q[rig.slot(name)] for name in rig.system.joints])
    assert np.abs(rig.state.position[rig.idx] - truth).max() < 0.02


def test_a_garbled_frame_never_reaches_a_controller(rig):
    for can_id in SITO_IDS:
        rig.motor(can_id).garbage = True
    standby(rig, position=0.1)
    for _ in range(25):
        rig.tick()
        truth = np.array([rig.plant.q[rig.slot(name)] for name in rig.system.joints])
        assert np.abs(rig.state.position[rig.idx] - truth).max() < 0.02  # one feedback period of motion
        assert np.all(np.abs(rig.state.velocity[rig.idx]) < 3.2)
    assert rig.system.invalid_frames >= 25 * 4


def test_bus_off_is_flagged(rig):
    rig.emulator.inject_bus_off()
    rig.tick()
    assert "bus-off" in rig.system.flags["can2/bus_off"]


def test_bus_off_stays_until_reactivation(rig):
    rig.emulator.inject_bus_off()
    rig.tick(20)
    assert "can2/bus_off" in rig.system.flags
    rig.system.deactivate()
    rig.activate()
    rig.tick()
    assert rig.system.flags == {}


def test_interface_down_is_flagged_and_the_loop_keeps_running(rig):
    rig.host_bus.shutdown()
    rig.emulator.step(PERIOD)
    rig.system.read(0.0, rig.state)
    rig.system.write(0.0, rig.command)
    rig.system.read(0.0, rig.state)
    assert "interface is down" in rig.system.flags["can2/interface_down"]
    assert "can2/tx_overrun" not in rig.system.flags


def test_flags_version_changes_only_when_flags_change(rig):
    rig.motor(39).silent = True
    rig.tick(12)
    assert "can2/rx_timeout/39" in rig.system.flags
    version = rig.system.flags_version
    rig.tick(5)
    assert rig.system.flags_version == version


def test_no_command_is_limp_without_a_flag(rig):
    """Nothing claims the wrists (a calibration run): NaN position and zero gains send them limp, unflagged."""
    system, emulator = rig.system, rig.emulator
    rig.command.data[:] = 0.0
    rig.command.position[:] = float("nan")
    rig.tick(3)
    assert not any("invalid_command" in key for key in system.flags)
    for motor in emulator.motors.values():
        assert motor.kp == 0.0 and motor.kd == 0.0


def test_above_what_the_bus_carries_commands_go_out_every_nth_tick_and_feedback_streams_at_that_cycle(make_rig):
    rig = make_rig(update_rate=1000.0)
    rig.activate()
    assert (rig.system.io_every, rig.system.feedback_ms) == (4, 4)
    assert all(rig.motor(i).feedback_ms == (4, 4, 0) for i in SITO_IDS)
    rig.sniffed()
    commands = []
    for _ in range(12):
        rig.tick()
        commands.append(sum(1 for ident, _ in rig.host_frames() if ident & 0xFF == FrameType.COMMAND))
    assert commands == [4, 0, 0, 0] * 3
    assert rig.system.io_s == 0.0  # a tick between bus cycles spends nothing on the bus
    rig.system.deactivate()
    rig.activate()  # a re-activation starts a new cycle: its first tick sends
    rig.sniffed()
    rig.tick()
    assert sum(1 for ident, _ in rig.host_frames() if ident & 0xFF == FrameType.COMMAND) == 4


# --- the hardware file's limits against the wire ---------------------------------------------------------------

def test_a_velocity_limit_the_int16_field_cannot_carry_is_refused_naming_the_key(robot):
    limits = {**robot.hardware.command_limits, "sito": CommandLimits(stiffness=100.0, damping=10.0, velocity=3.5)}
    fast = replace(robot, hardware=replace(robot.hardware, command_limits=limits))
    with pytest.raises(ConfigError) as caught:
        SitoSystem(fast, identity_calibration(fast.hardware), update_rate=50.0, bus=object())
    assert caught.value.key == "command_limits.sito.velocity"
    assert "3.5 rad/s is beyond what the Sito wire carries (3.1415 rad/s)" in caught.value.problem
