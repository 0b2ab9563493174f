"""EthercatSystem against the recorded process image of FakeMaster: calibration, CSP targets, enable, flags."""

from __future__ import annotations

import math
import time
import tracemalloc

import numpy as np
import pytest

from doubles.master import OPERATION_ENABLED, FakeMaster, erob_ring
from humanoid_prime.config.calibration import JointCalibration, load_calibration
from humanoid_prime.control.flags import Level
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD, RATED_TORQUE_NM
from humanoid_prime.drivers.ethercat._tick import layouts
from humanoid_prime.drivers.ethercat.errors import SdoRefused
from humanoid_prime.drivers.ethercat.master import OP_REQUEST_REPEAT_S, RX_DTYPE, TX_DTYPE, next_op_requests
from humanoid_prime.drivers.ethercat.system import EthercatSystem
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, AlState

C = COUNTS_PER_RAD


class Rig:
    def __init__(self, robot, tmp_path, calibration=None, master=None, emulated=False) -> None:
        self.robot = robot
        self.master = master or FakeMaster()
        calibration = calibration or load_calibration(robot.hardware)
        self.system = EthercatSystem(robot, calibration, update_rate=50.0, master=self.master,
                                     config_dir=tmp_path, emulated=emulated)
        self.command = CommandArrays(robot.n)
        self.state = StateArrays(robot.n)

    def tick(self) -> None:
        self.system.read(0.0, self.state)
        self.system.write(0.0, self.command)

    def ring_of(self, joint: str) -> int:
        return self.robot.hardware.erob_slaves[joint]


@pytest.fixture
def rig(robot, tmp_path):
    r = Rig(robot, tmp_path)
    r.master.position_counts[:] = np.arange(10) * 1000 - 4321
    r.system.configure()
    r.system.activate()
    yield r
    r.system.shutdown()


@pytest.fixture
def calibrated(robot, tmp_path):
    cal = load_calibration(robot.hardware).with_joint("left_wrist_yaw", JointCalibration(-1, 0.3))
    r = Rig(robot, tmp_path, cal)
    r.system.configure()
    r.system.activate()
    yield r
    r.system.shutdown()


def test_activation_enables_every_drive(rig):
    assert (rig.master.statusword == OPERATION_ENABLED).all()
    assert rig.master.operational


def test_enabling_puts_the_target_on_the_actual_position(rig):
    assert (rig.master.sent["target_position"] == rig.master.position_counts).all()
    assert (rig.master.sent["controlword"] == 0x0F).all()


def test_configure_writes_one_folded_slave_config_per_erob_joint(rig, tmp_path):
    assert sorted(p.stem for p in tmp_path.glob("*.yaml")) == sorted(rig.robot.hardware.erob_joints)


def test_the_keeper_feeds_the_ring_while_nobody_ticks(rig):
    sent = rig.master.frames
    deadline = time.monotonic() + 5.0
    while rig.master.kept_cycles < 5 and time.monotonic() < deadline:  # nobody calls read() or write()
        time.sleep(0.01)
    assert rig.master.kept_cycles >= 5
    assert rig.master.frames - sent >= 5


def test_the_keeper_stays_quiet_while_the_owner_ticks(rig):
    rig.tick()
    kept = rig.master.kept_cycles
    for _ in range(40):
        rig.tick()
        time.sleep(0.002)  # far inside the two periods (40 ms) the keeper waits before it takes over
    assert rig.master.kept_cycles == kept


def test_a_commanded_position_reaches_the_drive_through_factor_and_offset(calibrated):
    j = calibrated.robot.index("left_wrist_yaw")
    calibrated.command.position[j] = 0.5
    calibrated.command.stiffness[j] = 20.0
    calibrated.tick()
    ring = calibrated.ring_of("left_wrist_yaw")
    assert calibrated.master.sent["target_position"][ring] == math.floor(-0.5 * C + 0.3 * C + 0.5)


