"""prime limp's procedure: damped limp of one eRob, restored exactly as found on every exit path."""

import pytest

from doubles.mailboxes import FACTORY_WINDOW, DriveMailboxes
from humanoid_prime.calibration.limp import DampedLimp
from humanoid_prime.errors import PrimeError


def found(drives, p):
    return dict(drives.values[p])


def test_limp_sets_gate_then_zero_position_gain_and_integral(robot):
    drives = DriveMailboxes()
    with DampedLimp(drives, 3) as limp:
        assert drives.values[3] == {"gate": 1, "pos_reg": 0, "vel_reg": 94, "integral": 0, "window": FACTORY_WINDOW}
        assert limp.readback.registers.pos_reg == 0 and limp.readback.gate == 1


def test_limp_can_lower_the_damping(robot):
    drives = DriveMailboxes()
    with DampedLimp(drives, 3, vel_reg=20):
        assert drives.values[3]["vel_reg"] == 20


def test_registers_are_restored_after_enter(robot):
    drives = DriveMailboxes()
    before = found(drives, 3)
    with DampedLimp(drives, 3):
        pass
    assert found(drives, 3) == before


@pytest.mark.parametrize("exc", [KeyboardInterrupt, RuntimeError, SystemExit])
def test_registers_are_restored_on_any_exception(robot, exc):
    drives = DriveMailboxes()
    before = found(drives, 5)
    with pytest.raises(exc), DampedLimp(drives, 5):
        raise exc()
    assert found(drives, 5) == before


def test_other_slaves_are_untouched(robot):
    drives = DriveMailboxes()
    before = {p: found(drives, p) for p in range(10) if p != 3}
    with DampedLimp(drives, 3):
        assert {p: found(drives, p) for p in range(10) if p != 3} == before


def test_lost_bus_reports_which_registers_were_not_restored(robot):
    drives = DriveMailboxes()
    with pytest.raises(PrimeError) as info, DampedLimp(drives, 3):
        drives.dead.add(3)
    text = str(info.value)
    assert "ring 3: could not restore" in text
    for name in ("pos_reg 0x2382:01", "integral 0x2381:02", "gate 0x2383"):
        assert name in text


def test_limp_that_does_not_take_is_reported_and_undone(robot):
    drives = DriveMailboxes()
    before = found(drives, 1)
    original = drives.sdo_write

    def gate_stuck(position, index, sub_index, data):
        if (index, sub_index) == (0x2383, 0) and int.from_bytes(data, "little") == 1:
            return  # a drive that never arms the gate: gain writes are ignored
        original(position, index, sub_index, data)

    drives.sdo_write = gate_stuck
    with pytest.raises(PrimeError, match="limp did not take"), DampedLimp(drives, 1):
        pass
    assert found(drives, 1) == before
