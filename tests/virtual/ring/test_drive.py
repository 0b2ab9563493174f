"""The eRob drive model: CiA402 states from controlwords, CSP impedance from the gain registers."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.drivers.erob.gains import gains_to_registers
from humanoid_prime.drivers.ethercat.wire import ABORT_LENGTH
from humanoid_prime.virtual.plant import InertiaPlant
from humanoid_prime.virtual.ring.drive import (
    ERROR_COMMUNICATION,
    ERROR_FOLLOWING,
    FACTORY_POS_REG,
    FACTORY_VEL_REG,
    Cia402State,
    ErobDrive,
)
from humanoid_prime.virtual.ring.od import SdoAbort


def command(drive: ErobDrive, controlword: int, mode: int = 8) -> None:
    drive.mode.value = mode
    drive.controlword.value = controlword
    drive.process_outputs()


def enable(drive: ErobDrive) -> None:
    for controlword in (0x06, 0x07, 0x0F):
        command(drive, controlword)


def write(drive: ErobDrive, address: tuple[int, int], value: int) -> None:
    """Download ``value`` with the size the drive holds the object in (as SizedSdo does)."""
    entry = drive.od.entry(*address)
    drive.od.download(address[0], address[1], value.to_bytes(entry.size, "little", signed=entry.fmt.islower()))


def run(drive: ErobDrive, plant: InertiaPlant, seconds: float, dt: float = 0.001) -> None:
    torque = np.zeros(1)
    braked = np.zeros(1, dtype=bool)
    for _ in range(round(seconds / dt)):
        torque[0] = drive.step(float(plant.q[0]), float(plant.qd[0]), dt)
        braked[0] = drive.braked
        plant.step(torque, braked, dt)
    drive.update_feedback(float(plant.q[0]), float(plant.qd[0]))


def stiffness_under(drive: ErobDrive, external_nm: float) -> float:
    """Hold target 0 against a constant external torque; realised stiffness = torque / deflection."""
    plant = InertiaPlant(np.array([0.3]))
    enable(drive)
    plant.external[0] = external_nm
    run(drive, plant, 4.0)
    return external_nm / float(plant.q[0])


def test_power_on_state_is_switch_on_disabled():
    drive = ErobDrive()
    assert drive.state == Cia402State.SWITCH_ON_DISABLED
    assert drive.statusword.value == 0x0250


@pytest.mark.parametrize(("controlwords", "state"), [
    ((0x06,), Cia402State.READY_TO_SWITCH_ON),
    ((0x06, 0x07), Cia402State.SWITCHED_ON),
    ((0x06, 0x07, 0x0F), Cia402State.OPERATION_ENABLED),
    ((0x06, 0x0F), Cia402State.OPERATION_ENABLED),
    ((0x06, 0x07, 0x0F, 0x07), Cia402State.SWITCHED_ON),
    ((0x06, 0x07, 0x0F, 0x06), Cia402State.READY_TO_SWITCH_ON),
    ((0x06, 0x07, 0x0F, 0x00), Cia402State.SWITCH_ON_DISABLED),
    ((0x06, 0x07, 0x0F, 0x02), Cia402State.QUICK_STOP_ACTIVE),
    ((0x07,), Cia402State.SWITCH_ON_DISABLED),
    ((0x0F,), Cia402State.SWITCH_ON_DISABLED),
])
def test_controlword_sequence_reaches_the_cia402_state(controlwords, state):
    drive = ErobDrive()
    for controlword in controlwords:
        command(drive, controlword)
    assert drive.state == state


def test_operation_enabled_in_csp_reports_5687():
    drive = ErobDrive()
    enable(drive)
    drive.update_feedback(0.0, 0.0)
    assert drive.statusword.value == 5687 == 0x1637
    assert drive.mode_display.value == 8


def test_fault_in_csp_reports_4616_with_the_error_code():
    drive = ErobDrive()
    enable(drive)
    drive.fault(ERROR_COMMUNICATION)
    drive.update_feedback(0.0, 0.0)
    assert drive.statusword.value == 4616 == 0x1208
    assert drive.error_code.value == 0xA000


def test_fault_reset_needs_a_rising_edge_of_bit_7():
    drive = ErobDrive()
    drive.fault(ERROR_COMMUNICATION)
    command(drive, 0x00)
    command(drive, 0x80)
    assert drive.state == Cia402State.SWITCH_ON_DISABLED
    assert drive.error_code.value == 0


def test_fault_reset_held_high_does_not_reset_a_new_fault():
    drive = ErobDrive()
    command(drive, 0x80)
    drive.fault(ERROR_COMMUNICATION)
    command(drive, 0x80)
    assert drive.state == Cia402State.FAULT


def test_latched_fault_survives_fault_reset_until_cleared():
    drive = ErobDrive()
    drive.fault(0x730F, latched=True)
    command(drive, 0x00)
    command(drive, 0x80)
    assert drive.state == Cia402State.FAULT
    drive.clear_latched()
    command(drive, 0x00)
    command(drive, 0x80)
    assert drive.state == Cia402State.SWITCH_ON_DISABLED


def test_error_history_keeps_newest_first_in_0x1003():
    drive = ErobDrive()
    drive.fault(ERROR_COMMUNICATION)
    drive.fault(ERROR_FOLLOWING)
    assert drive.od.value(0x1003, 0) == 2
    assert [drive.od.value(0x1003, 1), drive.od.value(0x1003, 2)] == [0x8500, 0xA000]
    assert drive.error_history == [0x8500, 0xA000]


def test_writing_zero_to_0x1003_0_clears_the_history():
    drive = ErobDrive()
    drive.fault(ERROR_COMMUNICATION)
    drive.od.download(0x1003, 0, b"\x00")
    assert drive.error_history == []


def test_gate_closed_runs_factory_gains_and_ignores_gain_writes():
    drive = ErobDrive()
    write(drive, (0x2382, 1), 100)
    write(drive, (0x2381, 1), 10)
    assert (drive.pos_reg.value, drive.vel_reg.value) == (FACTORY_POS_REG, FACTORY_VEL_REG)
    assert not drive.last_gain_write_applied
    kp, kd, _ = drive.gains
    assert kp == pytest.approx(300.0, rel=0.01)
    assert kd == pytest.approx(9.97, rel=0.01)


def test_factory_gains_hold_stiffly():
    assert stiffness_under(ErobDrive(), 10.0) == pytest.approx(300.0, rel=0.03)


def test_bus_gains_realise_0_7_of_the_nominal_stiffness():
    drive = ErobDrive()
    registers = gains_to_registers(20.0, 2.0)  # STANDBY, torque_efficiency 1.0
    write(drive, (0x2383, 0), 1)
    write(drive, (0x2382, 1), registers.pos_reg)
    write(drive, (0x2381, 1), registers.vel_reg)
    write(drive, (0x2381, 2), 0)
    assert stiffness_under(drive, 5.0) == pytest.approx(0.7 * 20.0, rel=0.03)


def test_efficiency_corrected_registers_realise_the_nominal_stiffness():
    drive = ErobDrive()
    registers = gains_to_registers(20.0, 2.0, efficiency=0.7)
    write(drive, (0x2383, 0), 1)
    write(drive, (0x2382, 1), registers.pos_reg)
    write(drive, (0x2381, 1), registers.vel_reg)
    assert stiffness_under(drive, 5.0) == pytest.approx(20.0, rel=0.03)


def test_closing_the_gate_restores_factory_registers():
    drive = ErobDrive()
    write(drive, (0x2383, 0), 1)
    write(drive, (0x2382, 1), 0)
    write(drive, (0x2383, 0), 0)
    assert drive.pos_reg.value == FACTORY_POS_REG


def test_zero_registers_leave_the_joint_limp():
    drive = ErobDrive()
    write(drive, (0x2383, 0), 1)
    write(drive, (0x2382, 1), 0)
    write(drive, (0x2381, 1), 0)
    plant = InertiaPlant(np.array([0.3]))
    enable(drive)
    plant.external[0] = 0.3  # 1 rad/s^2
    run(drive, plant, 0.5)
    assert float(plant.q[0]) == pytest.approx(0.5 * 1.0 * 0.5**2, rel=0.05)


def test_following_error_beyond_the_window_faults_with_0x8500():
    drive = ErobDrive()
    plant = InertiaPlant(np.array([0.3]))
    enable(drive)
    drive.target_position.value = round(1.0 * COUNTS_PER_RAD)  # 1 rad away: window is 0.5 rad
    run(drive, plant, 0.05)
    assert drive.state == Cia402State.FAULT
    assert drive.error_code.value == 0x8500
    assert drive.statusword.value == 0x1208


def test_following_error_inside_the_window_keeps_running():
    drive = ErobDrive()
    plant = InertiaPlant(np.array([0.3]))
    enable(drive)
    drive.target_position.value = round(0.1 * COUNTS_PER_RAD)
    run(drive, plant, 1.0)
    assert drive.state == Cia402State.OPERATION_ENABLED
    assert float(plant.q[0]) == pytest.approx(0.1, abs=0.002)


def test_disabled_drive_holds_the_joint_on_its_brake():
    drive = ErobDrive()
    plant = InertiaPlant(np.array([0.3]))
    plant.external[0] = 5.0
    run(drive, plant, 0.5)
    assert float(plant.q[0]) == 0.0


def test_feedback_objects_use_encoder_counts_and_per_mille_torque():
    drive = ErobDrive()
    enable(drive)
    drive.torque_nm = 2.3
    drive.update_feedback(1.0, -0.5)
    assert drive.position_actual.value == round(COUNTS_PER_RAD) == 83443
    assert drive.velocity_actual.value == round(-0.5 * COUNTS_PER_RAD)
    assert drive.torque_actual.value == 100  # 2.3 Nm of 23 Nm rated


def test_by_default_the_loop_gains_are_unsigned16_as_the_eds_declares_and_a_4_byte_write_aborts():
    drive = ErobDrive()
    write(drive, (0x2383, 0), 1)
    for address in ((0x2381, 1), (0x2381, 2), (0x2382, 1), (0x2382, 2)):
        assert drive.od.entry(*address).size == 2
        with pytest.raises(SdoAbort) as abort:
            drive.od.download(*address, struct.pack("<I", 20))
        assert abort.value.code == ABORT_LENGTH


def test_the_u32_variant_holds_the_gains_in_4_bytes_and_aborts_a_2_byte_write():
    drive = ErobDrive(gain_bytes=4)
    assert drive.od.entry(0x2382, 1).size == 4
    with pytest.raises(SdoAbort) as abort:
        drive.od.download(0x2382, 1, struct.pack("<H", 20))
    assert abort.value.code == ABORT_LENGTH


@pytest.mark.parametrize("address, value", [((0x2382, 0), 2), ((0x2381, 0), 2), ((0x1003, 0), 0),
                                            ((0x6502, 0), 0x38D)])
def test_the_object_layout_of_the_eds(address, value):
    assert ErobDrive().od.value(*address) == value


def test_the_error_history_keeps_the_four_newest():
    drive = ErobDrive()
    for code in (0x8500, 0xA000, 0x8400, 0x8130, 0x730F):
        drive.fault(code)
    assert drive.error_history == [0x730F, 0x8130, 0x8400, 0xA000]


@pytest.mark.parametrize("rated_mnm", [23000, 31000])
def test_rated_torque_is_read_only_pdo_mappable_and_scales_torque_actual(rated_mnm):
    drive = ErobDrive(rated_torque_mnm=rated_mnm)
    entry = drive.od.entry(0x6076, 0)
    assert (entry.value, entry.access, entry.pdo) == (rated_mnm, "ro", "tx")
    with pytest.raises(SdoAbort):
        drive.od.download(0x6076, 0, struct.pack("<I", 1000))
    drive.torque_nm = 2.3
    drive.update_feedback(0.0, 0.0)
    assert drive.torque_actual.value == round(2.3 / (rated_mnm / 1000) * 1000)


def test_the_torque_offset_takes_plus_minus_3000_per_mille():
    drive = ErobDrive()
    write(drive, (0x60B2, 0), 3000)
    with pytest.raises(SdoAbort):
        drive.od.download(0x60B2, 0, struct.pack("<h", 3001))


def test_at_power_up_the_drive_maps_the_vendor_layout():
    od = ErobDrive().od
    assert [od.value(0x1600, s) for s in range(4)] == [3, 0x607A0020, 0x60FE0020, 0x60400010]
    assert [od.value(0x1A00, s) for s in range(4)] == [3, 0x60640020, 0x60FD0020, 0x60410010]