def test_the_drive_position_reads_back_in_the_joint_frame(calibrated):
    ring = calibrated.ring_of("left_wrist_yaw")
    calibrated.master.position_counts[ring] = round(-0.5 * C + 0.3 * C)
    calibrated.tick()
    assert calibrated.state.position[calibrated.robot.index("left_wrist_yaw")] == pytest.approx(0.5, abs=1e-5)


def test_each_joint_is_bound_to_its_ring_position(rig):
    for joint in rig.robot.hardware.erob_joints:
        rig.master.position_counts[rig.ring_of(joint)] = round(0.01 * rig.robot.index(joint) * C)
    rig.tick()
    for joint in rig.robot.hardware.erob_joints:
        assert rig.state.position[rig.robot.index(joint)] == pytest.approx(0.01 * rig.robot.index(joint), abs=1e-5)


def test_zero_stiffness_keeps_the_target_on_the_actual_position(rig):
    rig.command.position[:] = 1.0
    rig.command.stiffness[:] = 0.0
    rig.command.damping[:] = 6.0
    rig.master.position_counts[:] = [11, -22, 33, -44, 55, -66, 77, -88, 99, -110]
    rig.tick()
    rig.tick()
    assert (rig.master.sent["target_position"] == rig.master.position_counts).all()


def test_stiffness_makes_the_target_follow_the_command(rig):
    rig.command.position[:] = 0.25
    rig.command.stiffness[:] = 20.0
    rig.tick()
    assert (rig.master.sent["target_position"] == math.floor(0.25 * C + 0.5)).all()


def test_a_drive_that_is_not_enabled_keeps_its_target_on_the_actual_position(rig):
    rig.command.position[:] = 0.25
    rig.command.stiffness[:] = 20.0
    rig.master.fault(2, 0x8500)
    rig.master.position_counts[2] = 777
    rig.tick()
    assert rig.master.sent["target_position"][2] == 777


def test_velocity_and_effort_feed_forward_are_scaled_into_counts_and_per_mille(rig):
    j = rig.robot.index("left_shoulder_pitch")
    rig.command.velocity[j] = 1.0
    rig.command.effort[j] = 2.3
    rig.command.stiffness[j] = 20.0
    rig.tick()
    assert rig.master.sent["velocity_offset"][0] == math.floor(C + 0.5)
    assert rig.master.sent["torque_offset"][0] == round(2.3 * 1000 / RATED_TORQUE_NM)


def test_velocity_and_effort_read_back_in_si_units(rig):
    rig.master.velocity_counts[0] = round(2.0 * C)
    rig.master.torque_per_mille[0] = 100
    rig.tick()
    j = rig.robot.index("left_shoulder_pitch")
    assert rig.state.velocity[j] == pytest.approx(2.0, abs=1e-5)
    assert rig.state.effort[j] == pytest.approx(100 * RATED_TORQUE_NM / 1000)


def test_the_calibration_direction_flips_velocity_and_effort(calibrated):
    ring = calibrated.ring_of("left_wrist_yaw")
    calibrated.master.velocity_counts[ring] = round(2.0 * C)
    calibrated.master.torque_per_mille[ring] = 100
    calibrated.tick()
    j = calibrated.robot.index("left_wrist_yaw")
    assert calibrated.state.velocity[j] == pytest.approx(-2.0, abs=1e-5)
    assert calibrated.state.effort[j] == pytest.approx(-100 * RATED_TORQUE_NM / 1000)


def test_a_nan_position_holds_the_last_target_while_the_joint_moves(rig):
    rig.command.position[:] = 0.25
    rig.command.stiffness[:] = 20.0
    rig.tick()
    rig.command.position[:] = np.nan
    rig.command.stiffness[:] = 0.0
    rig.master.position_counts[:] = 12345
    rig.tick()
    rig.tick()
    assert (rig.master.sent["target_position"] == math.floor(0.25 * C + 0.5)).all()


def test_a_nan_position_right_after_enabling_holds_the_enabled_position(rig):
    rig.command.position[:] = np.nan
    enabled_at = rig.master.position_counts.copy()
    rig.master.position_counts[:] += 5000
    rig.tick()
    assert (rig.master.sent["target_position"] == enabled_at).all()


