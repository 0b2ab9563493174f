"""One eRob's impedance settings over SDO (``DriveSettings``), and the parts of one switch (``gain_switch``)."""

import threading

import pytest

from doubles.mailboxes import FACTORY_WINDOW, DriveMailboxes
from humanoid_prime.control.flags import Level
from humanoid_prime.drivers.erob.gains import ErobRegisters
from humanoid_prime.drivers.ethercat.sdo_client import SizedSdo
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.drive_settings import DriveSettings
from humanoid_prime.runtime.gain_switch import Rendezvous, SlaveSwitch, SwitchReport

STANDBY = ErobRegisters(pos_reg=515, vel_reg=19, integral=0)
DAMPING = ErobRegisters(pos_reg=0, vel_reg=56, integral=0)


def drive(drives, *, window_counts=2 * FACTORY_WINDOW, retries=3, position=3):
    log: list = []
    settings = DriveSettings("left_elbow_pitch", position, SizedSdo(drives), window_counts, retries=retries,
                             closing=threading.Event(), log=log)
    return settings, log


def test_arming_widens_the_window_then_sets_the_gate_then_learns_the_registers():
    drives = DriveMailboxes()
    settings, log = drive(drives)
    assert settings.arm() is None
    assert [name for _t, _p, name, _v in log] == ["following_window", "gate"]
    assert drives.values[3]["window"] == 2 * FACTORY_WINDOW and drives.values[3]["gate"] == 1
    assert settings.gate_armed and settings.registers == ErobRegisters(300, 94, 5)


def test_a_window_wider_than_the_run_needs_is_kept():
    drives = DriveMailboxes()
    settings, _log = drive(drives, window_counts=FACTORY_WINDOW // 2)
    settings.arm()
    assert drives.values[3]["window"] == FACTORY_WINDOW


def test_nothing_is_armed_once_the_run_is_closing():
    drives = DriveMailboxes()
    closing = threading.Event()
    closing.set()
    settings = DriveSettings("left_elbow_pitch", 3, SizedSdo(drives), 1000, retries=0, closing=closing, log=[])
    assert settings.arm() is None
    assert not settings.gate_armed and drives.log == []


def test_a_gate_that_cannot_be_set_is_an_error_naming_the_joint_and_its_ring():
    drives = DriveMailboxes()
    drives.dead.add(3)
    settings, _log = drive(drives, retries=0)
    text, level = settings.arm()
    assert level is Level.ERROR and text.startswith("left_elbow_pitch (ring 3): gate not armed")
    assert not settings.gate_armed


def test_gains_go_out_only_where_they_change_in_the_order_that_is_never_stiffer_than_both_modes():
    drives = DriveMailboxes()
    settings, _log = drive(drives)
    settings.arm()
    # from the factory's (300, 94, 5): damping falls, so vel_reg goes before pos_reg
    assert settings.write_gains(Mode.STANDBY, STANDBY) == ((("integral", 0), ("vel_reg", 19), ("pos_reg", 515)), 0,
                                                           None)
    written, _retries, error = settings.write_gains(Mode.DAMPING, DAMPING)
    assert written == (("pos_reg", 0), ("vel_reg", 56)) and error is None  # damping rises: pos_reg first
    assert drives.registers(3) == (0, 56, 0) and settings.registers == DAMPING


def test_a_failed_write_is_retried_and_exhausted_retries_say_what_was_written():
    drives = DriveMailboxes()
    settings, _log = drive(drives, retries=1)
    settings.arm()
    drives.fail_next[3] = 1
    assert settings.write_gains(Mode.STANDBY, STANDBY)[1] == 1
    drives.fail_next[3] = 2
    written, _retries, error = settings.write_gains(Mode.DAMPING, DAMPING)
    assert written == () and error == "DAMPING gains not fully applied (nothing written): ring 3: SDO timeout"


def test_the_read_back_flags_a_drive_holding_other_gains_and_forgets_what_it_holds():
    drives = DriveMailboxes()
    settings, _log = drive(drives)
    settings.arm()
    settings.write_gains(Mode.STANDBY, STANDBY)
    drives.values[3]["pos_reg"] = 300  # changed behind the manager's back
    switch = SlaveSwitch(3, "left_elbow_pitch", (), 0, 0.01, mode="STANDBY")
    settings.check(switch, settings.written, STANDBY)
    assert switch.read_back == {"pos_reg": 300, "vel_reg": 19, "integral": 0}
    assert switch.problem.startswith("STANDBY switch: gains read back as")
    assert settings.registers is None  # the next switch writes all three


def test_a_read_back_overtaken_by_a_later_switch_leaves_it_to_that_switchs_own():
    drives = DriveMailboxes()
    settings, _log = drive(drives)
    settings.arm()
    settings.write_gains(Mode.STANDBY, STANDBY)
    switch = SlaveSwitch(3, "left_elbow_pitch", (), 0, 0.01, mode="STANDBY")
    settings.check(switch, settings.written - 1, STANDBY)
    assert switch.read_back is None and switch.problem is None


def test_a_drive_back_from_a_power_loss_gets_its_window_gate_and_the_current_gains_again():
    drives = DriveMailboxes()
    settings, log = drive(drives)
    settings.arm()
    settings.write_gains(Mode.STANDBY, STANDBY)
    drives.values[3] = {"gate": 0, "pos_reg": 300, "vel_reg": 94, "integral": 5, "window": FACTORY_WINDOW}
    del log[:]
    assert settings.restore((Mode.STANDBY, STANDBY)) is None
    assert [name for _t, _p, name, _v in log] == ["following_window", "gate", "integral", "vel_reg", "pos_reg"]
    assert drives.registers(3) == (515, 19, 0)


def test_a_failed_restore_keeps_the_drive_held():
    drives = DriveMailboxes()
    settings, _log = drive(drives, retries=0)
    settings.arm()
    drives.fail_next[3] = 1
    text, level = settings.restore((Mode.STANDBY, STANDBY))
    assert level is Level.ERROR and text.endswith("; its drive stays held disabled")


def test_reset_puts_the_gate_to_0_and_the_drives_own_window_back():
    drives = DriveMailboxes()
    settings, _log = drive(drives)
    settings.arm()
    assert settings.reset() is None
    assert drives.values[3]["gate"] == 0 and drives.values[3]["window"] == FACTORY_WINDOW


def test_a_reset_that_fails_names_the_joint_and_what_was_not_put_back():
    drives = DriveMailboxes()
    settings, _log = drive(drives, retries=0)
    settings.arm()
    drives.dead.add(3)
    problem = settings.reset()
    assert problem.startswith("left_elbow_pitch (ring 3): gate not reset: ")
    assert f"following-error window not restored to {FACTORY_WINDOW}" in problem


def test_a_switch_report_takes_the_slowest_slave_as_its_wall_time_and_the_spread_as_its_skew():
    slaves = (SlaveSwitch(0, "a", (), 1, 0.004), SlaveSwitch(1, "b", (), 2, 0.011), SlaveSwitch(2, "c", (), 0, 0.007))
    report = SwitchReport.of("STANDBY", slaves, together=True)
    assert (report.wall_seconds, report.skew_seconds, report.retries) == (0.011, pytest.approx(0.007), 3)
    assert report.ok and report.as_dict()["read_back"] == "pending"


def test_a_rendezvous_of_one_never_waits_and_one_whose_party_never_comes_is_not_together():
    alone = Rendezvous(1, timeout=60.0)
    alone.meet()
    assert alone.together
    missed = Rendezvous(2, timeout=0.01)
    missed.meet()  # the other party never arrives
    assert not missed.together
