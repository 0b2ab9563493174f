"""The SII EEPROM interface of one emulated ESC (registers 0x0500-0x050F): 0x0500 configuration, 0x0502
control/status (command in bits 8-10: 1 read, 2 write; bit 6 set: reads deliver 8 bytes; bit 15 busy; bits 11-14
errors), 0x0504 word address, 0x0508 data.

A command is carried out after ``busy_s`` (0: at once, as an emulator can): until then the status shows busy and
the data register is not yet the new data, as on a slave whose EEPROM is an I2C part of its own.
"""

from __future__ import annotations

import struct

from humanoid_prime.drivers.ethercat.wire import (
    EEPROM_BUSY,
    EEPROM_COMMAND_READ,
    EEPROM_COMMAND_SHIFT,
    EEPROM_COMMAND_WRITE,
    EEPROM_NACK,
    EEPROM_READ_8_BYTES,
    EEPROM_WRITE_ENABLE,
    REG_EEPROM_ADDRESS,
    REG_EEPROM_CONTROL,
    REG_EEPROM_DATA,
)

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
READ_BYTES = 8


class SiiEeprom:
    """The EEPROM ``image`` behind the registers in ``mem``; times are the frame times the ESC passes in."""

    def __init__(self, image: bytes, mem: bytearray, *, busy_s: float = 0.0) -> None:
        self.image = bytearray(image)
        self.mem = mem
        self.busy_ns = round(busy_s * 1e9)
        self.commands = 0
        self._pending: tuple[int, int, int] | None = None  # (due ns, control, word address)

    def power_on(self) -> None:
        self._pending = None
        _U16.pack_into(self.mem, REG_EEPROM_CONTROL, EEPROM_READ_8_BYTES)

    def command_written(self, now_ns: int) -> None:
        """The master wrote the control register: carry the command out now, or mark it busy until it is done."""
        control = _U16.unpack_from(self.mem, REG_EEPROM_CONTROL)[0]
        address = _U32.unpack_from(self.mem, REG_EEPROM_ADDRESS)[0]
        self.commands += 1
        if self.busy_ns:
            self._pending = (now_ns + self.busy_ns, control, address)
            _U16.pack_into(self.mem, REG_EEPROM_CONTROL, EEPROM_READ_8_BYTES | EEPROM_BUSY)
        else:
            self._carry_out(control, address)

    def before_read(self, now_ns: int) -> None:
        """A read of the EEPROM registers at ``now_ns``: a command whose time has come is done."""
        if self._pending is not None and now_ns >= self._pending[0]:
            _due, control, address = self._pending
            self._pending = None
            self._carry_out(control, address)

    def _carry_out(self, control: int, address: int) -> None:
        command = (control >> EEPROM_COMMAND_SHIFT) & 0x07
        status = EEPROM_READ_8_BYTES
        if command == EEPROM_COMMAND_READ:
            start = 2 * address
            data = bytes(self.image[start:start + READ_BYTES])
            self.mem[REG_EEPROM_DATA:REG_EEPROM_DATA + READ_BYTES] = data.ljust(READ_BYTES, b"\xff")
        elif command == EEPROM_COMMAND_WRITE:
            if control & EEPROM_WRITE_ENABLE and 2 * address + 2 <= len(self.image):
                self.image[2 * address:2 * address + 2] = self.mem[REG_EEPROM_DATA:REG_EEPROM_DATA + 2]
            else:
                status |= EEPROM_NACK
        elif command:
            status |= EEPROM_NACK
        _U16.pack_into(self.mem, REG_EEPROM_CONTROL, status)