def test_a_finite_position_with_zero_stiffness_follows_even_after_a_hold(rig):
    rig.command.position[:] = np.nan
    rig.tick()
    rig.command.position[:] = 0.0
    rig.master.position_counts[:] = 4242
    rig.tick()
    rig.tick()
    assert (rig.master.sent["target_position"] == 4242).all()


def test_a_single_lost_frame_is_counted_but_not_flagged(rig):
    rig.master.wkc_override = -1
    rig.tick()
    rig.tick()
    rig.master.wkc_override = None
    rig.tick()
    assert rig.system.wkc_errors == 2
    assert "ethercat/wkc" not in rig.system.flags


def test_a_working_counter_mismatch_for_three_cycles_raises_a_flag_until_it_recovers(rig):
    rig.master.wkc_override = 20
    for _ in range(3):
        rig.tick()
    assert rig.system.flags["ethercat/wkc"] == ("EtherCAT working counter 20, expected 30 on fake0 for 3 cycles: "
                                                "process data is not reaching every drive")
    rig.master.wkc_override = None
    rig.tick()
    assert "ethercat/wkc" not in rig.system.flags


def test_an_emulated_ring_that_falls_silent_blames_the_emulator_not_a_cable(robot, tmp_path):
    rig = Rig(robot, tmp_path, emulated=True)
    rig.system.configure()
    rig.system.activate()
    rig.master.wkc_override = 0
    for _ in range(3):
        rig.tick()
    assert rig.system.flags["ethercat/wkc"] == (
        "no EtherCAT drive answered on fake0 for 3 cycles (working counter 0): the virtual Prime stopped answering "
        "or fell behind (a loaded machine)")
    rig.system.shutdown()


def test_a_line_cut_before_the_first_drive_is_flagged_as_such_and_the_text_follows_the_count(rig):
    rig.master.wkc_override = 0  # nothing answers: no slave can be named by the supervision either
    for _ in range(3):
        rig.tick()
    assert rig.system.flags["ethercat/wkc"] == (
        "no EtherCAT drive answered on fake0 for 3 cycles (working counter 0): the line is cut before the first "
        "drive; check the cable from fake0 and the power of ring 0 (left_shoulder_pitch)")
    rig.master.wkc_override = 20  # the first drive is back, some of the others not yet
    rig.tick()
    assert rig.system.flags["ethercat/wkc"].startswith("EtherCAT working counter 20, expected 30 on fake0")
    rig.master.wkc_override = None
    rig.tick()
    assert "ethercat/wkc" not in rig.system.flags


def test_a_drive_fault_raises_a_flag_with_the_decoded_statusword_and_error(rig):
    rig.master.fault(3, 0x8500)
    rig.system.read(0.0, rig.state)
    text = rig.system.flags["ethercat/ring3/fault"]
    assert text.startswith("left_elbow_pitch (ring 3): fault, statusword 4616 (0x1208), "
                           "error 0x8500 position (following) error over limit")


def test_a_drive_fault_latches_until_the_operator_resets_it(rig):
    rig.master.fault(3, 0x8500)
    controlwords = []
    for _ in range(5):
        rig.tick()
        controlwords.append(int(rig.master.sent["controlword"][3]))
    assert controlwords == [0x00] * 5  # disable voltage; no fault reset of its own
    rig.system.read(0.0, rig.state)
    assert "latched" in rig.system.flags["ethercat/ring3/fault"]
    assert rig.system.latched_faults() == [rig.system.flags["ethercat/ring3/fault"].split(" (latched")[0]]
    rig.system.reset_faults()
    controlwords = []
    for _ in range(5):
        rig.tick()
        controlwords.append(int(rig.master.sent["controlword"][3]))
    assert controlwords == [0x80, 0x06, 0x07, 0x0F, 0x0F]
    assert rig.master.statusword[3] == OPERATION_ENABLED
    rig.system.read(0.0, rig.state)
    assert "ethercat/ring3/fault" not in rig.system.flags and rig.system.latched_faults() == []


