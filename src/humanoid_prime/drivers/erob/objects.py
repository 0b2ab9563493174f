"""eRob CoE object indices and the process-data layout Prime maps (DESIGN §2).

The same layout is used by the master (to map and decode), the slave-config fold (channels and
their factor/offset) and the ring emulator (to answer), so it lives here once.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

# CiA402 objects
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODE_OF_OPERATION = 0x6060
MODE_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TORQUE_ACTUAL = 0x6077
RATED_TORQUE = 0x6076  # u32 mN*m, read-only, read from each drive (an eRob80H120I reads 31000)
TARGET_POSITION = 0x607A
VELOCITY_OFFSET = 0x60B1
TORQUE_OFFSET = 0x60B2
ERROR_CODE = 0x603F
ERROR_HISTORY = 0x1003
FOLLOWING_ERROR_WINDOW = 0x6065
# CiA402 max torque, u16 per mille of 0x6076. ZeroErr's EDS V1.5 does not list it: a host probes for it.
MAX_TORQUE = 0x6072
DIGITAL_INPUTS = 0x60FD
# a VAR, mapped as 0x60FE:00: the drive's own dictionary as SOEM's slaveinfo lists it (0x1600 = 607A0020 60FE0020
# 60400010 in a public ZeroErr CSP example), and the public IgH eRob example maps 0x60FE, 0
DIGITAL_OUTPUTS = (0x60FE, 0x00)
SUPPORTED_DRIVE_MODES = 0x6502
TORQUE_OFFSET_LIMIT_PER_MILLE = 3000  # 0x60B2 range, +-3000 (ZeroErr EDS V1.5)

# Communication objects
DEVICE_TYPE = 0x1000
IDENTITY = 0x1018
SM_COMM_TYPE = 0x1C00
RXPDO_ASSIGN = 0x1C12
TXPDO_ASSIGN = 0x1C13
RXPDO_MAP = 0x1600
TXPDO_MAP = 0x1A00
SYNC_OUTPUT = 0x1C32  # SM2 synchronisation parameters (cycle time in :02)
SYNC_INPUT = 0x1C33

# ZeroErr manufacturer objects: loop gains, SDO only (not PDO-mappable)
POS_LOOP_GAIN = (0x2382, 0x01)  # pos_reg
VEL_LOOP_GAIN = (0x2381, 0x01)  # vel_reg
VEL_LOOP_INTEGRAL = (0x2381, 0x02)  # held at 0 for a clean impedance
POS_LOOP_INTEGRAL = (0x2382, 0x02)  # position-loop integral (ZeroErr EDS V1.5); Prime leaves it alone
BUS_GAIN_GATE = (0x2383, 0x00)  # 1 = bus-written gains, 0 = factory gains (default)
# Their widths differ between sources (the EDS: gains UNSIGNED16; a public host: u32; one table: the gate
# UDINT), so they are written with the size each drive reports (drivers/ethercat/sdo.SizedSdo).


@dataclass(frozen=True)
class PdoEntry:
    index: int
    sub_index: int
    fmt: str  # struct format of one value, little-endian on the wire
    name: str

    @property
    def bits(self) -> int:
        return struct.calcsize("<" + self.fmt) * 8

    @property
    def dtype(self) -> str:
        """The NumPy field type of the entry (a pad byte is an unsigned byte the drive ignores)."""
        return "<u1" if self.fmt == "x" else "<" + self.fmt

    @property
    def mapping(self) -> int:
        """The 32-bit value of this entry in a 0x16xx/0x1Axx mapping object: index:sub:bit-length."""
        return (self.index << 16) | (self.sub_index << 8) | self.bits


# Each ends in a pad byte (mapping entry 0x00000008) to an even length, as ZeroErr's own demo and the
# drive's fixed PDOs do ("padding for alignment", eRob_pysoem_demo; 0x1605/0x1A06 end in 8 pad bits).
RXPDO: tuple[PdoEntry, ...] = (
    PdoEntry(CONTROLWORD, 0, "H", "controlword"),
    PdoEntry(TARGET_POSITION, 0, "i", "target_position"),
    PdoEntry(VELOCITY_OFFSET, 0, "i", "velocity_offset"),
    PdoEntry(TORQUE_OFFSET, 0, "h", "torque_offset"),
    PdoEntry(MODE_OF_OPERATION, 0, "b", "mode_of_operation"),
    PdoEntry(0x0000, 0, "x", "pad"),
)
TXPDO: tuple[PdoEntry, ...] = (
    PdoEntry(STATUSWORD, 0, "H", "statusword"),
    PdoEntry(POSITION_ACTUAL, 0, "i", "position_actual"),
    PdoEntry(VELOCITY_ACTUAL, 0, "i", "velocity_actual"),
    PdoEntry(TORQUE_ACTUAL, 0, "h", "torque_actual"),
    PdoEntry(ERROR_CODE, 0, "H", "error_code"),
    PdoEntry(MODE_DISPLAY, 0, "b", "mode_display"),
    PdoEntry(0x0000, 0, "x", "pad"),
)

RXPDO_STRUCT = struct.Struct("<" + "".join(e.fmt for e in RXPDO))  # 14 bytes, master -> drive
TXPDO_STRUCT = struct.Struct("<" + "".join(e.fmt for e in TXPDO))  # 16 bytes, drive -> master

# What a drive maps at power up (ZeroErr's description, DESIGN §2); Prime maps its own layout in PRE-OP.
POWER_UP_RXPDO: tuple[PdoEntry, ...] = (
    PdoEntry(TARGET_POSITION, 0, "i", "target_position"),
    PdoEntry(*DIGITAL_OUTPUTS, "I", "digital_outputs"),
    PdoEntry(CONTROLWORD, 0, "H", "controlword"),
)
POWER_UP_TXPDO: tuple[PdoEntry, ...] = (
    PdoEntry(POSITION_ACTUAL, 0, "i", "position_actual"),
    PdoEntry(DIGITAL_INPUTS, 0, "I", "digital_inputs"),
    PdoEntry(STATUSWORD, 0, "H", "statusword"),
)


def pdo_mapping_writes(assign: int, mapping: int, entries: tuple[PdoEntry, ...]) -> list[tuple[int, int, bytes]]:
    """The SDO downloads that map ``entries`` into PDO ``mapping`` and assign it to ``assign`` (in order).

    Assignment and mapping are cleared first, because a drive accepts mapping changes only while the
    PDO is neither assigned nor enabled (count 0).
    """
    writes = [(assign, 0, b"\x00"), (mapping, 0, b"\x00")]
    writes += [(mapping, sub, struct.pack("<I", e.mapping)) for sub, e in enumerate(entries, start=1)]
    writes += [(mapping, 0, bytes([len(entries)])), (assign, 1, struct.pack("<H", mapping)), (assign, 0, b"\x01")]
    return writes


MAPPING_WRITES = (pdo_mapping_writes(RXPDO_ASSIGN, RXPDO_MAP, RXPDO)
                  + pdo_mapping_writes(TXPDO_ASSIGN, TXPDO_MAP, TXPDO))
