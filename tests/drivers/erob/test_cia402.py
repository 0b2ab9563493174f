"""CiA402 statusword decoding, the enable sequence, and the error table."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from humanoid_prime.drivers.erob.cia402 import (
    DISABLE_VOLTAGE,
    ENABLE_OPERATION,
    FAULT_RESET,
    QUICK_STOP,
    SHUTDOWN,
    SWITCH_ON,
    DriveState,
    describe_error,
    drive_state,
    enable_step,
    set_bits,
)


def test_5687_is_operation_enabled():
    assert drive_state(5687) is DriveState.OPERATION_ENABLED
    assert DriveState.OPERATION_ENABLED.value == "operation enabled"


def test_4616_is_fault():
    assert drive_state(4616) is DriveState.FAULT
    assert DriveState.FAULT.value == "fault"


@pytest.mark.parametrize("statusword, state", [
    (0x0000, DriveState.NOT_READY_TO_SWITCH_ON),
    (0x0040, DriveState.SWITCH_ON_DISABLED),
    (0x0021, DriveState.READY_TO_SWITCH_ON),
    (0x0023, DriveState.SWITCHED_ON),
    (0x0027, DriveState.OPERATION_ENABLED),
    (0x0007, DriveState.QUICK_STOP_ACTIVE),
    (0x000F, DriveState.FAULT_REACTION_ACTIVE),
    (0x0008, DriveState.FAULT),
    (0x0001, DriveState.UNDEFINED),
])
def test_state_patterns(statusword, state):
    assert drive_state(statusword) is state


def test_high_bits_do_not_change_the_state():
    assert drive_state(0xFF80 | 0x27) is DriveState.OPERATION_ENABLED


def test_set_bits_of_5687():
    assert set_bits(5687) == ["ready to switch on", "switched on", "operation enabled", "voltage enabled",
                              "quick stop", "remote", "target reached", "drive follows the command value"]


def test_set_bits_of_4616():
    assert set_bits(4616) == ["fault", "remote", "drive follows the command value"]


def test_controlword_constants():
    assert (SHUTDOWN, SWITCH_ON, ENABLE_OPERATION, FAULT_RESET, DISABLE_VOLTAGE, QUICK_STOP) == (
        0x06, 0x07, 0x0F, 0x80, 0x00, 0x02)


@pytest.mark.parametrize("statusword, controlword", [
    (0x0040, SHUTDOWN),
    (0x0021, SWITCH_ON),
    (0x0023, ENABLE_OPERATION),
    (0x0027, ENABLE_OPERATION),
    (0x0008, FAULT_RESET),
    (0x0000, DISABLE_VOLTAGE),
    (0x000F, DISABLE_VOLTAGE),
    (0x0007, DISABLE_VOLTAGE),
])
def test_enable_step(statusword, controlword):
    assert enable_step(statusword) == controlword


def _drive(state: DriveState, controlword: int) -> DriveState:
    """The CiA402 transitions a drive makes for the commands enable_step sends."""
    command = controlword & 0x8F
    if state is DriveState.FAULT and command == FAULT_RESET:
        return DriveState.SWITCH_ON_DISABLED
    table = {
        (DriveState.SWITCH_ON_DISABLED, SHUTDOWN): DriveState.READY_TO_SWITCH_ON,
        (DriveState.READY_TO_SWITCH_ON, SWITCH_ON): DriveState.SWITCHED_ON,
        (DriveState.SWITCHED_ON, ENABLE_OPERATION): DriveState.OPERATION_ENABLED,
        (DriveState.QUICK_STOP_ACTIVE, DISABLE_VOLTAGE): DriveState.SWITCH_ON_DISABLED,
    }
    return table.get((state, command), state)


_WORDS = {DriveState.SWITCH_ON_DISABLED: 0x40, DriveState.READY_TO_SWITCH_ON: 0x21, DriveState.SWITCHED_ON: 0x23,
          DriveState.OPERATION_ENABLED: 0x27, DriveState.QUICK_STOP_ACTIVE: 0x07, DriveState.FAULT: 0x08}


@pytest.mark.parametrize("start", list(_WORDS))
def test_enable_steps_reach_operation_enabled_from_any_state(start):
    state = start
    for _ in range(5):
        state = _drive(state, enable_step(_WORDS[state]))
    assert state is DriveState.OPERATION_ENABLED


DESIGN_STATES = {  # (statusword & 0x6F) and (statusword & 0x4F) patterns, DESIGN §2
    0x6F: {0x21: DriveState.READY_TO_SWITCH_ON, 0x23: DriveState.SWITCHED_ON, 0x27: DriveState.OPERATION_ENABLED,
           0x07: DriveState.QUICK_STOP_ACTIVE},
    0x4F: {0x00: DriveState.NOT_READY_TO_SWITCH_ON, 0x40: DriveState.SWITCH_ON_DISABLED,
           0x0F: DriveState.FAULT_REACTION_ACTIVE, 0x08: DriveState.FAULT},
}


@given(st.integers(0, 0xFFFF))
def test_every_statusword_decodes_to_the_state_its_bit_pattern_names(statusword):
    named = [states[statusword & mask] for mask, states in DESIGN_STATES.items() if statusword & mask in states]
    assert drive_state(statusword) == (named[0] if named else DriveState.UNDEFINED)
    assert enable_step(statusword) in (SHUTDOWN, SWITCH_ON, ENABLE_OPERATION, FAULT_RESET, DISABLE_VOLTAGE)


@pytest.mark.parametrize("code, meaning", [
    (0xA000, "EtherCAT communication error"),
    (0x8500, "position (following) error over limit"),
    (0x8400, "velocity error over limit"),
    (0x8130, "CAN heartbeat error"),
    (0x730F, "multi-turn battery low (latched)"),
])
def test_erob_error_codes(code, meaning):
    assert describe_error(code) == meaning


def test_unknown_error_code_is_named_not_raised():
    assert describe_error(0x1234) == "unknown eRob error 0x1234"