def test_a_reset_is_one_rising_edge_and_a_drive_whose_cause_persists_stays_latched(rig):
    rig.master.fault(3, 0x730F)
    rig.master.fault(5, 0x8500)
    rig.master.drives_follow = False  # the drives refuse the reset (the cause persists)
    rig.tick()
    rig.system.reset_faults()
    controlwords = []
    for _ in range(4):
        rig.tick()
        controlwords.append((int(rig.master.sent["controlword"][3]), int(rig.master.sent["controlword"][5])))
    rig.master.drives_follow = True
    assert controlwords == [(0x80, 0x80), (0x00, 0x00), (0x00, 0x00), (0x00, 0x00)]
    assert {int(rig.master.sent["controlword"][k]) for k in (0, 1, 2, 4)} == {0x0F}  # the others stay enabled


def test_a_lost_slave_raises_a_flag_naming_the_joint_and_its_state(rig):
    rig.master.slave_ok[2] = False
    rig.master.al_state[2] = AlState.SAFE_OP | AL_ERROR
    rig.master.health_version += 1
    rig.tick()
    assert rig.system.flags["ethercat/ring2/lost"] == ("left_shoulder_yaw (ring 2): slave lost "
                                                       "(in SAFE-OP + ERROR); recovering")
    rig.master.slave_ok[2] = True
    rig.master.health_version += 1
    rig.tick()
    assert "ethercat/ring2/lost" not in rig.system.flags


def test_a_lost_slave_s_flag_keeps_why_it_left_once_its_error_is_acknowledged(rig):
    rig.master.slave_ok[2] = False
    rig.master.left_op[2] += 1
    rig.master.left_op_code[2] = 0x001A
    rig.master.al_state[2] = AlState.SAFE_OP  # the recovery acknowledged the error: the flag and code are gone
    rig.master.health_version += 1
    rig.tick()
    assert rig.system.flags["ethercat/ring2/lost"] == (
        "left_shoulder_yaw (ring 2): slave lost (in SAFE-OP; it left OP with AL status 0x001A synchronization "
        "error); recovering")


def test_a_lost_slave_s_flag_says_why_its_recovery_cannot_go_on(rig):
    rig.master.slave_ok[2] = False
    rig.master.al_state[2] = AlState.SAFE_OP
    rig.master.recovery_problems[2] = "its clock did not come into step with the ring's: 50000 ns off"
    rig.master.health_version += 1
    rig.tick()
    assert rig.system.flags["ethercat/ring2/lost"] == (
        "left_shoulder_yaw (ring 2): slave lost (in SAFE-OP; its clock did not come into step with the ring's: "
        "50000 ns off); recovering")


def test_deactivation_disables_every_drive_and_keeps_the_ring_fed(rig):
    rig.tick()
    rig.system.deactivate()
    assert (rig.master.sent["controlword"] == 0).all()
    assert (rig.master.sent["target_position"] == rig.master.position_counts).all()
    assert rig.master.operational


def test_a_deactivated_system_enables_again_without_a_second_bringup(rig):
    rig.system.deactivate()
    frames = rig.master.frames
    rig.system.activate()
    assert (rig.master.statusword == OPERATION_ENABLED).all()
    assert rig.master.frames - frames < 10


def test_a_ring_that_does_not_match_fails_configure_and_releases_the_master(robot, tmp_path):
    from humanoid_prime.drivers.ethercat.errors import RingError

    r = Rig(robot, tmp_path, master=FakeMaster(erob_ring(9)))
    with pytest.raises(RingError, match="found 9 slaves, expected 10"):
        r.system.configure()
    assert r.master.closed


def test_an_sdo_before_the_ring_is_in_op_is_refused(robot, tmp_path):
    r = Rig(robot, tmp_path)
    r.system.configure()
    with pytest.raises(SdoRefused, match="refused: the ring is still being brought up.*0xA000"):
        r.master.sdo_read(0, 0x603F, 0)
    assert r.master.sdo_log == []


