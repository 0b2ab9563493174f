"""CiA402 drive states, controlword commands and eRob error codes (DESIGN §2).

Decoding only; no bus access. Every lookup answers for any integer: an unknown code is named as unknown,
never an exception.
"""

from __future__ import annotations

from enum import Enum


class DriveState(Enum):
    """CiA402 power state machine states, valued by their human labels."""

    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"
    UNDEFINED = "undefined"


# (mask, value) -> state, per CiA402: four states are told apart by 0x6F, four by 0x4F.
OPERATION_ENABLED_PATTERN = (0x6F, 0x27)
FAULT_PATTERN = (0x4F, 0x08)
_STATE_PATTERNS: tuple[tuple[int, int, DriveState], ...] = (
    (0x4F, 0x00, DriveState.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, DriveState.SWITCH_ON_DISABLED),
    (0x6F, 0x21, DriveState.READY_TO_SWITCH_ON),
    (0x6F, 0x23, DriveState.SWITCHED_ON),
    (*OPERATION_ENABLED_PATTERN, DriveState.OPERATION_ENABLED),
    (0x6F, 0x07, DriveState.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, DriveState.FAULT_REACTION_ACTIVE),
    (*FAULT_PATTERN, DriveState.FAULT),
)

# Statusword bits; 12 and 13 carry their cyclic-synchronous-position meaning (Prime runs CSP only).
STATUSWORD_BITS: dict[int, str] = {
    0: "ready to switch on",
    1: "switched on",
    2: "operation enabled",
    3: "fault",
    4: "voltage enabled",
    5: "quick stop",
    6: "switch on disabled",
    7: "warning",
    8: "manufacturer specific (bit 8)",
    9: "remote",
    10: "target reached",
    11: "internal limit active",
    12: "drive follows the command value",
    13: "following error",
    14: "manufacturer specific (bit 14)",
    15: "manufacturer specific (bit 15)",
}

# Controlword commands (the low byte; bit 7 is fault reset).
DISABLE_VOLTAGE = 0x00
QUICK_STOP = 0x02
SHUTDOWN = 0x06
SWITCH_ON = 0x07
ENABLE_OPERATION = 0x0F
FAULT_RESET = 0x80

# eRob error codes (0x603F, history in 0x1003): meaning, and what usually causes it on Prime.
ERROR_CODES: dict[int, str] = {
    0x0000: "no error",
    0xA000: "EtherCAT communication error",
    0x8500: "position (following) error over limit",
    0x8400: "velocity error over limit",
    0x8130: "CAN heartbeat error",
    0x730F: "multi-turn battery low (latched)",
}
# The one fault that clears by itself: a drive may raise it while its DC locks during bring-up.
BRINGUP_TRANSIENT_FAULT = 0xA000

ERROR_HINTS: dict[int, str] = {
    0xA000: "mailbox (SDO) traffic during DC activation, a starved output watchdog, or a SYNC0 cycle that differs "
            "from the frame period; keep SDOs off the bus until joint states flow",
    0x8500: "the CSP target stayed put while the joint moved; keep the target on the actual position while "
            "stiffness is zero",
    0x8400: "the joint moved faster than the drive's velocity error window allows",
    0x8130: "the drive lost its CAN heartbeat",
    0x730F: "replace the multi-turn encoder battery, then clear the latched error",
}

def drive_state(statusword: int) -> DriveState:
    """The CiA402 state a statusword reports (UNDEFINED for a bit pattern no state has)."""
    for mask, value, state in _STATE_PATTERNS:
        if statusword & mask == value:
            return state
    return DriveState.UNDEFINED


def set_bits(statusword: int) -> list[str]:
    """Names of the statusword bits that are set, lowest bit first."""
    return [name for bit, name in STATUSWORD_BITS.items() if statusword >> bit & 1]


def enable_step(statusword: int) -> int:
    """The controlword that moves a drive one step toward operation enabled.

    Fault reset acts on the rising edge of bit 7: while the drive stays in fault, the caller alternates
    FAULT_RESET (0x80) with DISABLE_VOLTAGE (0x00) on successive cycles. States the drive leaves on its
    own (not ready, fault reaction) and undefined patterns get DISABLE_VOLTAGE; quick stop goes back
    through switch on disabled. Operation enabled keeps ENABLE_OPERATION.
    """
    return {
        DriveState.SWITCH_ON_DISABLED: SHUTDOWN,
        DriveState.READY_TO_SWITCH_ON: SWITCH_ON,
        DriveState.SWITCHED_ON: ENABLE_OPERATION,
        DriveState.OPERATION_ENABLED: ENABLE_OPERATION,
        DriveState.FAULT: FAULT_RESET,
    }.get(drive_state(statusword), DISABLE_VOLTAGE)


def describe_error(code: int) -> str:
    """Meaning of an eRob error code (0x603F); unknown codes are named as such."""
    return ERROR_CODES.get(code, f"unknown eRob error 0x{code:04X}")