def test_an_sdo_after_activation_with_joint_states_flowing_goes_out(rig):
    rig.tick()
    rig.master.sdo_write(4, 0x2383, 0, b"\x01")
    assert rig.master.objects[(4, 0x2383, 0)] == b"\x01"
    assert rig.system.bus_ready


def test_an_sdo_is_refused_while_a_slave_is_out_of_op(rig):
    rig.tick()
    rig.master.slave_ok[5] = False
    with pytest.raises(SdoRefused, match="ring 5 is not in OP"):
        rig.master.sdo_read(5, 0x603F, 0)


def test_while_one_slave_recovers_the_others_still_take_sdos(rig):
    # a gate reset at the end of a run must not be refused on nine drives because the tenth is relocking
    rig.tick()
    rig.master.slave_ok[9] = False
    assert not rig.system.bus_ready
    rig.master.sdo_write(4, 0x2383, 0, b"\x00")
    assert rig.master.objects[(4, 0x2383, 0)] == b"\x00"
    with pytest.raises(SdoRefused, match="ring 9 is not in OP"):
        rig.master.sdo_write(9, 0x2383, 0, b"\x00")


def test_the_master_says_why_sdos_are_not_yet_allowed(robot, tmp_path, rig):
    r = Rig(robot, tmp_path)
    r.system.configure()
    assert "is not operational" in r.master.readiness()
    rig.tick()
    assert rig.master.readiness() == ""
    rig.master.slave_ok[7] = False
    rig.master.al_state[7] = 0x04 | 0x10  # SAFE-OP with the error flag
    rig.master.al_status_code[7] = 0x001A
    assert "has slaves recovering: ring 7 SAFE-OP + ERROR (AL status 0x001A" in rig.master.readiness()
    rig.master.slave_ok[7] = True
    rig.master.flowing = False
    rig.master.wkc = -1
    assert rig.master.readiness().endswith("process data is not flowing (working counter -1, expected 30)")


def test_the_bring_up_loop_asks_a_waiting_slave_for_op_again_only_every_half_second():
    # every AL control write is a frame round trip the next cycle waits behind: asking ten waiting slaves every
    # 10 ms at 1 kHz delayed a frame past the drives' sync tolerance each time and kept restarting their DC lock
    to_push = next_op_requests
    waiting = [(AlState.SAFE_OP, 0)] * 3
    asked = np.zeros(3)  # the broadcast OP request at t = 0
    assert to_push(waiting, asked, 0.01) == []
    assert to_push(waiting, asked, OP_REQUEST_REPEAT_S - 0.001) == []
    assert to_push(waiting, asked, OP_REQUEST_REPEAT_S) == [(k, AlState.SAFE_OP) for k in range(3)]
    assert asked.tolist() == [OP_REQUEST_REPEAT_S] * 3
    # an error is acknowledged at once, and OP asked for at the next look, however recently it was asked before
    states = [(AlState.OP, 0), (AlState.SAFE_OP | AL_ERROR, 0x001A), (AlState.PRE_OP, 0)]
    assert to_push(states, asked, 0.6) == [(1, AlState.SAFE_OP | AL_ERROR)]
    assert to_push([(AlState.OP, 0), (AlState.SAFE_OP, 0), (AlState.PRE_OP, 0)], asked, 0.61) == [(1, AlState.SAFE_OP)]
    assert to_push([(AlState.OP, 0), (AlState.SAFE_OP, 0), (AlState.PRE_OP, 0)], asked, 0.62) == []


def test_read_and_write_keep_no_memory_per_tick(rig):
    rig.command.stiffness[:] = 20.0
    rig.command.position[:] = 0.1
    rig.tick()
    for _ in range(10):
        rig.tick()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for _ in range(2000):
            rig.tick()
        retained = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert retained < 1024  # NumPy's one-off caches only; one array kept per tick would be 2000 times more


def test_a_drive_that_never_enables_fails_activation_with_its_state(robot, tmp_path):
    master = FakeMaster()
    master.drives_follow = False  # drives ignore every controlword
    r = Rig(robot, tmp_path, master=master)
    r.system.enable_timeout_s = 0.05
    r.system.configure()
    with pytest.raises(Exception, match=r"right_shoulder_yaw \(ring 7\): switch on disabled, statusword 592"):
        r.system.activate()
    r.system.shutdown()


def test_the_bringup_dc_fault_clears_by_itself(robot, tmp_path):
    master = FakeMaster()
    master.fault(4, 0xA000)  # raised while the drive's DC locked
    r = Rig(robot, tmp_path, master=master)
    r.system.configure()
    r.system.activate()
    assert r.system.enabled.all()
    r.system.shutdown()


def test_a_drive_in_another_fault_at_bringup_stays_latched_and_the_rest_enable(robot, tmp_path):
    master = FakeMaster()
    master.fault(7, 0x730F)
    r = Rig(robot, tmp_path, master=master)
    r.system.configure()
    r.system.activate()  # does not wait out the enable timeout for a latched drive
    joint = r.robot.hardware.erob_joints.index("right_shoulder_yaw")
    assert r.system.faulted[joint] and not r.system.enabled[joint]
    assert r.system.enabled.sum() == 9
    r.system.read(0.0, r.state)
    assert r.system.flags["ethercat/ring7/fault"].startswith(
        "right_shoulder_yaw (ring 7): fault, statusword 4616 (0x1208), error 0x730F multi-turn battery low")
    r.system.shutdown()


def test_efforts_scale_with_the_rated_torque_each_drive_reports(robot, tmp_path):
    master = FakeMaster()
    master.rated_torque_mnm[0] = 31000  # an eRob80H120I
    r = Rig(robot, tmp_path, master=master)
    r.system.configure()
    r.system.activate()
    j = robot.index("left_shoulder_pitch")
    r.command.effort[j] = 3.1
    r.command.stiffness[j] = 20.0
    r.master.torque_per_mille[0] = 500
    r.tick()
    assert r.master.sent["torque_offset"][0] == 100  # per mille of 31 N*m, not of the nominal 23
    r.tick()
    assert r.state.effort[j] == pytest.approx(15.5)
    assert r.system.rated_torque_nm[0] == 31.0 and r.system.rated_torque_nm[1] == 23.0
    assert "ethercat/ring0/rated_torque" not in r.system.flags
    r.system.shutdown()


def test_an_unread_rated_torque_falls_back_to_nominal_with_a_warning(robot, tmp_path):
    master = FakeMaster()
    master.rated_torque_mnm[2] = None
    r = Rig(robot, tmp_path, master=master)
    r.system.configure()
    r.system.activate()
    assert r.system.flags["ethercat/ring2/rated_torque"] == (
        "left_shoulder_yaw (ring 2): rated torque (0x6076) unknown (no reply (working counter 0)); efforts "
        f"scaled with the nominal {RATED_TORQUE_NM:g} N*m")
    assert r.system.levels["ethercat/ring2/rated_torque"] is Level.WARN
    assert math.isnan(r.system.rated_torque_nm[2])
    j = robot.index("left_shoulder_yaw")
    r.command.effort[j] = 2.3
    r.command.stiffness[j] = 20.0
    r.tick()
    assert r.master.sent["torque_offset"][2] == 100
    r.system.shutdown()


def test_the_torque_offset_is_clamped_to_the_drive_s_range(rig):
    j = rig.robot.index("left_shoulder_pitch")
    rig.command.stiffness[j] = 20.0
    rig.command.effort[j] = 1e4
    rig.tick()
    assert rig.master.sent["torque_offset"][0] == 3000  # +-3000 per mille (ZeroErr EDS), not the int16 range
    rig.command.effort[j] = -1e4
    rig.tick()
    assert rig.master.sent["torque_offset"][0] == -3000


def test_a_drive_that_drops_out_mid_run_stays_disabled_until_the_operators_reset(rig):
    from doubles.master import SWITCH_ON_DISABLED

    rig.tick()
    ring = rig.ring_of("left_elbow_pitch")
    rig.master.statusword[ring] = SWITCH_ON_DISABLED  # its slave lost power and came back
    for _ in range(5):  # enabling takes three steps: five ticks would have enabled it
        rig.tick()
    assert rig.master.statusword[ring] == SWITCH_ON_DISABLED
    assert rig.master.sent["controlword"][ring] == 0
    flag = rig.system.flags[f"ethercat/ring{ring}/disabled"]
    assert f"left_elbow_pitch (ring {ring}): the drive dropped out (power or link" in flag
    assert (rig.master.statusword[np.arange(10) != ring] == OPERATION_ENABLED).all()
    rig.system.reset_faults()
    for _ in range(5):
        rig.tick()
    assert rig.master.statusword[ring] == OPERATION_ENABLED
    assert f"ethercat/ring{ring}/disabled" not in rig.system.flags


def test_with_a_settings_keeper_a_reset_releases_a_dropped_drive_only_after_its_settings_are_restored(rig):
    from doubles.master import SWITCH_ON_DISABLED

    wakes = []
    rig.system.on_restore_needed = lambda: wakes.append(True)  # as the impedance manager sets it
    rig.tick()
    rig.master.statusword[4] = SWITCH_ON_DISABLED  # its slave lost power: factory gains, back in OP
    rig.tick()
    assert wakes and rig.system.awaiting_restore() == [(4, 0)]
    assert "impedance settings are restored" in rig.system.flags["ethercat/ring4/disabled"]
    rig.system.reset_faults()
    for _ in range(5):
        rig.tick()
    assert rig.master.statusword[4] == SWITCH_ON_DISABLED  # the reset came before the settings: still held
    rig.master.left_op[4] += 1  # it left OP again while its settings were written: they may be lost again
    rig.system.settings_restored(4, 0)
    assert rig.system.awaiting_restore() == [(4, 1)]
    rig.system.settings_restored(4, 1)
    rig.tick()
    assert rig.system.awaiting_restore() == []
    assert "latched" in rig.system.flags["ethercat/ring4/disabled"]
    rig.system.reset_faults()
    for _ in range(5):
        rig.tick()
    assert rig.master.statusword[4] == OPERATION_ENABLED
    assert "ethercat/ring4/disabled" not in rig.system.flags


def test_a_held_drive_whose_slave_drops_again_after_its_settings_came_back_waits_for_them_anew(rig):
    # restored, not yet released by the operator, and then its slave lost power again: factory settings once more
    from doubles.master import SWITCH_ON_DISABLED

    rig.system.on_restore_needed = lambda: None
    rig.tick()
    rig.master.statusword[4] = SWITCH_ON_DISABLED
    rig.tick()
    rig.system.settings_restored(4, 0)
    rig.tick()
    assert rig.system.awaiting_restore() == [] and "latched" in rig.system.flags["ethercat/ring4/disabled"]
    for ok in (False, True):  # out of OP and back: the supervision counts the departure
        rig.master.slave_ok[4] = ok
        rig.master.left_op[4] += not ok
        rig.master.health_version += 1
        rig.tick()
    assert rig.system.awaiting_restore() == [(4, 1)]
    assert "impedance settings are restored" in rig.system.flags["ethercat/ring4/disabled"]
    rig.system.reset_faults()
    for _ in range(5):
        rig.tick()
    assert rig.master.statusword[4] == SWITCH_ON_DISABLED  # not released on the settings it booted with


def test_a_faulted_drive_that_leaves_its_fault_by_itself_is_held_until_the_operators_reset(rig):
    """A drive in fault that loses power comes back out of it: without a fault reset of ours, that is a drop."""
    from doubles.master import SWITCH_ON_DISABLED

    rig.tick()
    rig.master.fault(2, 0x7500)
    rig.tick()
    assert "ethercat/ring2/fault" in rig.system.flags
    rig.master.statusword[2] = SWITCH_ON_DISABLED  # power lost and back: the fault is gone, nobody reset it
    rig.master.error_code[2] = 0
    for _ in range(5):
        rig.tick()
    assert rig.master.statusword[2] == SWITCH_ON_DISABLED and rig.master.sent["controlword"][2] == 0
    assert "ethercat/ring2/disabled" in rig.system.flags and "ethercat/ring2/fault" not in rig.system.flags
    rig.system.reset_faults()
    for _ in range(5):
        rig.tick()
    assert rig.master.statusword[2] == OPERATION_ENABLED


def test_a_drive_the_operators_reset_takes_out_of_its_fault_enables_at_once(rig):
    rig.tick()
    rig.master.fault(2, 0x7500)
    rig.tick()
    rig.system.reset_faults()
    for _ in range(6):
        rig.tick()
    assert rig.master.statusword[2] == OPERATION_ENABLED
    assert not {"ethercat/ring2/disabled", "ethercat/ring2/fault"} & set(rig.system.flags)


def test_a_reset_while_the_slave_is_still_away_leaves_its_drive_held(rig):
    from doubles.master import SWITCH_ON_DISABLED

    rig.tick()
    rig.master.statusword[7] = SWITCH_ON_DISABLED
    rig.master.slave_ok[7] = False
    rig.tick()
    rig.system.reset_faults()
    for _ in range(5):
        rig.tick()
    assert rig.master.statusword[7] == SWITCH_ON_DISABLED
    assert "ethercat/ring7/disabled" in rig.system.flags


def test_a_non_finite_feed_forward_goes_out_as_zero_and_targets_clamp_to_the_pdo_type(rig):
    j = rig.robot.index("left_shoulder_pitch")
    rig.command.stiffness[j] = 20.0
    rig.command.velocity[j], rig.command.effort[j] = math.inf, math.nan
    rig.command.position[j] = 1e9  # rad: far past INTEGER32 counts
    rig.tick()
    assert rig.master.sent["velocity_offset"][0] == 0
    assert rig.master.sent["torque_offset"][0] == 0
    assert rig.master.sent["target_position"][0] == np.iinfo(np.int32).max
    rig.command.position[j] = -1e9
    rig.tick()
    assert rig.master.sent["target_position"][0] == np.iinfo(np.int32).min


def test_the_compiled_tick_s_structs_are_the_pdo_layout():
    for key, dtype in (("rx", RX_DTYPE), ("tx", TX_DTYPE)):
        fields, size = layouts()[key]
        assert fields == tuple((name, dtype.fields[name][1]) for name in dtype.names)
        assert size == dtype.itemsize


def test_the_compiled_tick_refuses_a_process_image_of_another_layout(robot, tmp_path):
    """The kernel reaches the process image through C structs: a layout that differs fails at binding,
    before anything is written at the wrong offset."""
    narrow = np.dtype([(name, "<i2" if name == "position_actual" else TX_DTYPE.fields[name][0])
                       for name in TX_DTYPE.names])
    r = Rig(robot, tmp_path, master=FakeMaster(input_dtype=narrow))
    r.system.configure()
    with pytest.raises(ValueError, match="dtype mismatch"):
        r.system.activate()
    r.system.shutdown()


def test_a_slave_out_of_op_and_back_between_two_ticks_is_said_for_one_tick_with_why_it_left(rig):
    """A loop kept off the CPU while the supervision found a slave out of OP and brought it back: the next tick
    says so, with the AL status code the slave gave for leaving, and the tick after clears it."""
    rig.tick()
    rig.master.left_op[2] += 1
    rig.master.left_op_code[2] = 0x001B
    rig.master.health_version += 1
    rig.tick()
    assert rig.system.flags["ethercat/ring2/lost"] == (
        "left_shoulder_yaw (ring 2): slave left OP (AL status 0x001B sync manager watchdog) and came back")
    rig.tick()
    assert "ethercat/ring2/lost" not in rig.system.flags
